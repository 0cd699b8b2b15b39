//! A real rclpy publisher -> fall-guard's ROS 2 source: `JointState`,
//! `JointTrajectory` (published once before fall-guard starts, so only the
//! transient-local subscription can get it) and `CompressedImage` arrive in
//! their streams' feeds, converted at the source's edge (joints and plan in
//! model order, the image as received), with the values rclpy sent.
//!
//! Needs the rclpy venv (`bash tests/ros/setup_venv.sh`); skipped loudly
//! without it unless FALL_GUARD_REQUIRE_ROS is set.

#[path = "ros/support.rs"]
mod support;

use std::sync::Arc;
use std::time::{Duration, Instant};

use fall_guard_runtime::msgs::CompressedImage;
use fall_guard_runtime::ros::RosNode;
use fall_guard_runtime::shutdown::ShutdownTrigger;
use fall_guard_runtime::sources::ros::{subscribe, CameraFeed, RosFeeds};
use fall_guard_runtime::streams::input::InputLimits;
use fall_guard_runtime::streams::sample::Sample;
use fall_guard_runtime::streams::{stream, Stamped, StreamKind, StreamTap};
use fall_guard_runtime::window::WindowSpec;
use support::{domain_id, localhost_settings, rclpy_python, Peer};

// The scenario of `ros_peer.py publish` (same numbers there).
const JOINTS: [&str; 3] = ["abs_y", "abs_x", "abs_z"];
const PLAN_STAMP_NS: i64 = 1_700_000_000_250_000_000;
const PLAN_STEP_NS: i64 = 33_333_333;
const JPEG_BYTES: [u8; 10] = [0xFF, 0xD8, 0xFF, 0xE0, 0x00, 0x10, 0x4A, 0x46, 0xFF, 0xD9];

fn joint_positions(i: i64) -> [f64; 3] {
    [0.01 * i as f64, -0.5 + 0.001 * i as f64, 1.25]
}

/// Waits until the stream's latest sample has `seq >= n`.
async fn wait_count<T>(
    tap: &mut StreamTap<T>,
    n: u64,
    timeout: Duration,
) -> Option<Arc<Stamped<T>>> {
    let wait = async {
        loop {
            if let Some(s) = tap.latest().filter(|s| s.seq >= n) {
                return Some(s);
            }
            tap.changed().await?;
        }
    };
    tokio::time::timeout(timeout, wait).await.ok().flatten()
}

fn joints(m: &Stamped<Sample>) -> &[f32] {
    match &m.value {
        Sample::Joints { positions_rad, .. } => positions_rad,
        other => panic!("not joints: {other:?}"),
    }
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn rclpy_inputs_arrive_in_their_feeds() {
    let Some(python) = rclpy_python("rclpy_inputs_arrive_in_their_feeds") else {
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
    let spec = WindowSpec {
        n_ticks: 1,
        max_horizon_ticks: 0,
        rate_hz: 30.0,
        joint_names: JOINTS.map(str::to_owned).to_vec(),
        frame_size: 0,
    };
    // The scenario's sensor stamps are near the epoch: the boundary takes
    // any past stamp here.
    let limits = InputLimits {
        max_past_ns: i64::MAX / 2,
        ..InputLimits::shapes(JOINTS.len(), 0)
    };
    let (joints_feed, mut joints_tap) = stream::<Sample>(StreamKind::Joints, limits.clone());
    let (plan_feed, mut plans) = stream::<Sample>(StreamKind::Plan, limits.clone());
    let (camera_feed, mut camera) = stream::<Arc<CompressedImage>>(StreamKind::Camera, limits);
    let topics = fall_guard_runtime::ros::TopicsConfig::default();
    let feeds = RosFeeds {
        joints: Some((topics.input(StreamKind::Joints).to_owned(), joints_feed)),
        camera: Some((
            topics.input(StreamKind::Camera).to_owned(),
            CameraFeed::Images(camera_feed),
        )),
        plan: Some((topics.input(StreamKind::Plan).to_owned(), plan_feed)),
    };
    let (trigger, shutdown) = ShutdownTrigger::new();
    let tasks = subscribe(&mut node, feeds, &spec, &shutdown).expect("subscriptions");

    let timeout = Duration::from_secs(30);
    let ((js_first, js_after), (plan, plan_after), (image_first, image_after)) = tokio::join!(
        async {
            (
                wait_count(&mut joints_tap, 1, timeout).await,
                started.elapsed(),
            )
        },
        async { (wait_count(&mut plans, 1, timeout).await, started.elapsed()) },
        async { (wait_count(&mut camera, 1, timeout).await, started.elapsed()) },
    );
    let stderr = publisher.stderr();
    let js_first = js_first.unwrap_or_else(|| panic!("no JointState in 30 s; publisher: {stderr}"));
    let plan =
        plan.unwrap_or_else(|| panic!("no latched JointTrajectory in 30 s; publisher: {stderr}"));
    let image_first =
        image_first.unwrap_or_else(|| panic!("no CompressedImage in 30 s; publisher: {stderr}"));

    // The plan, field by field, in model order (the spec's order is the
    // message's), stamped at its reception.
    let Sample::Plan { plan: p, stamp_ns } = &plan.value else {
        panic!("not a plan: {plan:?}");
    };
    assert_eq!(p.stamp_ns, PLAN_STAMP_NS);
    assert_eq!(p.n_joints, JOINTS.len());
    assert_eq!(p.times_ns.len(), 4);
    for k in 0..4 {
        let k_f = k as f64;
        assert_eq!(p.times_ns[k], PLAN_STAMP_NS + k as i64 * PLAN_STEP_NS);
        assert_eq!(
            p.positions_rad[3 * k..3 * k + 3],
            [0.1 * k_f, 0.2 * k_f, -0.3 * k_f]
        );
    }
    assert_eq!(plan.stamp_ns, *stamp_ns);
    assert!(
        *stamp_ns > PLAN_STAMP_NS,
        "a plan is stamped at its reception"
    );
    assert_eq!(plan.seq, 1, "the plan was published once");

    // Joint states keep streaming: wait for a few more, check first and latest.
    let js_later = wait_count(&mut joints_tap, js_first.seq + 5, timeout)
        .await
        .expect("joint states keep coming");
    for js in [&js_first, &js_later] {
        let i = (js.stamp_ns - 1_000_000_000) / 33_000_000;
        assert_eq!(
            js.stamp_ns,
            1_000_000_000 + i * 33_000_000,
            "the header stamp"
        );
        let expected = joint_positions(i).map(|v| v as f32);
        assert_eq!(joints(js), expected);
    }
    assert!(js_later.stamp_ns > js_first.stamp_ns);

    // The image: format and bytes exactly as sent, at its header stamp.
    let image_later = wait_count(&mut camera, image_first.seq + 3, timeout)
        .await
        .expect("images keep coming");
    for img in [&image_first, &image_later] {
        let m = &img.value;
        let i = (img.stamp_ns - 1_000_000_000) / 33_000_000;
        assert_eq!(m.header.stamp.to_ns(), img.stamp_ns);
        assert_eq!(m.format, "jpeg");
        assert_eq!(m.header.frame_id, "head_camera");
        let mut expected = JPEG_BYTES.to_vec();
        expected.push((i % 256) as u8);
        assert_eq!(m.data, expected);
    }

    for tap_stats in [joints_tap.stats(), plans.stats(), camera.stats()] {
        let s = tap_stats.snapshot();
        assert_eq!((s.errors, s.rejected), (0, 0), "{s:?}");
    }
    let counts = (
        joints_tap.latest().map_or(0, |r| r.seq),
        camera.latest().map_or(0, |r| r.seq),
    );
    // The subscriptions end on shutdown.
    trigger.fire();
    for task in tasks {
        tokio::time::timeout(Duration::from_secs(5), task)
            .await
            .expect("a subscription ends on shutdown")
            .expect("no panic");
    }
    eprintln!(
        "ros_inputs: domain {domain}: first JointState {js_after:?}, latched JointTrajectory \
         {plan_after:?}, first CompressedImage {image_after:?} after the Rust node started; \
         {} joint states, {} images received",
        counts.0, counts.1
    );
}
