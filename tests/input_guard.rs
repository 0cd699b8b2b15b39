//! The out-of-range guard through the daemon: the shipped networks given the
//! input ranges of a split of the fixture set (`fall-guard-lab ranges`), then
//! - a simulated training episode replays bit for bit as without ranges
//!   before its fall, given the training split's ranges (every window
//!   inside them: nothing clipped);
//! - the real walk, given the ranges of the validation split (two episodes
//!   of the dynamic gait, whose trunk sways less than the real one: the
//!   training split holds a walk of the hardware gait, the real walk's own
//!   step), is named at the first full window: under `hold` the forecast is not valid
//!   and says which input, how far out and since when, and `/diagnostics`
//!   names it; under `forecast` it is published, the excursion beside it.

mod daemon_common;

use std::path::{Path, PathBuf};

use daemon_common::*;
use fall_guard_lab::dataset::Split;
use fall_guard_lab::ranges::{run_ranges, RangesOptions};
use fall_guard_runtime::model::LoadedModel;
use fall_guard_runtime::msgs::DiagnosticArray;
use fall_guard_runtime::outputs::annotate::read_forecasts;
use fall_guard_runtime::recording::{read_topic, Recording};

const NETWORKS: [&str; 4] = ["emp", "mp", "ep", "p"];

/// The shipped networks with the ranges of the fixture set's `split`, in `dir`.
fn networks_with_ranges(dir: &Path, split: Split) {
    let episodes = match split {
        Split::Train => "4 episodes",
        _ => "2 episodes",
    };
    for name in NETWORKS {
        let message = run_ranges(&RangesOptions {
            model: in_repo(&format!("models/{name}.bpk")),
            data: in_repo("tests/fixtures"),
            split,
            out: Some(dir.join(format!("{name}.bpk"))),
        })
        .expect("ranges written");
        assert!(message.contains(episodes), "{message}");
    }
}

/// `config` (a file in the repository) with its networks taken from `dir`
/// and its recording given, plus `extra` lines in `[model]`.
fn config_on(config: &str, dir: &Path, recording: &Path, extra: &str) -> PathBuf {
    let text = std::fs::read_to_string(in_repo(config)).expect("config");
    let mut out = String::new();
    for line in text.lines() {
        let key = line.split('=').next().unwrap_or("").trim();
        match key {
            "dir" => out.push_str(&format!("dir = {:?}\n", dir.display().to_string())),
            "recording" => out.push_str(&format!(
                "recording = {:?}\n",
                recording.display().to_string()
            )),
            _ => {
                out.push_str(line);
                out.push('\n');
                if line.trim() == "[model]" {
                    out.push_str(extra);
                    out.push('\n');
                }
            }
        }
    }
    let path = dir.join(format!("{}-{}.toml", extra.len(), config.replace('/', "-")));
    std::fs::write(&path, out).expect("write config");
    path
}

fn replay(config: &Path, out: &Path) -> (Vec<Line>, String) {
    let run = fall_guard(&[
        "replay",
        "--config",
        config.to_str().expect("utf8"),
        "--max-speed",
        "--out",
        out.to_str().expect("utf8"),
    ]);
    assert!(run.status.success(), "replay failed: {}", stderr(&run));
    (parse_lines(&run.stdout), stderr(&run))
}

#[test]
fn ranges_leave_the_weights_and_a_training_episode_untouched() {
    let scratch = tempfile::tempdir().expect("tempdir");
    let dir = scratch.path();
    networks_with_ranges(dir, Split::Train);
    for name in NETWORKS {
        let shipped = LoadedModel::load(in_repo(&format!("models/{name}.bpk"))).expect("shipped");
        let ranged = LoadedModel::load(dir.join(format!("{name}.bpk"))).expect("with ranges");
        let ranges = ranged.meta.input_ranges.as_ref().expect("ranges stored");
        assert!(
            ranges.measured_on.starts_with("the train split of"),
            "{ranges:?}"
        );
        assert_eq!(ranges.joints.len(), shipped.meta.joint_names.len());
        // A shipped file may carry its own training set's ranges: they are replaced.
        let (mut without, mut shipped_meta) = (ranged.meta.clone(), shipped.meta.clone());
        without.input_ranges = None;
        shipped_meta.input_ranges = None;
        assert_eq!(without, shipped_meta, "{name}: only the ranges changed");
        let tail = |p: PathBuf| {
            let bytes = std::fs::read(p).expect("read");
            let json = u64::from_le_bytes(bytes[8..16].try_into().expect("8")) as usize;
            bytes[16 + json..].to_vec()
        };
        assert!(
            tail(in_repo(&format!("models/{name}.bpk"))) == tail(dir.join(format!("{name}.bpk"))),
            "{name}: weights copied byte for byte"
        );
    }

    // A training episode (a fall by a push at 5.0 s): every window before the fall
    // lies inside the ranges, so its forecasts are the same bits.
    let recording = in_repo("tests/fixtures/episode_00003.mcap");
    let onset = Recording::open(&recording)
        .expect("episode")
        .episode()
        .expect("episode metadata")
        .fall_onset_ns
        .expect("a falling episode");
    let shipped_dir = in_repo("models");
    let with = config_on("config/replay.toml", dir, &recording, "");
    let without_dir = scratch.path().join("shipped");
    std::fs::create_dir_all(&without_dir).expect("mkdir");
    for name in NETWORKS {
        std::fs::copy(
            shipped_dir.join(format!("{name}.bpk")),
            without_dir.join(format!("{name}.bpk")),
        )
        .expect("copy");
    }
    let without = config_on("config/replay.toml", &without_dir, &recording, "");
    let (a, b) = (dir.join("with.mcap"), dir.join("without.mcap"));
    let (lines, _) = replay(&with, &a);
    replay(&without, &b);
    let (fa, fb) = (
        read_forecasts(&a).expect("a"),
        read_forecasts(&b).expect("b"),
    );
    assert_eq!(fa.len(), fb.len());
    let mut compared = 0;
    for (((t, pa), (_, pb)), line) in fa.iter().zip(&fb).zip(&lines) {
        if *t >= onset {
            break;
        }
        let bits = |v: &[f32]| v.iter().map(|x| x.to_bits()).collect::<Vec<_>>();
        assert_eq!(bits(pa), bits(pb), "tick at {t} ns moved: {line:?}");
        assert!(!line.reason.contains("training range"), "{line:?}");
        compared += usize::from(line.valid);
    }
    // The window fills at 2 s and the fall comes at 5.0 s: 90 ticks.
    assert!(compared >= 80, "{compared} valid forecasts before the fall");
}

#[test]
fn the_real_walk_is_named_at_its_first_full_window() {
    let scratch = tempfile::tempdir().expect("tempdir");
    let dir = scratch.path();
    networks_with_ranges(dir, Split::Validation);
    let walk = in_repo("tests/fixtures/real/poppy_muffin_walk.mcap");
    let config = "tests/fixtures/real/replay.toml";

    // hold (the default): not valid from the first full window, naming why.
    let held = dir.join("held.mcap");
    let (lines, _) = replay(&config_on(config, dir, &walk, ""), &held);
    let first = lines
        .iter()
        .position(|l| !l.reason.starts_with("ring filling") && !l.reason.contains("refilling"))
        .expect("a full window");
    let line = &lines[first];
    assert!(
        line.reason
            .starts_with("inputs outside the training range: "),
        "the first full window is judged at once: {line:?}"
    );
    let names = robot_joints();
    assert!(
        names.iter().any(|n| line.reason.contains(&format!("{n} "))),
        "a joint is named: {}",
        line.reason
    );
    assert!(line.reason.contains(" deg above ") || line.reason.contains(" deg below "));
    assert!(line
        .reason
        .contains(&format!("since t={:.3} s", line.stamp_s)));
    assert!(!line.valid && line.imminent, "{line:?}");
    let forecasts = read_forecasts(&held).expect("forecasts");
    assert!(
        forecasts[first].1.iter().all(|p| p.is_nan()),
        "published as NaN"
    );
    let diagnostics = read_topic::<DiagnosticArray>(&held, "/diagnostics").expect("diagnostics");
    let inputs = status(&diagnostics.last().expect("published").1, "inputs");
    assert_eq!(inputs.level, 1, "WARN: {inputs:?}");
    let value = |key: &str| status_value(inputs, key).unwrap_or_default();
    assert!(!value("out_of_range").is_empty(), "{inputs:?}");
    assert_eq!(value("policy"), "hold");
    assert!(
        value("bounds").starts_with("measured on the validation split of"),
        "{inputs:?}"
    );
    assert!(
        inputs.message.contains("fall_imminent asserted"),
        "{}",
        inputs.message
    );

    // forecast: published, the excursion named beside it.
    let (lines, _) = replay(
        &config_on(config, dir, &walk, "out_of_range = \"forecast\""),
        &dir.join("forecast.mcap"),
    );
    let line = &lines[first];
    assert!(line.valid, "{line:?}");
    assert!(line.probabilities.iter().all(|p| (0.0..=1.0).contains(p)));
}
