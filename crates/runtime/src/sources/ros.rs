//! Input streams from ROS 2: `/joint_states`, `/planned_trajectory` and
//! `/head_camera/image_raw/compressed`, each subscribed with the QoS of
//! `docs/ros.md`, converted at this edge and offered straight into its
//! stream's feed (the input boundary numbers and stamps it; nothing is
//! queued here).
//!
//! One tokio task per topic takes each message as DDS hands it over and
//! converts it with the functions a replay uses ([`Sample::joints_from_msg`],
//! [`Sample::frame_from_msg`], [`Sample::plan_from_msg`]); a
//! conversion error is offered as its typed [`Rejection`], counted at the
//! boundary. The stamp is a sensor message's header stamp (its reception
//! when the header has none) and a plan's reception, since a plan is known
//! from the moment it arrives. Samples DDS could not deserialize are the
//! stream's `dds_undecodable` count, logged once.
//!
//! `record` takes the camera's images as they came, not decoded
//! ([`CameraFeed::Images`]), with their stamps checked at the same
//! boundary.

use std::sync::Arc;

use futures::{pin_mut, StreamExt};
use ros2_client::Subscription;
use tokio::task::JoinHandle;

use crate::msgs::{CompressedImage, Header, JointState, JointTrajectory};
use crate::ros::{qos, RosError, RosNode};
use crate::shutdown::Shutdown;
use crate::streams::input::{InputLimits, Rejection, StreamValue};
use crate::streams::sample::Sample;
use crate::streams::StreamFeed;
use crate::window::WindowSpec;

pub const JOINT_STATE: &str = "sensor_msgs/msg/JointState";
pub const JOINT_TRAJECTORY: &str = "trajectory_msgs/msg/JointTrajectory";
pub const COMPRESSED_IMAGE: &str = "sensor_msgs/msg/CompressedImage";

/// Where the camera's images go.
#[derive(Debug, Clone)]
pub enum CameraFeed {
    /// Decoded to the networks' frames (`run`).
    Frames(StreamFeed<Sample>),
    /// As received, not decoded (`record`).
    Images(StreamFeed<Arc<CompressedImage>>),
}

/// The streams read from ROS 2, each with its topic (ROS names: relative
/// ones resolve under the node namespace) and the feed its messages go
/// into; `None` leaves that stream to another source (the servo bus, the
/// V4L2 camera) or to none.
#[derive(Debug, Clone, Default)]
pub struct RosFeeds {
    pub joints: Option<(String, StreamFeed<Sample>)>,
    pub camera: Option<(String, CameraFeed)>,
    pub plan: Option<(String, StreamFeed<Sample>)>,
}

/// Subscribe to the topics of `feeds` on `node` and offer what arrives,
/// converted for windows of `spec` (joint names, frame size), until
/// `shutdown`. The tasks hold the subscriptions: join them before the
/// node shuts down.
pub fn subscribe(
    node: &mut RosNode,
    feeds: RosFeeds,
    spec: &WindowSpec,
    shutdown: &Shutdown,
) -> Result<Vec<JoinHandle<()>>, RosError> {
    let runtime = tokio::runtime::Handle::try_current().map_err(|_| RosError::NoRuntime)?;
    let mut on = Subscriber {
        node,
        runtime: &runtime,
        shutdown,
    };
    let mut tasks = Vec::new();
    if let Some((topic, feed)) = feeds.joints {
        let names = spec.joint_names.clone();
        tasks.push(on.spawn(
            &topic,
            JOINT_STATE,
            qos::sensor_data(),
            feed,
            move |msg: JointState, received_ns| joints_sample(&msg, &names, received_ns),
        )?);
    }
    if let Some((topic, camera)) = feeds.camera {
        let qos = qos::sensor_data();
        tasks.push(match camera {
            CameraFeed::Frames(feed) => {
                let frame_size = spec.frame_size;
                let limits = feed.limits().clone();
                on.spawn(
                    &topic,
                    COMPRESSED_IMAGE,
                    qos,
                    feed,
                    move |msg: CompressedImage, received_ns| {
                        frame_sample(&msg, frame_size, &limits, received_ns)
                    },
                )?
            }
            CameraFeed::Images(feed) => on.spawn(
                &topic,
                COMPRESSED_IMAGE,
                qos,
                feed,
                |msg: CompressedImage, received_ns| {
                    (header_stamp(&msg.header, received_ns), Ok(Arc::new(msg)))
                },
            )?,
        });
    }
    if let Some((topic, feed)) = feeds.plan {
        let names = spec.joint_names.clone();
        tasks.push(on.spawn(
            &topic,
            JOINT_TRAJECTORY,
            qos::planned_trajectory(),
            feed,
            move |msg: JointTrajectory, received_ns| plan_sample(&msg, &names, received_ns),
        )?);
    }
    Ok(tasks)
}

/// A `JointState` in model order, at its header stamp.
pub fn joints_sample(
    msg: &JointState,
    joint_names: &[String],
    received_ns: i64,
) -> (i64, Result<Sample, Rejection>) {
    let stamp_ns = header_stamp(&msg.header, received_ns);
    let sample = Sample::joints_from_msg(msg, joint_names, stamp_ns);
    (stamp_ns, sample.map_err(|e| Rejection::from_sample(&e)))
}

/// A camera image decoded to a `frame_size` frame, at its header stamp;
/// an image too large for `limits` is rejected before it is decoded.
pub fn frame_sample(
    msg: &CompressedImage,
    frame_size: u32,
    limits: &InputLimits,
    received_ns: i64,
) -> (i64, Result<Sample, Rejection>) {
    let stamp_ns = header_stamp(&msg.header, received_ns);
    if let Err(too_large) = limits.image_size(msg.data.len()) {
        return (stamp_ns, Err(too_large));
    }
    let sample = Sample::frame_from_msg(msg, frame_size, stamp_ns);
    (stamp_ns, sample.map_err(|e| Rejection::from_sample(&e)))
}

/// A plan in model order, at its reception.
pub fn plan_sample(
    msg: &JointTrajectory,
    joint_names: &[String],
    received_ns: i64,
) -> (i64, Result<Sample, Rejection>) {
    let sample = Sample::plan_from_msg(msg, joint_names, received_ns);
    (received_ns, sample.map_err(|e| Rejection::from_sample(&e)))
}

/// A header's stamp, or `received_ns` when the sender left it zero.
fn header_stamp(header: &Header, received_ns: i64) -> i64 {
    let stamp = header.stamp.to_ns();
    if stamp > 0 {
        stamp
    } else {
        received_ns
    }
}

/// Where [`subscribe`] creates its subscriptions and runs their tasks.
struct Subscriber<'a> {
    node: &'a mut RosNode,
    runtime: &'a tokio::runtime::Handle,
    shutdown: &'a Shutdown,
}

impl Subscriber<'_> {
    /// Subscribe to `topic` (`type_name`, `qos`) and spawn the task that
    /// converts each message as it arrives (with the system clock at its
    /// reception) and offers it into `feed`, until the shutdown.
    fn spawn<M, T, F>(
        &mut self,
        topic: &str,
        type_name: &str,
        qos: ros2_client::QosProfile,
        feed: StreamFeed<T>,
        convert: F,
    ) -> Result<JoinHandle<()>, RosError>
    where
        M: serde::de::DeserializeOwned + Send + Sync + 'static,
        T: StreamValue,
        F: Fn(M, i64) -> (i64, Result<T, Rejection>) + Send + 'static,
    {
        let topic = self.node.resolve(topic);
        let t = self.node.topic(&topic, type_name, &qos)?;
        let sub: Subscription<M> = self
            .node
            .node_mut()
            .create_subscription(&t, Some(qos))
            .map_err(|e| RosError::Endpoint {
                kind: "subscription",
                topic: topic.clone(),
                reason: e.to_string(),
            })?;
        tracing::info!(topic = %topic, type_name, "ROS 2 subscription ready");
        let mut shutdown = self.shutdown.clone();
        Ok(self.runtime.spawn(async move {
            let stream = sub.async_stream();
            pin_mut!(stream);
            let mut received = 0u64;
            let mut undecodable = 0u64;
            loop {
                let next = tokio::select! {
                    next = stream.next() => next,
                    () = shutdown.recv() => return,
                };
                let Some(sample) = next else { break };
                match sample {
                    Ok((msg, _info)) => {
                        received += 1;
                        if received == 1 {
                            tracing::info!(topic = %topic, "first ROS 2 message received");
                        }
                        let (stamp_ns, value) = convert(msg, crate::clock::unix_now_ns());
                        let _ = feed.offer(stamp_ns, value);
                    }
                    Err(e) => {
                        undecodable += 1;
                        if undecodable == 1 {
                            tracing::warn!(topic = %topic, error = %e, "undecodable ROS 2 message (further ones are only counted)");
                        }
                        feed.stats().set_external(
                            undecodable,
                            vec![("dds_undecodable".into(), undecodable.to_string())],
                        );
                    }
                }
            }
            tracing::warn!(topic = %topic, "ROS 2 subscription stream ended");
            feed.stats().set_state("subscription ended");
        }))
    }
}
