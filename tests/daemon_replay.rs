//! The daemon replays real MCAP recordings end to end (the real binary):
//! one forecast per tick once the ring is full, equal to an offline forward
//! pass over the same windows, the safety latch consistent with its
//! thresholds, the model degrading and recovering when the camera
//! stream disappears from the recording for a while, and forecasts not
//! valid (the latch asserted) from a joints gap until the window refills,
//! and a bad message inside a recording rejected at its stream's boundary
//! while the replay goes on.

mod daemon_common;

use daemon_common::*;
use fall_guard_runtime::model::{Convolutions, LoadedModel, ProjectionWeights};
use fall_guard_runtime::msgs::DiagnosticArray;
use fall_guard_runtime::recording::{read_topic, topics, Recording};
use fall_guard_runtime::window::{EpisodeTicks, Streams, WindowSpec};

fn spec() -> WindowSpec {
    WindowSpec {
        n_ticks: N_TICKS,
        max_horizon_ticks: HORIZONS_TICKS[1],
        rate_hz: RATE_HZ,
        joint_names: robot_joints(),
        frame_size: FRAME_SIZE,
    }
}

#[test]
fn replay_prints_one_forecast_per_tick_equal_to_offline_inference() {
    let scene = Scene::new("falling.mcap");
    let recording = scene.path("falling.mcap");
    write_recording(&recording, 7, true, 90);
    let (lines, _) = scene.replay_max_speed();

    let rec = Recording::open(&recording).expect("fixture reads");
    let episode = EpisodeTicks::from_recording(&rec, &spec()).expect("ticks");
    let first = episode.first_tick().expect("ticks");
    assert_eq!(lines.len(), episode.ticks.len(), "one line per tick");
    for (i, line) in lines.iter().enumerate() {
        assert_eq!(line.tick, first + i as i64, "ticks are consecutive");
        if i + 1 < N_TICKS {
            assert!(
                !line.valid,
                "tick {} valid before the ring is full",
                line.tick
            );
            assert!(line.reason.starts_with("ring filling"), "{line:?}");
            assert!(line.probabilities.is_empty());
            assert!(line.imminent, "latch asserted while the ring fills");
        } else {
            assert!(line.valid, "tick {} not valid: {}", line.tick, line.reason);
            assert_eq!(line.ablation, "EMP");
            assert_eq!(line.probabilities.len(), HORIZONS_MS.len());
            assert!(
                line.probabilities.windows(2).all(|w| w[0] <= w[1]),
                "monotone: {line:?}"
            );
        }
    }

    // The same windows, cut offline and run through the same network, its
    // input projection and trajectory convolutions held in int8 as the daemon
    // holds them by default.
    let emp = LoadedModel::load(scene.path("models/emp.fgm"))
        .expect("model")
        .with_projection(ProjectionWeights::Int8)
        .with_convolutions(Convolutions::Int8);
    for line in lines.iter().skip(N_TICKS - 1) {
        let window = episode
            .window_ending_at(line.tick, &spec(), Streams::ALL)
            .expect("offline window");
        let offline = emp
            .forecast_arrays(&window.joints, &window.plan, &window.frames)
            .expect("offline forward");
        for (printed, exact) in line.probabilities.iter().zip(&offline) {
            assert!(
                (printed - exact).abs() <= 0.00005 + 1e-6,
                "tick {}: {printed} vs {exact}",
                line.tick
            );
        }
    }

    // The latch follows its thresholds (trigger 0.6, release 0.3) at 533 ms,
    // asserted while the ring fills (no valid forecast yet).
    let mut on = true;
    for line in lines.iter().filter(|l| l.valid) {
        let p = line.probabilities[1];
        if !on && p >= 0.6 {
            on = true;
        } else if on && p < 0.3 {
            on = false;
        }
        // Rounded to 4 decimals in print: skip the ambiguous band.
        if (p - 0.6).abs() > 1e-4 && (p - 0.3).abs() > 1e-4 {
            assert_eq!(line.imminent, on, "latch at tick {}", line.tick);
        }
    }
}

/// A recording whose camera frames are 320x240 JPEGs (a camera's own size,
/// as `record` keeps them) replays to exactly the forecasts of the same
/// recording with those frames already resized to the networks' 32x32.
#[test]
fn camera_frames_of_any_size_replay_as_their_resized_frames() {
    use fall_guard_runtime::frame::{decode_compressed, encode_jpeg, encode_png, Frame};
    let scene = Scene::new("unused.mcap");
    let base = scene.path("base.mcap");
    write_recording(&base, 7, true, 60);
    let big = scene.path("big_frames.mcap");
    copy_with_images(&base, &big, |msg| {
        let small = decode_compressed(&msg.format, &msg.data, FRAME_SIZE).expect("frame");
        let (w, h) = (320u32, 240u32);
        let rgb = (0..h)
            .flat_map(|y| (0..w).map(move |x| (x, y)))
            .flat_map(|(x, y)| {
                let (sx, sy) = (x * FRAME_SIZE / w, y * FRAME_SIZE / h);
                let i = ((sy * FRAME_SIZE + sx) * 3) as usize;
                [small.rgb[i], small.rgb[i + 1], small.rgb[i + 2]]
            })
            .collect();
        let mut out = msg.clone();
        out.data = encode_jpeg(&Frame::from_rgb(w, h, rgb).expect("frame"), 90).expect("jpeg");
        out
    });
    let resized = scene.path("resized.mcap");
    copy_with_images(&big, &resized, |msg| {
        let frame = decode_compressed(&msg.format, &msg.data, FRAME_SIZE).expect("frame");
        let mut out = msg.clone();
        out.format = "png".into();
        out.data = encode_png(&frame).expect("png");
        out
    });
    let big_rec = Recording::open(&big).expect("reads");
    let first = image::load_from_memory(&big_rec.images[0].msg.data).expect("jpeg");
    assert_eq!((first.width(), first.height()), (320, 240));

    let replay = |recording: &std::path::Path| replay_recording(&scene.config, recording).0;
    let from_big = replay(&big);
    let from_resized = replay(&resized);
    assert!(
        from_big.iter().any(|l| l.valid && l.ablation == "EMP"),
        "no valid EMP forecast"
    );
    assert_eq!(from_big, from_resized);
}

/// A replay scene whose recording loses the camera from 1.5 s to 2.5 s
/// (ticks 45..75): EMP, then MP, then EMP again.
fn camera_gap_scene() -> Scene {
    let scene = Scene::new("no_camera.mcap");
    let full = scene.path("full.mcap");
    write_recording(&full, 3, false, 120);
    copy_without(
        &full,
        &scene.path("no_camera.mcap"),
        topics::HEAD_CAMERA,
        1_500_000_000,
        2_500_000_000,
    );
    scene
}

#[test]
fn camera_loss_degrades_to_mp_and_recovers_to_emp() {
    let scene = camera_gap_scene();
    let (lines, err) = scene.replay_max_speed();
    let ablation_at = |tick: i64| {
        lines
            .iter()
            .find(|l| l.tick == tick)
            .map(|l| l.ablation.clone())
    };
    assert_eq!(ablation_at(40).as_deref(), Some("EMP"));
    // Stale after 100 ms: MP from tick ~49 on, and its forecasts are valid.
    let mp: Vec<&Line> = lines.iter().filter(|l| l.ablation == "MP").collect();
    assert!(!mp.is_empty(), "no MP forecast");
    let (first_mp, last_mp) = (mp[0].tick, mp[mp.len() - 1].tick);
    assert!((45..=52).contains(&first_mp), "MP from tick {first_mp}");
    assert!(mp.iter().all(|l| l.valid), "MP forecasts must be valid");
    // Back to EMP only after a whole window of fresh frames (75 + 16).
    assert!(
        (75 + N_TICKS as i64 - 2..=75 + N_TICKS as i64 + 1).contains(&(last_mp + 1)),
        "EMP again from tick {}",
        last_mp + 1
    );
    assert_eq!(ablation_at(last_mp + 1).as_deref(), Some("EMP"));
    assert!(lines
        .iter()
        .filter(|l| l.tick > last_mp)
        .all(|l| l.ablation == "EMP" && l.valid));
    assert!(err.contains("model switch"), "switches are logged: {err}");
}

/// `[model.thresholds]`: the latch uses the pair of the network that made
/// the forecast. Defaults no untrained network reaches, and a pair for MP
/// that every probability reaches: off while EMP forecasts, on while MP
/// does, off again once EMP is back.
#[test]
fn each_network_latches_with_its_own_thresholds() {
    let scene = camera_gap_scene();
    let config = std::fs::read_to_string(&scene.config).expect("config");
    let config = config.replace(
        "trigger = 0.6\nrelease = 0.3",
        "trigger = 0.999\nrelease = 0.998",
    );
    assert!(config.contains("trigger = 0.999"), "config changed shape");
    std::fs::write(
        &scene.config,
        format!("{config}\n[model.thresholds]\nmp = [0.001, 0.0005]\n"),
    )
    .expect("config");
    let (lines, err) = scene.replay_max_speed();
    let valid = |a: &str| -> Vec<&Line> {
        lines
            .iter()
            .filter(|l| l.valid && l.ablation == a)
            .collect()
    };
    let (emp, mp) = (valid("EMP"), valid("MP"));
    assert!(!emp.is_empty() && !mp.is_empty(), "{err}");
    assert!(
        mp.iter().all(|l| l.imminent),
        "MP latches at its own trigger: {mp:?}"
    );
    assert!(
        emp.iter().all(|l| !l.imminent),
        "EMP keeps the default pair: {emp:?}"
    );
}

/// `[model].fallbacks = "when_needed"`: the fallback is loaded at its first
/// use (logged once), and every forecast is what the daemon with all
/// networks loaded at start prints.
#[test]
fn fallbacks_loaded_when_needed_forecast_as_if_loaded_at_start() {
    let scene = camera_gap_scene();
    let (at_start, at_start_log) = scene.replay_max_speed();
    assert!(!at_start_log.contains("fallback loaded at its first use"));
    let text = std::fs::read_to_string(&scene.config).expect("config");
    let lazy = text.replace(
        "release = 0.3\n",
        "release = 0.3\nfallbacks = \"when_needed\"\n",
    );
    assert_ne!(lazy, text, "config edited");
    std::fs::write(&scene.config, lazy).expect("config");
    let (when_needed, log) = scene.replay_max_speed();
    assert!(log.contains("released until it is first needed"), "{log}");
    // MP is needed once (the camera gap); EP and P never.
    assert_eq!(
        log.matches("fallback loaded at its first use").count(),
        1,
        "{log}"
    );
    assert!(log.contains("key=\"[model].mp\""), "{log}");
    assert!(when_needed.iter().any(|l| l.ablation == "MP" && l.valid));
    assert_eq!(at_start.len(), when_needed.len());
    for (a, b) in at_start.iter().zip(&when_needed) {
        assert_eq!(
            (a.tick, &a.ablation, a.valid, a.imminent),
            (b.tick, &b.ablation, b.valid, b.imminent)
        );
        assert_eq!(a.probabilities.len(), b.probabilities.len());
        for (x, y) in a.probabilities.iter().zip(&b.probabilities) {
            assert!(
                x == y || (x.is_nan() && y.is_nan()),
                "tick {}: {x} vs {y}",
                a.tick
            );
        }
    }
}

/// Writes `text` (the scene's config) with `key = "value"` added to its
/// `[model]` table.
fn set_model_key(scene: &Scene, text: &str, key: &str, value: &str) {
    let edited = text.replace(
        "release = 0.3\n",
        &format!("release = 0.3\n{key} = \"{value}\"\n"),
    );
    assert_ne!(edited, text, "config edited");
    std::fs::write(&scene.config, edited).expect("config");
}

/// Two replays of one scene under two settings: the same ticks with the
/// same networks and validity, each probability within `tolerance`; how
/// many probabilities differ at all.
fn probabilities_moved(a: &[Line], b: &[Line], tolerance: f32) -> usize {
    assert_eq!(a.len(), b.len());
    let mut moved = 0usize;
    for (a, b) in a.iter().zip(b) {
        assert_eq!(
            (a.tick, &a.ablation, a.valid),
            (b.tick, &b.ablation, b.valid)
        );
        for (x, y) in a.probabilities.iter().zip(&b.probabilities) {
            assert!((x - y).abs() < tolerance, "tick {}: {x} vs {y}", a.tick);
            moved += usize::from(x != y);
        }
    }
    moved
}

/// `[model].projection = "int8"` (the default): every network's input
/// projection held in int8 (logged at start); the daemon forecasts the
/// same ticks with the same networks and validity, each probability moved
/// a little and not left unchanged.
#[test]
fn int8_projection_forecasts_close_to_the_stored_weights() {
    let scene = camera_gap_scene();
    let text = std::fs::read_to_string(&scene.config).expect("config");
    set_model_key(&scene, &text, "projection", "as_file");
    let (stored, stored_log) = scene.replay_max_speed();
    assert!(
        stored_log.contains("projection=\"as_file\""),
        "{stored_log}"
    );
    // Without the key: int8, the default.
    std::fs::write(&scene.config, &text).expect("config");
    let (_, default_log) = scene.replay_max_speed();
    assert!(default_log.contains("projection=\"int8\""), "{default_log}");
    set_model_key(&scene, &text, "projection", "int8");
    let (quantised, log) = scene.replay_max_speed();
    assert!(log.contains("projection=\"int8\""), "{log}");
    let moved = probabilities_moved(&stored, &quantised, 0.05);
    assert!(moved > 0, "int8 changed no probability: not applied");
    assert!(quantised.iter().any(|l| l.ablation == "MP" && l.valid));
}

/// `[model].convolutions`: without the key the daemon runs `"auto"` and
/// logs what it chose on this CPU for every network (`"int8"` on x86-64
/// with AVX2); `"int8"` forecasts the same ticks with the same networks and
/// validity as `"f32"`, each probability within 0.01 and not every one
/// unchanged.
#[test]
fn int8_convolutions_forecast_close_to_f32() {
    let scene = camera_gap_scene();
    let text = std::fs::read_to_string(&scene.config).expect("config");
    set_model_key(&scene, &text, "convolutions", "f32");
    let (plain, plain_log) = scene.replay_max_speed();
    assert!(plain_log.contains("convolutions=\"f32\""), "{plain_log}");
    set_model_key(&scene, &text, "convolutions", "int8");
    let (quantised, log) = scene.replay_max_speed();
    assert!(log.contains("convolutions=\"int8\""), "{log}");
    let moved = probabilities_moved(&plain, &quantised, 0.01);
    assert!(moved > 0, "int8 changed no probability: not applied");
    assert!(quantised.iter().any(|l| l.ablation == "EMP" && l.valid));
    // Without the key: auto, resolved on this CPU and said so.
    std::fs::write(&scene.config, &text).expect("config");
    let (auto, auto_log) = scene.replay_max_speed();
    let chosen = Convolutions::Auto.resolved();
    assert!(
        auto_log.contains(&format!("convolutions=\"{}\"", chosen.name())),
        "{auto_log}"
    );
    let same_as = if chosen == Convolutions::Int8 {
        &quantised
    } else {
        &plain
    };
    assert_eq!(same_as.len(), auto.len());
    for (a, b) in same_as.iter().zip(&auto) {
        let bits = |l: &Line| {
            l.probabilities
                .iter()
                .map(|p| p.to_bits())
                .collect::<Vec<_>>()
        };
        assert_eq!(
            (a.tick, &a.ablation, a.valid, bits(a)),
            (b.tick, &b.ablation, b.valid, bits(b)),
            "auto is {}",
            chosen.name()
        );
    }
}

#[test]
fn label_marks_the_fall_onset_in_place() {
    let dir = tempfile::tempdir().expect("tempdir");
    let path = dir.path().join("walk.mcap");
    write_recording(&path, 5, false, 60);
    let out = fall_guard(&["label", path.to_str().expect("utf8"), "--fall-at", "1.5"]);
    assert!(out.status.success(), "label failed: {}", stderr(&out));
    let rec = Recording::open(&path).expect("read");
    let start = rec.start_ns().expect("messages");
    assert_eq!(
        rec.episode().expect("meta").fall_onset_ns,
        Some(start + 1_500_000_000)
    );
    let out = fall_guard(&["label", path.to_str().expect("utf8"), "--no-fall"]);
    assert!(out.status.success(), "label failed: {}", stderr(&out));
    assert_eq!(
        Recording::open(&path)
            .expect("read")
            .episode()
            .expect("meta")
            .fall_onset_ns,
        None
    );
    let out = fall_guard(&["label", path.to_str().expect("utf8"), "--fall-at", "99"]);
    assert!(!out.status.success());
    assert!(
        stderr(&out).contains("outside the recording"),
        "{}",
        stderr(&out)
    );
}

#[test]
fn joints_gap_invalidates_forecasts_until_the_window_refills() {
    let scene = Scene::new("joints_gap.mcap");
    // Thresholds no untrained network reaches: every valid forecast is below
    // release, so the latch is off whenever the forecast is valid.
    let config = std::fs::read_to_string(&scene.config).expect("config");
    std::fs::write(
        &scene.config,
        config.replace(
            "trigger = 0.6\nrelease = 0.3",
            "trigger = 0.999\nrelease = 0.998",
        ),
    )
    .expect("config");
    // Joint states gone from 2.0 s to 2.5 s (ticks 60..75): the servo bus
    // unplugged, camera and plan going on.
    write_joints_gap_recording(&scene);
    let (lines, _) = scene.replay_max_speed();
    assert!(lines.windows(2).all(|w| w[1].tick == w[0].tick + 1));

    // Valid before the gap, with the latch off.
    let before = lines.iter().find(|l| l.tick == 55).expect("tick 55");
    assert!(before.valid && !before.imminent, "{before:?}");
    // Stale joints: invalid, named, the latch asserted.
    let stale: Vec<&Line> = lines
        .iter()
        .filter(|l| l.reason.contains("joints stale"))
        .collect();
    assert!(!stale.is_empty(), "no tick with stale joints");
    let (first_stale, last_stale) = (stale[0].tick, stale[stale.len() - 1].tick);
    assert!((61..=65).contains(&first_stale), "stale from {first_stale}");
    assert_eq!(
        stale.len() as i64,
        last_stale - first_stale + 1,
        "one stale run"
    );
    // Joints back: still invalid until N fresh ticks fill the window, so the
    // first valid forecast is the one whose whole window is fresh again.
    let back = last_stale + 1;
    let first_valid = back + N_TICKS as i64 - 1;
    for line in lines.iter().filter(|l| l.tick >= first_stale) {
        if line.tick < back {
            assert!(!line.valid && line.imminent, "{line:?}");
        } else if line.tick < first_valid {
            assert!(!line.valid, "tick {} valid on held joints", line.tick);
            assert!(
                line.reason.contains("joints back, window refilling"),
                "{line:?}"
            );
            assert!(line.imminent, "latch asserted while refilling: {line:?}");
        } else {
            assert!(line.valid, "tick {} not valid: {}", line.tick, line.reason);
            assert!(!line.imminent, "latch off on a valid low forecast");
        }
    }
    assert!(lines.last().expect("lines").tick > first_valid + 5);
}

/// Latch chatter around a network switch (reported: four flips in 0.5 s
/// around P -> MP). The shipped networks on the bundled simulated
/// episodes with the camera gone (so MP, as `camera = "none"` runs) and
/// the plan lost from 1.5 s to 3.2 s: MP -> P when the plan goes stale,
/// P -> MP on the tick a fresh plan message is there again (the window's
/// plan is cut from the newest message alone: no refill), valid at once.
/// Around every switch the safety signal changes at most once per 0.5 s
/// (15 ticks).
#[test]
fn network_switches_do_not_make_the_latch_chatter() {
    let root = std::path::Path::new(env!("CARGO_MANIFEST_DIR"));
    let dir = tempfile::tempdir().expect("tempdir");
    let config = bundled_config_without_ros(dir.path());
    for episode in ["episode_00000", "episode_00003", "episode_00007"] {
        let src = root.join(format!("tests/fixtures/{episode}.mcap"));
        let t0 = Recording::open(&src).expect("fixture").joint_states[0].log_time_ns;
        let no_camera = dir.path().join(format!("{episode}_no_camera.mcap"));
        copy_without(&src, &no_camera, topics::HEAD_CAMERA, i64::MIN, i64::MAX);
        let cut = dir.path().join(format!("{episode}_plan_gap.mcap"));
        copy_without(
            &no_camera,
            &cut,
            topics::PLANNED_TRAJECTORY,
            t0 + 1_500_000_000,
            t0 + 3_200_000_000,
        );
        let (lines, _) = replay_recording(&config, &cut);
        let switches: Vec<(i64, &str)> = lines
            .windows(2)
            .filter(|w| w[0].ablation != w[1].ablation)
            .map(|w| (w[1].tick, w[1].ablation.as_str()))
            .collect();
        let names: Vec<&str> = switches.iter().map(|s| s.1).collect();
        assert!(
            names.ends_with(&["P", "MP"]),
            "{episode}: switches {switches:?}"
        );
        let (back, _) = switches[switches.len() - 1];
        let back_line = lines.iter().find(|l| l.tick == back).expect("switch tick");
        assert!(
            back_line.valid,
            "{episode}: MP back but not valid: {back_line:?}"
        );
        // The plan returns at 3.2 s: MP on the first tick whose plan
        // message is fresh again, not a window later.
        let t0_s = t0 as f64 / 1e9;
        assert!(
            back_line.stamp_s < t0_s + 3.2 + 1.1,
            "{episode}: MP back at {} s, the plan at {} s",
            back_line.stamp_s - t0_s,
            3.2
        );
        let flips: Vec<i64> = lines
            .windows(2)
            .filter(|w| w[0].imminent != w[1].imminent)
            .map(|w| w[1].tick)
            .collect();
        for (tick, _) in &switches {
            let near: Vec<i64> = flips
                .iter()
                .copied()
                .filter(|f| (f - tick).abs() <= 30)
                .collect();
            assert!(
                near.windows(2).all(|w| w[1] - w[0] >= 15),
                "{episode}: fall_imminent flips at ticks {near:?} around the switch at {tick} ({switches:?})"
            );
        }
    }
}

#[test]
fn a_bad_message_in_a_recording_is_rejected_and_the_replay_goes_on() {
    let scene = Scene::new("bad_joints.mcap");
    let clean = scene.path("clean.mcap");
    write_recording(&clean, 9, false, 120);
    // Joint state 40: CDR cut in half (does not decode); 45: a NaN angle
    // (decodes, fails the boundary's check). The file itself is sound.
    const CUT: usize = 40;
    const NAN: usize = 45;
    copy_with_joint_bytes(&clean, &scene.path("bad_joints.mcap"), |i, m| {
        let mut m = m.clone();
        if i == NAN {
            m.position[3] = f64::NAN;
        }
        let mut bytes = fall_guard_runtime::msgs::encode_cdr(&m).expect("encode");
        if i == CUT {
            bytes.truncate(bytes.len() / 2);
        }
        bytes
    });
    let replay = |recording: &str| {
        let out = scene.path(&format!("out_{recording}"));
        let run = fall_guard(&[
            "replay",
            "--config",
            scene.config.to_str().expect("utf8"),
            "--recording",
            scene.path(recording).to_str().expect("utf8"),
            "--max-speed",
            "--out",
            out.to_str().expect("utf8"),
        ]);
        assert!(run.status.success(), "replay failed: {}", stderr(&run));
        (parse_lines(&run.stdout), out)
    };
    let (want, _) = replay("clean.mcap");
    let (got, out) = replay("bad_joints.mcap");

    // The replay finishes: a forecast every tick, as many as the clean one.
    assert_eq!(
        got.iter().map(|l| l.tick).collect::<Vec<_>>(),
        want.iter().map(|l| l.tick).collect::<Vec<_>>()
    );
    // The joints stream holds its previous sample for one tick (33 ms,
    // under joints_stale_ms): every forecast stays valid. Only the windows
    // that hold a tick with a held sample differ: from the tick of joint
    // state CUT to the last window holding NAN's tick.
    let same = |a: &Line, b: &Line| {
        a.valid == b.valid
            && a.probabilities
                .iter()
                .zip(&b.probabilities)
                .all(|(x, y)| x == y || (x.is_nan() && y.is_nan()))
    };
    let differ: Vec<usize> = (0..want.len())
        .filter(|&i| !same(&want[i], &got[i]))
        .collect();
    assert!(got.iter().zip(&want).all(|(a, b)| a.valid == b.valid));
    let (first, last) = (differ[0], differ[differ.len() - 1]);
    assert!(
        first >= CUT - 1 && last < NAN + N_TICKS + 1,
        "forecasts differ at line indices {differ:?}"
    );
    assert!(
        last + 1 < want.len(),
        "no tick after the bad ones to compare"
    );

    // Both were counted at the joints boundary, per reason, on /diagnostics.
    let diagnostics = read_topic::<DiagnosticArray>(&out, "/diagnostics").expect("diagnostics");
    let (_, last_array) = diagnostics.last().expect("a diagnostics message");
    let joints = status(last_array, "joints");
    let value = |key: &str| {
        status_value(joints, key).unwrap_or_else(|| panic!("no {key} in {:?}", joints.values))
    };
    assert_eq!(value("rejected"), "2");
    assert_eq!(value("rejected_undecodable"), "1");
    assert_eq!(value("rejected_non_finite"), "1");
    assert!(
        value("last_rejection").starts_with("non_finite"),
        "{}",
        value("last_rejection")
    );
}

/// The end of a replay of a labelled fall says what the safety signal did
/// before it: asserted how far ahead, not asserted, or held throughout; a
/// recording without a fall says nothing of it.
#[test]
fn a_replayed_fall_reports_the_warnings_lead() {
    let dir = tempfile::tempdir().expect("tempdir");
    let config = bundled_config_without_ros(dir.path());
    let replay = |episode: &str| {
        replay_recording(&config, &in_repo(&format!("tests/fixtures/{episode}.mcap")))
    };

    // The ball's fall at 5.07 s (tick 152).
    let (lines, log) = replay("episode_00007");
    let said = log
        .lines()
        .find_map(|l| {
            l.split_once("the recording falls at 5.07 s: ")
                .map(|(_, r)| r)
        })
        .unwrap_or_else(|| panic!("no lead in: {log}"));
    let before: Vec<&Line> = lines.iter().filter(|l| l.tick < 152).collect();
    let last = before.last().expect("ticks before the fall");
    if let Some(rest) = said.strip_prefix("fall_imminent asserted at ") {
        // The tick it went on, and on from there to the fall.
        let at: f64 = rest.split(' ').next().expect("time").parse().expect("s");
        let lead: f64 = rest
            .split(", ")
            .nth(1)
            .and_then(|r| r.strip_suffix(" s ahead"))
            .expect("lead")
            .parse()
            .expect("s");
        assert!((at + lead - 5.07).abs() < 0.011, "{said}");
        // (A tick's stamp and its index agree within one tick.)
        let on_tick = (at * 30.0).round() as i64;
        assert!(before
            .iter()
            .filter(|l| l.tick > on_tick)
            .all(|l| l.imminent));
        assert!(before.iter().any(|l| l.tick < on_tick - 1 && !l.imminent));
    } else if said.starts_with("fall_imminent was not asserted") {
        assert!(!last.imminent);
    } else {
        assert!(
            said.starts_with("fall_imminent held from the start"),
            "{said}"
        );
        assert!(before.iter().all(|l| l.imminent));
    }

    // A walk: no fall, no lead.
    let (_, log) = replay("episode_00006");
    assert!(!log.contains("the recording falls at"), "{log}");
}
