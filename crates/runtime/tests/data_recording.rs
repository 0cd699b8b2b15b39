//! Recordings on disk: write, read back, damaged files, labelling.

use std::collections::BTreeMap;

use fall_guard_runtime::msgs::{Bool, CompressedImage, DiagnosticArray, Header, JointState, Time};
use fall_guard_runtime::recording::{
    label, topics, EpisodeMeta, Recording, RecordingError, RecordingWriter,
};
use fall_guard_testkit::recordings::{joint_names, learnable_episode};

fn meta() -> EpisodeMeta {
    let mut other = BTreeMap::new();
    other.insert("duration_s".to_string(), "1.5".to_string());
    EpisodeMeta {
        source: "robot".into(),
        robot: "poppy_humanoid".into(),
        rate_hz: 10.0,
        fall_onset_ns: None,
        seed: Some(4),
        sigma: Some(0.01),
        other,
    }
}

fn joint_state(t_ns: i64, v: f64) -> JointState {
    JointState {
        header: Header {
            stamp: Time::from_ns(t_ns),
            frame_id: "base".into(),
        },
        name: vec!["a".into(), "b".into()],
        position: vec![v, -v],
        velocity: vec![],
        effort: vec![0.5, 0.25],
    }
}

/// A small robot-like recording: joint states every 100 ms from t0.
fn write_small(path: &std::path::Path, t0: i64) {
    let mut w = RecordingWriter::create(path).unwrap();
    w.write_episode(&meta()).unwrap();
    for k in 0..15i64 {
        let t = t0 + k * 100_000_000;
        w.write(topics::JOINT_STATES, t, &joint_state(t, k as f64))
            .unwrap();
        if k % 5 == 0 {
            let img = CompressedImage {
                header: Header::default(),
                format: "jpeg".into(),
                data: vec![k as u8; 3],
            };
            w.write(topics::HEAD_CAMERA, t, &img).unwrap();
        }
    }
    // a topic fall-guard does not read is kept and ignored
    w.write("/diagnostics", t0, &DiagnosticArray::default())
        .unwrap();
    w.finish().unwrap();
}

#[test]
fn write_then_read_back() {
    let dir = tempfile::tempdir().unwrap();
    let path = dir.path().join("r.mcap");
    write_small(&path, 1_700_000_000_000_000_000);
    let rec = Recording::open(&path).unwrap();
    assert_eq!(rec.episode().unwrap(), &meta());
    assert_eq!(rec.joint_states.len(), 15);
    assert_eq!(
        rec.joint_states[3].msg,
        joint_state(1_700_000_000_300_000_000, 3.0)
    );
    assert_eq!(rec.joint_states[3].log_time_ns, 1_700_000_000_300_000_000);
    assert_eq!(rec.images.len(), 3);
    assert_eq!(rec.images[2].msg.data, vec![10u8; 3]);
    assert_eq!(
        rec.topics["/diagnostics"].type_name,
        "diagnostic_msgs/msg/DiagnosticArray"
    );
    assert_eq!(rec.topics[topics::JOINT_STATES].count, 15);
    assert!(rec.require_topic(topics::JOINT_STATES).is_ok());
    let err = rec.require_topic(topics::PLANNED_TRAJECTORY).unwrap_err();
    assert!(err.to_string().contains("/planned_trajectory"), "{err}");
    assert!(err.to_string().contains("r.mcap"), "{err}");
}

#[test]
fn schema_records_are_ros2msg_with_nested_definitions() {
    let dir = tempfile::tempdir().unwrap();
    let path = dir.path().join("r.mcap");
    write_small(&path, 0);
    let bytes = std::fs::read(&path).unwrap();
    let summary = mcap::Summary::read(&bytes).unwrap().unwrap();
    let js = summary
        .channels
        .values()
        .find(|c| c.topic == topics::JOINT_STATES)
        .unwrap();
    let schema = js.schema.as_ref().unwrap();
    assert_eq!(schema.name, "sensor_msgs/msg/JointState");
    assert_eq!(schema.encoding, "ros2msg");
    assert_eq!(js.message_encoding, "cdr");
    let text = std::str::from_utf8(&schema.data).unwrap();
    assert!(
        text.contains("MSG: std_msgs/Header\nbuiltin_interfaces/Time stamp"),
        "{text}"
    );
    let header = mcap::read::LinearReader::new(&bytes)
        .unwrap()
        .next()
        .unwrap()
        .unwrap();
    match header {
        mcap::records::Record::Header(h) => assert_eq!(h.profile, "ros2"),
        other => panic!("first record is {other:?}"),
    }
}

#[test]
fn truncated_and_corrupt_files_name_file_and_offset() {
    let dir = tempfile::tempdir().unwrap();
    let path = dir.path().join("r.mcap");
    write_small(&path, 0);
    let bytes = std::fs::read(&path).unwrap();

    for cut in [3usize, 100, bytes.len() / 2, bytes.len() - 9] {
        let p = dir.path().join(format!("cut{cut}.mcap"));
        std::fs::write(&p, &bytes[..cut]).unwrap();
        let err = Recording::open(&p).unwrap_err();
        assert!(
            matches!(
                err,
                RecordingError::Truncated { .. } | RecordingError::Corrupt { .. }
            ),
            "{err}"
        );
        let text = err.to_string();
        assert!(text.contains(&format!("cut{cut}.mcap")), "{text}");
        assert!(text.contains("at byte"), "{text}");
    }

    // a flipped byte inside the chunk: the chunk CRC catches it
    let mut bad = bytes.clone();
    let mid = bytes.len() / 3;
    bad[mid] ^= 0xff;
    let p = dir.path().join("flip.mcap");
    std::fs::write(&p, &bad).unwrap();
    let err = Recording::open(&p).unwrap_err();
    assert!(
        err.to_string().contains("flip.mcap") && err.to_string().contains("byte"),
        "{err}"
    );

    let p = dir.path().join("text.mcap");
    std::fs::write(&p, "not an mcap file at all").unwrap();
    let err = Recording::open(&p).unwrap_err();
    assert!(err.to_string().contains("bad magic"), "{err}");

    let err = Recording::open(dir.path().join("absent.mcap")).unwrap_err();
    assert!(
        matches!(err, RecordingError::Io { .. }) && err.to_string().contains("absent.mcap"),
        "{err}"
    );
}

#[test]
fn bad_message_bytes_are_named_with_topic_and_offset() {
    let dir = tempfile::tempdir().unwrap();
    let path = dir.path().join("r.mcap");
    let mut w = RecordingWriter::create(&path).unwrap();
    w.write_episode(&meta()).unwrap();
    w.write_cdr::<JointState>(topics::JOINT_STATES, 5, &[0, 1, 0, 0, 200, 0, 0, 0])
        .unwrap();
    w.finish().unwrap();
    let err = Recording::open(&path).unwrap_err();
    let text = err.to_string();
    assert!(matches!(err, RecordingError::Decode { .. }), "{text}");
    assert!(
        text.contains("/joint_states") && text.contains("at byte") && text.contains("r.mcap"),
        "{text}"
    );
    // A replay reads past it: the message comes back beside the recording.
    let (rec, undecodable) = Recording::open_for_replay(&path).unwrap();
    assert!(rec.joint_states.is_empty());
    assert_eq!(undecodable.len(), 1);
    assert_eq!(
        (undecodable[0].topic.as_str(), undecodable[0].log_time_ns),
        (topics::JOINT_STATES, 5)
    );
    assert!(matches!(
        undecodable[0].error,
        RecordingError::Decode { .. }
    ));
}

#[test]
fn wrong_type_on_a_known_topic_is_refused() {
    let dir = tempfile::tempdir().unwrap();
    let path = dir.path().join("r.mcap");
    let mut w = RecordingWriter::create(&path).unwrap();
    w.write(topics::JOINT_STATES, 5, &Bool { data: true })
        .unwrap();
    w.finish().unwrap();
    let err = Recording::open(&path).unwrap_err();
    assert!(matches!(err, RecordingError::WrongType { .. }), "{err}");
    assert!(err.to_string().contains("std_msgs/msg/Bool"), "{err}");
}

#[test]
fn metadata_errors_name_the_key() {
    let dir = tempfile::tempdir().unwrap();
    let path = dir.path().join("r.mcap");
    let mut w = RecordingWriter::create(&path).unwrap();
    let mut map = meta().to_map();
    map.insert("fall_onset_ns".into(), "soon".into());
    w.write_metadata("fall_guard.episode", map).unwrap();
    w.finish().unwrap();
    let err = Recording::open(&path).unwrap_err();
    assert!(
        err.to_string().contains("fall_onset_ns") && err.to_string().contains("soon"),
        "{err}"
    );

    let path = dir.path().join("none.mcap");
    let mut w = RecordingWriter::create(&path).unwrap();
    w.write(topics::JOINT_STATES, 5, &joint_state(5, 1.0))
        .unwrap();
    w.finish().unwrap();
    let rec = Recording::open(&path).unwrap();
    assert!(matches!(
        rec.episode(),
        Err(RecordingError::MissingMetadata { .. })
    ));
}

#[test]
fn label_sets_and_clears_the_fall() {
    let dir = tempfile::tempdir().unwrap();
    let path = dir.path().join("r.mcap");
    let t0 = 1_700_000_000_000_000_000;
    write_small(&path, t0);
    let before = Recording::open(&path).unwrap();

    let onset = label(&path, Some(0.75)).unwrap();
    assert_eq!(onset, Some(t0 + 750_000_000));
    let rec = Recording::open(&path).unwrap();
    assert_eq!(rec.episode().unwrap().fall_onset_ns, Some(t0 + 750_000_000));
    assert_eq!(rec.episode().unwrap().other, meta().other);
    let pairs = |r: &Recording| {
        r.joint_states
            .iter()
            .map(|m| (m.log_time_ns, m.msg.clone()))
            .collect::<Vec<_>>()
    };
    assert_eq!(pairs(&rec), pairs(&before));
    assert_eq!(rec.images.len(), before.images.len());
    assert_eq!(rec.topics["/diagnostics"].count, 1);
    let fallen: Vec<bool> = rec.fallen.iter().map(|m| m.msg.data).collect();
    assert_eq!(fallen, (0..15).map(|k| k >= 8).collect::<Vec<_>>());

    // relabel: no fall
    assert_eq!(label(&path, None).unwrap(), None);
    let rec = Recording::open(&path).unwrap();
    assert_eq!(rec.episode().unwrap().fall_onset_ns, None);
    assert_eq!(rec.fallen.len(), 15);
    assert!(rec.fallen.iter().all(|m| !m.msg.data));
    // no temp file left behind
    assert_eq!(std::fs::read_dir(dir.path()).unwrap().count(), 1);
}

#[test]
fn label_out_of_range_keeps_the_original() {
    let dir = tempfile::tempdir().unwrap();
    let path = dir.path().join("r.mcap");
    write_small(&path, 0);
    let original = std::fs::read(&path).unwrap();
    for bad in [-1.0, 99.0, f64::NAN] {
        let err = label(&path, Some(bad)).unwrap_err();
        assert!(err.to_string().contains("outside the recording"), "{err}");
        assert_eq!(std::fs::read(&path).unwrap(), original);
    }
    // a damaged file is refused and left as it was
    let cut = &original[..original.len() / 2];
    std::fs::write(&path, cut).unwrap();
    assert!(label(&path, Some(0.5)).is_err());
    assert_eq!(std::fs::read(&path).unwrap(), cut);
    assert_eq!(std::fs::read_dir(dir.path()).unwrap().count(), 1);
}

#[test]
fn synthetic_episode_matches_the_recording_contract() {
    let dir = tempfile::tempdir().unwrap();
    let path = dir.path().join("ep.mcap");
    let ep = learnable_episode(11, true, 90, &joint_names(25), 30.0, 64);
    ep.write(&path).unwrap();
    let rec = Recording::open(&path).unwrap();
    let m = rec.episode().unwrap();
    assert_eq!(
        (m.source.as_str(), m.robot.as_str(), m.rate_hz),
        ("sim", "poppy_humanoid", 30.0)
    );
    assert_eq!(m.seed, Some(11));
    assert_eq!(rec.joint_states.len(), 90);
    assert_eq!(rec.images.len(), 90);
    assert_eq!(rec.fallen.len(), 90);
    assert_eq!(rec.plans.len(), 3);
    assert_eq!(rec.start_ns(), Some(0));
    assert!(rec.images.iter().all(|i| i.msg.format == "jpeg"));
    let onset_tick = ep.fall_onset_tick.unwrap();
    assert_eq!(rec.fallen.iter().position(|b| b.msg.data), Some(onset_tick));
    assert_eq!(m.fall_onset_ns, Some(rec.fallen[onset_tick].log_time_ns));
    // the plan covers [now - 2.5 s, now + 3 s], one point per tick
    let plan = &rec.plans[1].msg;
    assert_eq!(plan.points.len(), 75 + 90 + 1);
    assert_eq!(
        plan.header.stamp.to_ns() + plan.points[75].time_from_start.to_ns(),
        rec.plans[1].log_time_ns
    );
}
