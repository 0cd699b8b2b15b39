//! The forecasts of every bundled recording, bit for bit, against a committed
//! reference (`tests/fixtures/forecast_reference.json`): the daemon's path
//! (`fall-guard replay --max-speed --out`, the embedded config: EMP and its
//! fallbacks, input projection in int8, trajectory convolutions as `auto`
//! chooses, int8 on x86-64 with AVX2, where the reference is written; the
//! real walk with its own config: MP) and the offline path (`fall-guard-lab eval --recording --per-tick-out`,
//! the lab's `commands::run_eval`, called here) of each shipped network. A
//! change that moves a single bit of any forecast fails here, naming the
//! run, the first tick that moved and the largest change.
//!
//! When the shipped networks change (or a change of numerics is intended and
//! measured), write the reference again and commit it with the change:
//! `FALL_GUARD_WRITE_REFERENCE=1 cargo test --test forecast_reference`.
//! `FALL_GUARD_BIN` runs another build of the robot's binary against the
//! reference (another profile, or an earlier commit's), `FALL_GUARD_LAB_BIN`
//! another build of the lab's for the offline path.

use std::collections::BTreeMap;
use std::path::{Path, PathBuf};
use std::process::Command;

use fall_guard_lab::commands::{run_eval, EvalOptions};
use fall_guard_runtime::model::ProjectionWeights;
use fall_guard_runtime::outputs::annotate::read_forecasts;

const REFERENCE: &str = "tests/fixtures/forecast_reference.json";
/// The recording the offline path forecasts with each network.
const OFFLINE_RECORDING: &str = "tests/fixtures/episode_00007.mcap";
const NETWORKS: [&str; 4] = ["emp", "mp", "ep", "p"];

/// One run's forecasts: the tick stamps and, per tick, each probability's
/// f32 bits in hex (NaN included: the daemon publishes NaN while not valid).
#[derive(Debug, Clone, PartialEq, serde::Serialize, serde::Deserialize)]
struct Run {
    stamps_ns: Vec<i64>,
    bits: Vec<String>,
}

fn root() -> PathBuf {
    PathBuf::from(env!("CARGO_MANIFEST_DIR"))
}

fn fall_guard(args: &[&str]) {
    let bin = std::env::var_os("FALL_GUARD_BIN")
        .map(PathBuf::from)
        .unwrap_or_else(|| PathBuf::from(env!("CARGO_BIN_EXE_fall-guard")));
    run(bin, args);
}

fn run(bin: PathBuf, args: &[&str]) {
    let out = Command::new(bin)
        .args(args)
        .current_dir(root())
        .output()
        .expect("run fall-guard");
    assert!(
        out.status.success(),
        "fall-guard {args:?} failed: {}",
        String::from_utf8_lossy(&out.stderr)
    );
}

fn run_of(rows: Vec<(i64, Vec<f32>)>) -> Run {
    let stamps_ns = rows.iter().map(|(t, _)| *t).collect();
    let bits = rows
        .iter()
        .map(|(_, p)| {
            p.iter()
                .map(|v| format!("{:08x}", v.to_bits()))
                .collect::<Vec<_>>()
                .join(" ")
        })
        .collect();
    Run { stamps_ns, bits }
}

fn replay(recording: &Path, config: Option<&Path>, scratch: &Path) -> Run {
    let out = scratch.join("out.mcap");
    let mut args = vec!["replay", "--max-speed", "--quiet"];
    let (recording, out_s) = (
        recording.to_str().expect("utf8"),
        out.to_str().expect("utf8"),
    );
    args.extend(["--recording", recording, "--out", out_s]);
    if let Some(c) = config {
        args.extend(["--config", c.to_str().expect("utf8")]);
    }
    fall_guard(&args);
    run_of(read_forecasts(&out).expect("forecasts in the replay's output"))
}

fn offline(network: &str, scratch: &Path) -> Run {
    let out = scratch.join(format!("{network}.jsonl"));
    let model = format!("models/{network}.bpk");
    match std::env::var_os("FALL_GUARD_LAB_BIN") {
        Some(lab) => run(
            PathBuf::from(lab),
            &[
                "eval",
                "--model",
                &model,
                "--recording",
                OFFLINE_RECORDING,
                "--per-tick-out",
                out.to_str().expect("utf8"),
            ],
        ),
        // What `fall-guard-lab eval` runs, with its defaults.
        None => {
            let report = run_eval(&EvalOptions::per_tick(
                root().join(&model),
                root().join(OFFLINE_RECORDING),
                out.clone(),
                ProjectionWeights::AsFile,
            ))
            .expect("the offline forecasts");
            assert!(report.is_none(), "no split evaluated without --data");
        }
    }
    let text = std::fs::read_to_string(&out).expect("per-tick forecasts");
    let rows = text
        .lines()
        .map(|line| {
            let v: serde_json::Value = serde_json::from_str(line).expect("a JSON line");
            let stamp = v["stamp_ns"].as_i64().expect("stamp_ns");
            let p = v["probabilities"]
                .as_array()
                .expect("probabilities")
                .iter()
                .map(|x| x.as_f64().expect("a number") as f32)
                .collect();
            (stamp, p)
        })
        .collect();
    run_of(rows)
}

fn all_runs() -> BTreeMap<String, Run> {
    let scratch = tempfile::tempdir().expect("tempdir");
    let mut runs = BTreeMap::new();
    let fixtures = root().join("tests/fixtures");
    let mut recordings: Vec<PathBuf> = std::fs::read_dir(&fixtures)
        .expect("fixtures")
        .map(|e| e.expect("entry").path())
        .filter(|p| p.extension().is_some_and(|x| x == "mcap"))
        .collect();
    recordings.sort();
    assert!(recordings.len() >= 8, "the simulated fixtures are there");
    for rec in &recordings {
        let name = rec.file_stem().expect("name").to_string_lossy();
        runs.insert(format!("replay {name}"), replay(rec, None, scratch.path()));
    }
    let real = fixtures.join("real");
    runs.insert(
        "replay real/poppy_muffin_walk".into(),
        replay(
            &real.join("poppy_muffin_walk.mcap"),
            Some(&real.join("replay.toml")),
            scratch.path(),
        ),
    );
    for network in NETWORKS {
        runs.insert(format!("eval {network}"), offline(network, scratch.path()));
    }
    runs
}

/// Where `now` first differs from `then`, and the largest change of a
/// probability over the run.
fn describe(then: &Run, now: &Run) -> String {
    if then.stamps_ns != now.stamps_ns {
        return format!(
            "tick stamps differ: {} ticks then, {} now",
            then.stamps_ns.len(),
            now.stamps_ns.len()
        );
    }
    let parse = |s: &str| -> Vec<f32> {
        s.split_whitespace()
            .map(|h| f32::from_bits(u32::from_str_radix(h, 16).expect("hex")))
            .collect()
    };
    let mut first = None;
    let mut largest = 0.0f32;
    for (i, (a, b)) in then.bits.iter().zip(&now.bits).enumerate() {
        if a != b {
            first.get_or_insert(i);
            for (x, y) in parse(a).iter().zip(parse(b).iter()) {
                let d = (x - y).abs();
                if d.is_nan() {
                    largest = f32::NAN;
                } else if !largest.is_nan() {
                    largest = largest.max(d);
                }
            }
        }
    }
    match first {
        Some(i) => format!(
            "first at tick {} of {} (t = {} ns): {} then, {} now; largest change {largest:e}",
            i,
            then.bits.len(),
            then.stamps_ns[i],
            then.bits[i],
            now.bits[i]
        ),
        None => "equal".into(),
    }
}

#[test]
fn every_bundled_recording_forecasts_bit_for_bit_as_the_reference() {
    let runs = all_runs();
    let path = root().join(REFERENCE);
    if std::env::var_os("FALL_GUARD_WRITE_REFERENCE").is_some() {
        let text = serde_json::to_string_pretty(&runs).expect("json");
        let partial = path.with_extension("json.partial");
        std::fs::write(&partial, text + "\n").expect("write the reference");
        std::fs::rename(&partial, &path).expect("rename the reference");
        eprintln!(
            "reference written: {} runs to {}",
            runs.len(),
            path.display()
        );
        return;
    }
    let text = std::fs::read_to_string(&path).expect("the committed reference");
    let reference: BTreeMap<String, Run> = serde_json::from_str(&text).expect("reference JSON");
    assert_eq!(
        reference.keys().collect::<Vec<_>>(),
        runs.keys().collect::<Vec<_>>(),
        "the same runs as the reference"
    );
    let moved: Vec<String> = reference
        .iter()
        .filter(|(name, then)| runs[*name] != **then)
        .map(|(name, then)| format!("{name}: {}", describe(then, &runs[name])))
        .collect();
    assert!(
        moved.is_empty(),
        "forecasts moved from the reference:\n{}",
        moved.join("\n")
    );
    let valid: usize = runs
        .values()
        .flat_map(|r| &r.bits)
        .filter(|b| !b.starts_with("7fc0"))
        .count();
    assert!(
        valid > 1000,
        "the reference holds valid forecasts ({valid})"
    );
}
