//! Bad input to the real binary: a config with a wrong key or value, a
//! truncated or corrupt recording, a network trained for other joints. Each
//! gives a clear error naming the problem, a non-zero exit, and no panic.

mod daemon_common;

use daemon_common::*;

fn replay(scene: &Scene) -> std::process::Output {
    fall_guard(&[
        "replay",
        "--config",
        scene.config.to_str().expect("utf8"),
        "--max-speed",
        "--quiet",
    ])
}

fn assert_clean_failure(out: &std::process::Output, needles: &[&str]) {
    let err = stderr(out);
    assert!(!out.status.success(), "should fail: {err}");
    assert_eq!(out.status.code(), Some(1), "exit code: {err}");
    assert!(!err.contains("panicked"), "panic: {err}");
    for needle in needles {
        assert!(
            err.contains(needle),
            "error should mention {needle:?}: {err}"
        );
    }
}

#[test]
fn wrong_config_key_is_named() {
    let scene = Scene::new("x.mcap");
    let text = std::fs::read_to_string(&scene.config).expect("read");
    std::fs::write(
        &scene.config,
        text.replace("trigger = 0.6", "trigger = 0.6\ntrigerr = 0.7"),
    )
    .expect("write");
    assert_clean_failure(
        &replay(&scene),
        &["replay.toml", "[model].trigerr", "unknown field"],
    );
}

#[test]
fn wrong_config_values_are_named() {
    let scene = Scene::new("x.mcap");
    write_recording(&scene.path("x.mcap"), 1, false, 40);
    let text = std::fs::read_to_string(&scene.config).expect("read");
    std::fs::write(
        &scene.config,
        text.replace("horizon_ms = 533", "horizon_ms = 700"),
    )
    .expect("write");
    assert_clean_failure(
        &replay(&scene),
        &["[model].horizon_ms: expected one of the model's horizons 267, 533, got 700"],
    );
    std::fs::write(
        &scene.config,
        text.replace("camera = \"ros\"", "camera = \"webcam\""),
    )
    .expect("write");
    assert_clean_failure(&replay(&scene), &["[streams].camera", "webcam"]);
    std::fs::write(
        &scene.config,
        text.replace("release = 0.3", "release = 0.9"),
    )
    .expect("write");
    assert_clean_failure(&replay(&scene), &["[model].release"]);
}

#[test]
fn truncated_recording_names_the_file() {
    let scene = Scene::new("cut.mcap");
    let full = scene.path("full.mcap");
    write_recording(&full, 2, true, 60);
    let bytes = std::fs::read(&full).expect("read");
    std::fs::write(scene.path("cut.mcap"), &bytes[..bytes.len() / 2]).expect("write");
    assert_clean_failure(&replay(&scene), &["cut.mcap"]);
}

#[test]
fn corrupt_recording_names_the_file() {
    let scene = Scene::new("bad.mcap");
    let full = scene.path("full.mcap");
    write_recording(&full, 2, true, 60);
    let mut bytes = std::fs::read(&full).expect("read");
    let mid = bytes.len() / 2;
    for b in &mut bytes[mid..mid + 64] {
        *b ^= 0xA5;
    }
    std::fs::write(scene.path("bad.mcap"), &bytes).expect("write");
    assert_clean_failure(&replay(&scene), &["bad.mcap"]);
    std::fs::write(scene.path("bad.mcap"), b"this is not an mcap file").expect("write");
    assert_clean_failure(&replay(&scene), &["bad.mcap"]);
}

#[test]
fn network_for_other_joints_is_refused() {
    let scene = Scene::new("x.mcap");
    write_recording(&scene.path("x.mcap"), 1, false, 40);
    // Same sizes, joints named j00..j24: not this robot.
    let other: Vec<String> = (0..robot_joints().len())
        .map(|j| format!("j{j:02}"))
        .collect();
    write_models(&scene.path("models"), &other);
    assert_clean_failure(&replay(&scene), &["[model].emp", "emp.fgm", "joint"]);
}

#[test]
fn missing_model_file_is_named() {
    let scene = Scene::new("x.mcap");
    std::fs::remove_file(scene.path("models/mp.fgm")).expect("rm");
    assert_clean_failure(&replay(&scene), &["[model].mp", "mp.fgm"]);
}

#[test]
fn missing_recording_is_named() {
    let scene = Scene::new("nowhere.mcap");
    assert_clean_failure(&replay(&scene), &["nowhere.mcap"]);
}

#[test]
fn network_with_a_trajectory_ablation_is_refused() {
    use fall_guard_runtime::model::TrajectoryInput;
    use fall_guard_runtime::model::{
        cpu_device, save_model, Ablation, Emp, ModelConfig, ModelMeta,
    };
    let scene = Scene::new("x.mcap");
    write_recording(&scene.path("x.mcap"), 1, false, 40);
    let joints = robot_joints();
    let mut config = ModelConfig::lite(
        N_TICKS,
        joints.len(),
        HORIZONS_TICKS.to_vec(),
        FRAME_SIZE as usize,
    );
    config.trajectory = TrajectoryInput::RealPosition;
    let meta = ModelMeta::new(config.clone(), Ablation::MP, RATE_HZ, joints);
    let emp = Emp::new(&config, Ablation::MP, &cpu_device());
    save_model(&scene.path("models/mp.fgm"), &meta, &emp).expect("save model");
    assert_clean_failure(
        &replay(&scene),
        &[
            "[model].mp",
            "mp.fgm",
            "real-position",
            "--trajectory planned",
        ],
    );
}
