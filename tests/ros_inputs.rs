//! A real rclpy publisher -> fall-guard's ROS 2 sources: `JointState`,
//! `JointTrajectory` (published once before fall-guard starts, so only the
//! transient-local subscription can get it) and `CompressedImage` arrive in
//! the latest-value watch channels with the values rclpy sent.
//!
//! Needs the rclpy venv (`bash tests/ros/setup_venv.sh`); skipped loudly
//! without it unless FALL_GUARD_REQUIRE_ROS is set.

#[path = "ros/support.rs"]
mod support;

use std::sync::atomic::Ordering;
use std::sync::Arc;
use std::time::{Duration, Instant};

use fall_guard::msgs::{CompressedImage, Header, JointState};
use fall_guard::ros::RosNode;
use fall_guard::sources::ros::{default_topics, InputMessage, Latest, RosInputs};
use fall_guard::streams::Stamped;
use support::{domain_id, localhost_settings, rclpy_python, Peer};

// The scenario of `ros_peer.py publish` (same numbers there).
const JOINTS: [&str; 3] = ["abs_y", "abs_x", "abs_z"];
const PLAN_STAMP_NS: i64 = 1_700_000_000_250_000_000;
const PLAN_STEP_NS: i64 = 33_333_333;
const JPEG_BYTES: [u8; 10] = [0xFF, 0xD8, 0xFF, 0xE0, 0x00, 0x10, 0x4A, 0x46, 0xFF, 0xD9];

fn joint_positions(i: i64) -> [f64; 3] {
    [0.01 * i as f64, -0.5 + 0.001 * i as f64, 1.25]
}

fn stamp_ns(header: &Header) -> i64 {
    i64::from(header.stamp.sec) * 1_000_000_000 + i64::from(header.stamp.nanosec)
}

/// Waits until the channel holds a message with `seq >= n`.
async fn wait_count(
    rx: &mut Latest,
    n: u64,
    timeout: Duration,
) -> Option<Arc<Stamped<InputMessage>>> {
    let wait = rx.wait_for(|v| v.as_ref().is_some_and(|r| r.seq >= n));
    match tokio::time::timeout(timeout, wait).await {
        Ok(Ok(v)) => v.clone(),
        _ => None,
    }
}

fn joint_state(m: &Stamped<InputMessage>) -> &JointState {
    match &m.value {
        InputMessage::Joints(msg) => msg,
        other => panic!("not a JointState: {other:?}"),
    }
}

fn image(m: &Stamped<InputMessage>) -> &CompressedImage {
    match &m.value {
        InputMessage::Camera(msg) => msg,
        other => panic!("not a CompressedImage: {other:?}"),
    }
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn rclpy_inputs_arrive_in_the_watch_channels() {
    let Some(python) = rclpy_python("rclpy_inputs_arrive_in_the_watch_channels") else {
        return;
    };
    let domain = domain_id(2);
    let mut publisher = Peer::spawn(&python, domain, &["publish", "--timeout", "45"]);
    let (plan_sent, _) = publisher
        .wait_for("published", Duration::from_secs(20))
        .await;
    assert!(
        plan_sent.is_some_and(|e| e["topic"] == "/planned_trajectory"),
        "{}",
        publisher.stderr()
    );
    // Let the plan be well in the past before fall-guard even exists.
    tokio::time::sleep(Duration::from_millis(300)).await;

    let started = Instant::now();
    let mut node = RosNode::start(&localhost_settings(domain, "/", "fall_guard")).expect("node");
    let inputs = RosInputs::start(&mut node, &default_topics()).expect("subscriptions");
    let mut joints = inputs.latest.joints.clone().expect("subscribed");
    let mut plans = inputs.latest.plan.clone().expect("subscribed");
    let mut camera = inputs.latest.camera.clone().expect("subscribed");

    let timeout = Duration::from_secs(30);
    let ((js_first, js_after), (plan, plan_after), (image_first, image_after)) = tokio::join!(
        async { (wait_count(&mut joints, 1, timeout).await, started.elapsed()) },
        async { (wait_count(&mut plans, 1, timeout).await, started.elapsed()) },
        async { (wait_count(&mut camera, 1, timeout).await, started.elapsed()) },
    );
    let stderr = publisher.stderr();
    let js_first = js_first.unwrap_or_else(|| panic!("no JointState in 30 s; publisher: {stderr}"));
    let plan =
        plan.unwrap_or_else(|| panic!("no latched JointTrajectory in 30 s; publisher: {stderr}"));
    let image_first =
        image_first.unwrap_or_else(|| panic!("no CompressedImage in 30 s; publisher: {stderr}"));

    // The plan, field by field.
    let InputMessage::Plan(p) = &plan.value else {
        panic!("not a JointTrajectory: {plan:?}");
    };
    assert_eq!(stamp_ns(&p.header), PLAN_STAMP_NS);
    assert_eq!(p.header.frame_id, "base_link");
    assert_eq!(p.joint_names, JOINTS);
    assert_eq!(p.points.len(), 4);
    for (k, point) in p.points.iter().enumerate() {
        let k_f = k as f64;
        assert_eq!(point.positions, vec![0.1 * k_f, 0.2 * k_f, -0.3 * k_f]);
        assert!(point.velocities.is_empty());
        let t_ns = i64::from(point.time_from_start.sec) * 1_000_000_000
            + i64::from(point.time_from_start.nanosec);
        assert_eq!(t_ns, k as i64 * PLAN_STEP_NS);
    }
    assert_eq!(plan.seq, 1, "the plan was published once");

    // Joint states keep streaming: wait for a few more, check first and latest.
    let js_later = wait_count(&mut joints, js_first.seq + 5, timeout)
        .await
        .expect("joint states keep coming");
    for js in [&js_first, &js_later] {
        let m = joint_state(js);
        let i = (stamp_ns(&m.header) - 1_000_000_000) / 33_000_000;
        assert_eq!(stamp_ns(&m.header), 1_000_000_000 + i * 33_000_000);
        assert_eq!(m.name, JOINTS);
        assert_eq!(m.position, joint_positions(i).to_vec());
        assert_eq!(m.velocity, vec![0.5, 0.0, -0.5]);
        assert!(m.effort.is_empty());
    }
    assert!(stamp_ns(&joint_state(&js_later).header) > stamp_ns(&joint_state(&js_first).header));
    assert!(js_later.stamp_ns >= js_first.stamp_ns);

    // The image: format and bytes exactly as sent.
    let image_later = wait_count(&mut camera, image_first.seq + 3, timeout)
        .await
        .expect("images keep coming");
    for img in [&image_first, &image_later] {
        let m = image(img);
        let i = (stamp_ns(&m.header) - 1_000_000_000) / 33_000_000;
        assert_eq!(m.format, "jpeg");
        assert_eq!(m.header.frame_id, "head_camera");
        let mut expected = JPEG_BYTES.to_vec();
        expected.push((i % 256) as u8);
        assert_eq!(m.data, expected);
    }

    for (kind, undecodable) in inputs.errors.iter() {
        assert_eq!(undecodable.load(Ordering::Relaxed), 0, "{kind}");
    }
    let counts = (
        joints.borrow().as_ref().map_or(0, |r| r.seq),
        camera.borrow().as_ref().map_or(0, |r| r.seq),
    );
    eprintln!(
        "ros_inputs: domain {domain}: first JointState {js_after:?}, latched JointTrajectory \
         {plan_after:?}, first CompressedImage {image_after:?} after the Rust node started; \
         {} joint states, {} images received",
        counts.0, counts.1
    );
}
