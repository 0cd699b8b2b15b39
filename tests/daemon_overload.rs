//! The overload policy through the daemon: a 20 s walk replayed at real
//! time with EMP's forecasts of its first 5 s slowed by 70 ms (the test hook
//! `FALL_GUARD_TEST_SLOW_INFERENCE`, 2x the 33 ms budget). The daemon
//! publishes every tick, valid or NaN with the reason (a skipped tick
//! names itself), sets EMP aside for MP once the budget is missed
//! persistently, says so on `/diagnostics`, and returns to EMP when it tries
//! it again after 10 s within budget; slowed further (15 ticks a
//! forecast), its late ticks are not charged to MP. No timing is asserted:
//! the slowed forecasts take 2 or 15 ticks whatever the machine.

mod daemon_common;

use daemon_common::*;
use fall_guard_runtime::msgs::DiagnosticArray;
use fall_guard_runtime::outputs::annotate::read_forecasts;
use fall_guard_runtime::pipeline::inference::SLOW_INFERENCE_ENV;
use fall_guard_runtime::recording::read_topic;

/// A 20 s walk replayed at real time with the hook `slow`: its lines in
/// tick order (every tick once, checked), the log and the output recording.
fn replay_slowed(slow: &str) -> (Scene, Vec<Line>, String, std::path::PathBuf) {
    let scene = Scene::new("walk.mcap");
    let ticks = 600;
    write_recording(&scene.path("walk.mcap"), 11, false, ticks);
    let out = scene.path("out.mcap");
    let run = std::process::Command::new(env!("CARGO_BIN_EXE_fall-guard"))
        .args([
            "replay",
            "--config",
            scene.config.to_str().expect("utf8"),
            "--speed",
            "1",
            "--out",
            out.to_str().expect("utf8"),
        ])
        .current_dir(scene.dir.path())
        .env("RUST_LOG", "info")
        .env(SLOW_INFERENCE_ENV, slow)
        .output()
        .expect("run fall-guard");
    let log = stderr(&run);
    assert!(run.status.success(), "replay failed: {log}");
    let mut lines = parse_lines(&run.stdout);
    lines.sort_by_key(|l| l.tick);

    // Every tick published once: a forecast, or NaN with its reason.
    let forecasts = read_forecasts(&out).expect("forecasts");
    assert_eq!(
        forecasts.len(),
        lines.len(),
        "one forecast message per line"
    );
    let first = lines.first().expect("lines").tick;
    for (i, l) in lines.iter().enumerate() {
        assert_eq!(l.tick, first + i as i64, "every tick once: {l:?}");
    }
    assert!(lines.len() >= ticks - 2, "{} lines", lines.len());
    let skipped: Vec<&Line> = lines
        .iter()
        .filter(|l| {
            l.reason
                .starts_with("skipped: the inference of an earlier tick")
        })
        .collect();
    assert!(!skipped.is_empty(), "slowed EMP skips ticks");
    assert!(skipped
        .iter()
        .all(|l| !l.valid && l.probabilities.is_empty()));
    (scene, lines, log, out)
}

/// The networks that ran, in turn, each with the tick it started at.
fn runs(lines: &[Line]) -> Vec<(&str, i64)> {
    lines.iter().fold(Vec::new(), |mut v, l| {
        if v.last()
            .is_none_or(|(a, _): &(&str, i64)| *a != l.ablation.as_str())
        {
            v.push((l.ablation.as_str(), l.tick));
        }
        v
    })
}

#[test]
fn a_slow_network_is_set_aside_for_a_lighter_one_and_taken_back() {
    let (_scene, lines, log, out) = replay_slowed("EMP:70:150");

    // EMP, then MP while EMP is set aside, then EMP again.
    let runs = runs(&lines);
    let order: Vec<&str> = runs.iter().map(|r| r.0).collect();
    assert!(
        order.starts_with(&["EMP", "MP", "EMP"]),
        "switches {runs:?}\n{log}"
    );
    let (down, up) = (runs[1].1, runs[2].1);
    assert!(up - down >= 300, "MP for at least 10 s: {runs:?}");
    // Once back, EMP (no longer slowed) keeps its budget to the end.
    assert_eq!(order.len(), 3, "{runs:?}");
    let after: Vec<&Line> = lines.iter().filter(|l| l.tick > up + 30).collect();
    let valid = after.iter().filter(|l| l.valid).count();
    assert!(
        valid * 10 >= after.len() * 9,
        "EMP forecasts after its return: {valid} valid of {}",
        after.len()
    );
    assert!(log.contains("overload: EMP set aside"), "{log}");
    assert!(log.contains("overload: EMP tried again"), "{log}");

    // /diagnostics said why while MP ran.
    let diagnostics = read_topic::<DiagnosticArray>(&out, "/diagnostics").expect("diagnostics");
    let said = diagnostics.iter().any(|(_, d)| {
        d.status.iter().any(|s| {
            s.name.ends_with(": model")
                && s.message
                    .starts_with("overloaded: running MP (EMP set aside")
                && status_value(s, "set_aside").as_deref() == Some("EMP")
        })
    });
    assert!(said, "the model status names the overload");
}

/// EMP slowed by 500 ms (15 ticks) a forecast: the ticks skipped while its
/// last forecast finishes after it was set aside, and MP's first forecast
/// (its whole window), are not MP's misses; MP keeps its budget and is not
/// set aside in turn (the daemon does not fall through to EP and P).
#[test]
fn the_network_set_aside_does_not_charge_its_late_ticks_to_the_next() {
    let (_scene, lines, log, _out) = replay_slowed("EMP:500:150");
    let runs = runs(&lines);
    let order: Vec<&str> = runs.iter().map(|r| r.0).collect();
    assert_eq!(order, ["EMP", "MP", "EMP"], "switches {runs:?}\n{log}");
    assert!(log.contains("overload: EMP set aside"), "{log}");
    assert!(!log.contains("overload: MP set aside"), "{log}");
}
