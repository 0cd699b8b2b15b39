//! Recordings written by the Python simulator (`sim/`, tests/fixtures/) read
//! by the Rust side: metadata, topics, ground truth, windows, sampler.

use std::path::Path;

use fall_guard_lab::dataset::{Dataset, Split};
use fall_guard_lab::sampler::{SamplerConfig, WindowSampler};
use fall_guard_runtime::recording::{topics, Recording};
use fall_guard_runtime::window::{Streams, WindowSpec};

#[test]
fn python_written_fixtures_read_resample_and_sample() {
    let dir = Path::new(concat!(env!("CARGO_MANIFEST_DIR"), "/../..")).join("tests/fixtures");
    let ds = Dataset::open(&dir).unwrap();
    let first = Recording::open(&ds.paths(Split::Train)[0]).unwrap();
    let names = first.joint_states[0].msg.name.clone();
    assert_eq!(names.len(), 25);
    let spec = WindowSpec {
        n_ticks: 60,
        max_horizon_ticks: 60,
        rate_hz: 30.0,
        joint_names: names,
        frame_size: 64,
    };

    let mut falls = 0;
    let mut all = Vec::new();
    for split in Split::ALL {
        for path in ds.paths(split) {
            let rec = Recording::open(&path).unwrap();
            let meta = rec.episode().unwrap();
            assert_eq!(
                (meta.source.as_str(), meta.rate_hz),
                ("sim", 30.0),
                "{}",
                path.display()
            );
            for t in [
                topics::JOINT_STATES,
                topics::PLANNED_TRAJECTORY,
                topics::HEAD_CAMERA,
                topics::GROUND_TRUTH_FALLEN,
            ] {
                rec.require_topic(t).unwrap();
            }
            // the ground-truth topic agrees with the metadata onset
            let first_fallen = rec
                .fallen
                .iter()
                .find(|b| b.msg.data)
                .map(|b| b.log_time_ns);
            match meta.fall_onset_ns {
                Some(onset) => {
                    falls += 1;
                    assert_eq!(first_fallen, Some(onset), "{}", path.display());
                }
                None => assert_eq!(first_fallen, None, "{}", path.display()),
            }
            let fallen_after: Vec<bool> = rec.fallen.iter().map(|b| b.msg.data).collect();
            assert!(
                fallen_after.windows(2).all(|w| w[0] <= w[1]),
                "sticky: {}",
                path.display()
            );
        }
        all.extend(ds.load_split(split, &spec, Streams::ALL).unwrap());
    }
    assert!(falls > 0);
    for ep in &all {
        let first_end = ep.first_complete_end_tick(60, Streams::ALL).unwrap();
        let w = ep.window_ending_at(first_end, &spec, Streams::ALL).unwrap();
        assert!(w.joints.iter().chain(&w.plan).all(|v| v.is_finite()));
        assert!(w.frames.iter().all(|v| (0.0..=1.0).contains(v)));
        // every tick after the first has a fresh joint sample (30 Hz on a 30 Hz grid)
        let late = ep
            .ticks
            .iter()
            .skip(1)
            .filter(|t| t.age_ns.joints.is_none_or(|a| a >= 33_333_334))
            .count();
        assert_eq!(late, 0, "{}", ep.path.display());
    }
    let mut sampler =
        WindowSampler::new(&all, SamplerConfig::new(60, vec![15, 30, 45, 60]), 1).unwrap();
    for p in sampler.epoch() {
        let ep = &all[p.episode];
        assert!(ep.fall_onset_tick.is_none_or(|o| p.end_tick < o));
        ep.window_ending_at(p.end_tick, &spec, Streams::ALL)
            .unwrap();
    }
}
