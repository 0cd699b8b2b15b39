//! The first real Poppy recording through the daemon: the walk in
//! `tests/fixtures/real/` (the authors' hardware buffers from poppy-muffin,
//! converted by `python -m sim poppy-muffin`, docs/real-recordings.md),
//! replayed with the config committed next to it (no camera, joints sampled
//! at their own times, 1-235 ms apart, staleness bound 300 ms) and the
//! shipped networks. The daemon runs MP (the network the streams allow),
//! publishes one forecast per tick, valid on every tick once the window is
//! full and equal to the offline forward pass over the same windows; the
//! joint values the network reads are values the recording holds, and the
//! `/joint_states` it passes on (`replay --out`) are the recording's own.

mod daemon_common;

use std::collections::HashSet;
use std::path::{Path, PathBuf};

use daemon_common::*;
use fall_guard_runtime::model::{Convolutions, LoadedModel, ProjectionWeights};
use fall_guard_runtime::msgs::DiagnosticArray;
use fall_guard_runtime::outputs::annotate::read_forecasts;
use fall_guard_runtime::recording::{read_topic, topics, Recording};
use fall_guard_runtime::window::{EpisodeTicks, Streams};

fn fixture_dir() -> PathBuf {
    Path::new(env!("CARGO_MANIFEST_DIR")).join("tests/fixtures/real")
}

#[test]
fn the_real_walk_replays_through_mp_with_the_recordings_own_joints() {
    let dir = fixture_dir();
    let recording = dir.join("poppy_muffin_walk.mcap");
    let rec = Recording::open(&recording).expect("the real walk reads");
    let meta = rec.episode().expect("episode metadata");
    assert_eq!(meta.source, "robot");
    assert_eq!(meta.fall_onset_ns, None, "the walk did not fall");
    assert!(!rec.topics.contains_key(topics::HEAD_CAMERA), "no camera");

    let scratch = tempfile::tempdir().expect("tempdir");
    let out = scratch.path().join("annotated.mcap");
    let run = fall_guard(&[
        "replay",
        "--config",
        dir.join("replay.toml").to_str().expect("utf8"),
        "--max-speed",
        "--out",
        out.to_str().expect("utf8"),
    ]);
    let log = stderr(&run);
    assert!(run.status.success(), "replay failed: {log}");
    let lines = parse_lines(&run.stdout);

    // The same ticks and windows, cut offline with the shipped MP network's
    // spec: valid exactly from the first full window on, every one by MP.
    let mp = LoadedModel::load(Path::new(env!("CARGO_MANIFEST_DIR")).join("models/mp.bpk"))
        .expect("shipped MP network")
        .with_projection(ProjectionWeights::Int8)
        .with_convolutions(Convolutions::Int8);
    let spec = mp.meta.window_spec();
    let needs = Streams {
        joints: true,
        camera: false,
        plan: true,
    };
    let episode = EpisodeTicks::from_recording(&rec, &spec).expect("ticks");
    let first = episode.first_tick().expect("ticks");
    let first_valid = episode
        .first_complete_end_tick(spec.n_ticks, needs)
        .expect("a full window");
    assert_eq!(lines.len(), episode.ticks.len(), "one line per tick");
    assert!(lines.len() > 1000, "35.6 s at 30 Hz: {} ticks", lines.len());
    let recorded: HashSet<u32> = rec
        .joint_states
        .iter()
        .flat_map(|m| m.msg.position.iter().map(|&v| (v as f32).to_bits()))
        .collect();
    for (i, line) in lines.iter().enumerate() {
        assert_eq!(line.tick, first + i as i64, "ticks are consecutive");
        assert_eq!(line.ablation, "MP", "no camera: MP at tick {}", line.tick);
        if line.tick < first_valid {
            assert!(!line.valid && line.imminent, "{line:?}");
            continue;
        }
        // The joints never go stale (300 ms bound above the largest gap).
        assert!(line.valid, "tick {} not valid: {}", line.tick, line.reason);
        let window = episode
            .window_ending_at(line.tick, &spec, needs)
            .expect("offline window");
        assert!(
            window
                .joints
                .iter()
                .all(|v| recorded.contains(&v.to_bits())),
            "tick {}: a joint value the recording does not hold",
            line.tick
        );
        let offline = mp
            .forecast_arrays(&window.joints, &window.plan, &window.frames)
            .expect("offline forward");
        assert_eq!(line.probabilities.len(), offline.len());
        for (printed, exact) in line.probabilities.iter().zip(&offline) {
            assert!(
                (printed - exact).abs() <= 0.00005 + 1e-6,
                "tick {}: {printed} vs {exact}",
                line.tick
            );
        }
    }

    // What it published, merged into the recording: the inputs unchanged
    // (every joint state at its time), one forecast per tick (NaN while not
    // valid), and the model status naming MP.
    let annotated = Recording::open(&out).expect("replay output reads");
    assert_eq!(annotated.episode, rec.episode);
    assert_eq!(annotated.joint_states.len(), rec.joint_states.len());
    for (a, b) in annotated.joint_states.iter().zip(&rec.joint_states) {
        assert_eq!((a.log_time_ns, &a.msg), (b.log_time_ns, &b.msg));
    }
    assert_eq!(annotated.plans.len(), rec.plans.len());
    let forecasts = read_forecasts(&out).expect("forecasts");
    assert_eq!(forecasts.len(), lines.len(), "one forecast per tick");
    for ((_, values), line) in forecasts.iter().zip(&lines) {
        if line.valid {
            assert!(values.iter().all(|p| (0.0..=1.0).contains(p)));
        } else {
            assert!(values.iter().all(|p| p.is_nan()), "tick {}", line.tick);
        }
    }
    let diagnostics = read_topic::<DiagnosticArray>(&out, "/diagnostics").expect("diagnostics");
    let last = &diagnostics.last().expect("diagnostics published").1;
    let model = status(last, "model");
    let value = |key: &str| status_value(model, key);
    assert_eq!(value("active_model").as_deref(), Some("MP"), "{model:?}");
    assert_eq!(value("valid").as_deref(), Some("true"), "{model:?}");
    let joints = status(last, "joints");
    assert_eq!(joints.level, 0, "joints OK at the end: {joints:?}");
}
