//! `fall-guard replay --out`: the recording with the daemon's outputs merged
//! in, as a person opens it in Foxglove with `docs/foxglove/fall-guard.json`.
//! The inputs come out unchanged, the forecast topic carries exactly what
//! was printed (NaN while not valid), `fall_imminent` its changes, and every
//! topic the layout shows is in the file.

mod daemon_common;

use std::collections::BTreeSet;

use daemon_common::*;
use fall_guard_runtime::msgs::{Bool, DiagnosticArray};
use fall_guard_runtime::outputs::annotate::read_forecasts;
use fall_guard_runtime::recording::{read_topic, topics, Recording};

/// Every topic a panel of the layout reads (the part of a message path
/// before the first `.`), from the keys Foxglove panels use for them.
fn layout_topics() -> BTreeSet<String> {
    let path = concat!(env!("CARGO_MANIFEST_DIR"), "/docs/foxglove/fall-guard.json");
    let text = std::fs::read_to_string(path).expect("layout file");
    let layout: serde_json::Value = serde_json::from_str(&text).expect("layout is JSON");
    let mut found = BTreeSet::new();
    fn walk(v: &serde_json::Value, found: &mut BTreeSet<String>) {
        match v {
            serde_json::Value::Object(map) => {
                for (k, v) in map {
                    let is_path = matches!(
                        k.as_str(),
                        "value" | "topicPath" | "topicToRender" | "imageTopic"
                    );
                    match (is_path, v.as_str()) {
                        (true, Some(s)) if s.starts_with('/') => {
                            let topic = s.split('.').next().unwrap_or(s);
                            found.insert(topic.to_string());
                        }
                        _ => walk(v, found),
                    }
                }
            }
            serde_json::Value::Array(items) => items.iter().for_each(|i| walk(i, found)),
            _ => {}
        }
    }
    walk(&layout["configById"], &mut found);
    // Every panel named in the layout tree has a config.
    let ids: Vec<&str> = layout["configById"]
        .as_object()
        .expect("configById")
        .keys()
        .map(String::as_str)
        .collect();
    let tree = layout["layout"].to_string();
    for id in &ids {
        assert!(tree.contains(id), "panel {id} is configured but not placed");
    }
    found
}

#[test]
fn replay_out_holds_the_inputs_and_what_was_published() {
    let scene = Scene::new("falling.mcap");
    let recording = scene.path("falling.mcap");
    write_recording(&recording, 7, true, 90);
    let out = scene.path("annotated.mcap");
    let run = fall_guard(&[
        "replay",
        "--config",
        scene.config.to_str().expect("utf8"),
        "--max-speed",
        "--out",
        out.to_str().expect("utf8"),
    ]);
    assert!(run.status.success(), "replay failed: {}", stderr(&run));
    let lines = parse_lines(&run.stdout);
    assert!(!scene.path("annotated.mcap.partial").exists());

    // The inputs, unchanged.
    let input = Recording::open(&recording).expect("input");
    let annotated = Recording::open(&out).expect("output reads as a recording");
    assert_eq!(annotated.episode, input.episode);
    assert_eq!(annotated.joint_states.len(), input.joint_states.len());
    assert_eq!(annotated.images.len(), input.images.len());
    assert_eq!(annotated.plans.len(), input.plans.len());
    for (a, b) in annotated.joint_states.iter().zip(&input.joint_states) {
        assert_eq!(a.log_time_ns, b.log_time_ns);
        assert_eq!(a.msg, b.msg);
    }

    // One forecast per printed tick: NaN exactly when not valid, else the
    // printed values (printed with 4 decimals).
    let forecasts = read_forecasts(&out).expect("forecasts");
    assert_eq!(forecasts.len(), lines.len(), "one forecast per tick");
    assert!(lines.iter().any(|l| l.valid) && lines.iter().any(|l| !l.valid));
    for ((_, values), line) in forecasts.iter().zip(&lines) {
        assert_eq!(values.len(), HORIZONS_MS.len());
        if line.valid {
            for (v, p) in values.iter().zip(&line.probabilities) {
                assert!((v - p).abs() <= 0.00005 + 1e-6, "tick {}", line.tick);
            }
        } else {
            assert!(values.iter().all(|v| v.is_nan()), "tick {}", line.tick);
        }
    }
    assert!(
        forecasts.windows(2).all(|w| w[0].0 < w[1].0),
        "one per tick, in time"
    );

    // fall_imminent: the first state, then each change, as published.
    let imminent = read_topic::<Bool>(&out, "/fall_guard/fall_imminent").expect("imminent");
    let mut changes = vec![lines[0].imminent];
    for w in lines.windows(2) {
        if w[1].imminent != w[0].imminent {
            changes.push(w[1].imminent);
        }
    }
    let written: Vec<bool> = imminent.iter().map(|(_, b)| b.data).collect();
    assert_eq!(written, changes);

    // Diagnostics with the model's status (active network, validity).
    let diagnostics = read_topic::<DiagnosticArray>(&out, "/diagnostics").expect("diagnostics");
    assert!(diagnostics.len() >= 2, "{} diagnostics", diagnostics.len());
    let model = diagnostics[diagnostics.len() - 1]
        .1
        .status
        .iter()
        .find(|s| s.name.ends_with(": model"))
        .expect("model status");
    assert!(model
        .values
        .iter()
        .any(|kv| kv.key == "active_model" && kv.value == "EMP"));

    // Every topic the Foxglove layout shows is in the file.
    let layout = layout_topics();
    for wanted in [
        "/fall_guard/forecast",
        "/fall_guard/fall_imminent",
        "/diagnostics",
        topics::JOINT_STATES,
        topics::HEAD_CAMERA,
    ] {
        assert!(layout.contains(wanted), "layout does not show {wanted}");
    }
    for topic in &layout {
        assert!(
            annotated.topics.contains_key(topic),
            "layout reads {topic}, absent from the replay output ({:?})",
            annotated.topics.keys().collect::<Vec<_>>()
        );
    }
}

#[test]
fn replay_out_to_a_missing_directory_fails_clearly_and_leaves_nothing() {
    let scene = Scene::new("short.mcap");
    write_recording(&scene.path("short.mcap"), 2, false, 70);
    let out = scene.path("no_such_dir/annotated.mcap");
    let run = fall_guard(&[
        "replay",
        "--config",
        scene.config.to_str().expect("utf8"),
        "--max-speed",
        "--quiet",
        "--out",
        out.to_str().expect("utf8"),
    ]);
    assert!(!run.status.success());
    let err = stderr(&run);
    assert!(err.contains("no_such_dir"), "error names the path: {err}");
    assert!(!err.contains("panicked"), "{err}");
    assert!(!scene.path("no_such_dir").exists());
}
