//! `fall-guard bench-daemon` (the real binary) on a synthetic recording:
//! the whole pipeline on the daemon's one lifecycle, replayed in a loop at
//! maximum speed, and its report (every tick forecast, a bus subscriber
//! standing in for the publisher without ROS 2, a clean stop).

mod daemon_common;

use daemon_common::*;

#[test]
fn bench_daemon_loops_the_recording_and_reports() {
    let scene = Scene::new("walk.mcap");
    write_recording(&scene.path("walk.mcap"), 11, false, 60);
    let json = scene.path("bench.json");
    let out = fall_guard(&[
        "bench-daemon",
        "--config",
        scene.config.to_str().expect("utf8"),
        "--duration-s",
        "2",
        "--json",
        json.to_str().expect("utf8"),
    ]);
    let log = stderr(&out);
    assert!(out.status.success(), "bench-daemon failed: {log}");
    let text = std::fs::read_to_string(&json).expect("the JSON report");
    let report: serde_json::Value = serde_json::from_str(&text).expect("JSON");
    let n = |key: &str| {
        report[key]
            .as_u64()
            .unwrap_or_else(|| panic!("{key} in {text}"))
    };
    assert!(n("passes") >= 1, "{text}");
    assert!(n("ticks") >= 50, "a whole pass (60 ticks) at least: {text}");
    assert_eq!(n("ticks"), n("forecasts") + n("overruns"), "{text}");
    assert_eq!(n("overruns"), 0, "maximum speed runs in lock-step: {text}");
    assert_eq!(report["published_via"], "bus subscriber", "{text}");
    assert_eq!(report["pacing"], "max", "{text}");
    // The report also goes to stdout, and forecasts do not.
    let stdout = String::from_utf8_lossy(&out.stdout);
    assert!(stdout.contains("\"passes\""), "{stdout}");
    assert!(!stdout.contains("tick "), "no forecast lines: {stdout}");
    let errors: Vec<&str> = log.lines().filter(|l| l.contains(" ERROR ")).collect();
    assert!(errors.is_empty(), "{errors:#?}");
}

#[test]
fn bench_daemon_refuses_a_speed_that_is_not_positive() {
    let scene = Scene::new("walk.mcap");
    let out = fall_guard(&[
        "bench-daemon",
        "--config",
        scene.config.to_str().expect("utf8"),
        "--speed",
        "0",
    ]);
    assert!(!out.status.success());
    let err = stderr(&out);
    assert!(err.contains("--speed"), "{err}");
    assert!(!err.contains("panicked"), "{err}");
}
