//! Input streams from ROS 2: `/joint_states`, `/planned_trajectory` and
//! `/head_camera/image_raw/compressed`, each subscribed with the QoS of
//! `docs/ros.md` and handed on as the latest value in a
//! `tokio::sync::watch` channel, never queued.
//!
//! Messages enter from DDS on one tokio task per topic; they leave unchanged
//! (the same `msgs.rs` structs a replay reads from MCAP, so one conversion
//! serves live and replay: the service's bridge converts them into the
//! tick's streams) as an [`InputMessage`] in a [`Stamped`], with the
//! reception time as its stamp and a running count as its `seq`.
//! Undecodable samples are counted per stream and logged once.
//!
//! Per stream ([`StreamKind`]): its topic ([`InputTopics`]), its type and
//! QoS ([`subscribe`]), its undecodable count ([`InputErrors`]).

use std::sync::atomic::{AtomicU64, Ordering};
use std::sync::Arc;
use std::time::Instant;

use futures::{pin_mut, StreamExt};
use ros2_client::Subscription;
use tokio::sync::watch;

use crate::msgs::{CompressedImage, JointState, JointTrajectory};
use crate::ros::{qos, RosError, RosNode};
use crate::streams::{PerStream, Stamped, StreamKind};

pub const JOINT_STATE: &str = "sensor_msgs/msg/JointState";
pub const JOINT_TRAJECTORY: &str = "trajectory_msgs/msg/JointTrajectory";
pub const COMPRESSED_IMAGE: &str = "sensor_msgs/msg/CompressedImage";

/// One message of an input stream as it arrived; the variant is the stream.
#[derive(Debug, Clone, PartialEq)]
pub enum InputMessage {
    Joints(JointState),
    Camera(CompressedImage),
    Plan(JointTrajectory),
}

impl InputMessage {
    pub fn kind(&self) -> StreamKind {
        match self {
            InputMessage::Joints(_) => StreamKind::Joints,
            InputMessage::Camera(_) => StreamKind::Camera,
            InputMessage::Plan(_) => StreamKind::Plan,
        }
    }
}

/// The latest message of a stream, stamped at reception (system clock, ns
/// since the Unix epoch: the clock of ROS header stamps) and numbered from
/// 1 (`seq`); `None` until the first one arrives.
pub type Latest = watch::Receiver<Option<Arc<Stamped<InputMessage>>>>;

/// Which topic each stream subscribes to (ROS names: relative ones resolve
/// under the node namespace); `None` leaves that stream to another source
/// (the servo bus, the V4L2 camera).
pub type InputTopics = PerStream<Option<String>>;

/// Every stream on its default topic (`[ros.topics]`, see `docs/ros.md`).
pub fn default_topics() -> InputTopics {
    let topics = crate::ros::TopicsConfig::default();
    PerStream::from_fn(|kind| Some(topics.input(kind).to_owned()))
}

/// Samples per stream that arrived but could not be decoded.
pub type InputErrors = PerStream<AtomicU64>;

/// The running subscriptions. Dropping it stops them.
pub struct RosInputs {
    /// The latest message of each subscribed stream.
    pub latest: PerStream<Option<Latest>>,
    pub errors: Arc<InputErrors>,
    tasks: Vec<tokio::task::JoinHandle<()>>,
}

impl RosInputs {
    /// Subscribes to the configured topics and spawns one forwarding task per
    /// topic on the current tokio runtime.
    pub fn start(node: &mut RosNode, topics: &InputTopics) -> Result<RosInputs, RosError> {
        let runtime = tokio::runtime::Handle::try_current().map_err(|_| RosError::NoRuntime)?;
        let errors = Arc::new(InputErrors::default());
        let mut tasks = Vec::new();
        let mut latest = PerStream::default();
        for (kind, topic) in topics.iter() {
            let Some(topic) = topic else { continue };
            let (rx, task) = subscribe(node, &runtime, kind, topic, Arc::clone(&errors))?;
            tasks.push(task);
            latest[kind] = Some(rx);
        }
        Ok(RosInputs {
            latest,
            errors,
            tasks,
        })
    }
}

/// Subscribe stream `kind` on `topic` with its message type and QoS, and
/// forward what arrives.
fn subscribe(
    node: &mut RosNode,
    runtime: &tokio::runtime::Handle,
    kind: StreamKind,
    topic: &str,
    errors: Arc<InputErrors>,
) -> Result<(Latest, tokio::task::JoinHandle<()>), RosError> {
    let resolved = node.resolve(topic);
    Ok(match kind {
        StreamKind::Joints => {
            let sub = subscription(node, topic, JOINT_STATE, qos::sensor_data())?;
            forward(runtime, sub, resolved, kind, errors, InputMessage::Joints)
        }
        StreamKind::Camera => {
            let sub = subscription(node, topic, COMPRESSED_IMAGE, qos::sensor_data())?;
            forward(runtime, sub, resolved, kind, errors, InputMessage::Camera)
        }
        StreamKind::Plan => {
            let sub = subscription(node, topic, JOINT_TRAJECTORY, qos::planned_trajectory())?;
            forward(runtime, sub, resolved, kind, errors, InputMessage::Plan)
        }
    })
}

impl Drop for RosInputs {
    fn drop(&mut self) {
        for task in &self.tasks {
            task.abort();
        }
    }
}

fn subscription<T: 'static>(
    node: &mut RosNode,
    topic: &str,
    type_name: &str,
    qos: ros2_client::QosProfile,
) -> Result<Subscription<T>, RosError> {
    let resolved = node.resolve(topic);
    let t = node.topic(topic, type_name, &qos)?;
    let sub = node
        .node_mut()
        .create_subscription(&t, Some(qos))
        .map_err(|e| RosError::Endpoint {
            kind: "subscription",
            topic: resolved.clone(),
            reason: e.to_string(),
        })?;
    tracing::info!(topic = %resolved, type_name, "ROS 2 subscription ready");
    Ok(sub)
}

fn forward<T>(
    runtime: &tokio::runtime::Handle,
    sub: Subscription<T>,
    topic: String,
    kind: StreamKind,
    errors: Arc<InputErrors>,
    message: fn(T) -> InputMessage,
) -> (Latest, tokio::task::JoinHandle<()>)
where
    T: serde::de::DeserializeOwned + Send + Sync + 'static,
{
    let (tx, rx) = watch::channel(None);
    let task = runtime.spawn(async move {
        let stream = sub.async_stream();
        pin_mut!(stream);
        let mut seq = 0u64;
        while let Some(sample) = stream.next().await {
            match sample {
                Ok((msg, _info)) => {
                    seq += 1;
                    if seq == 1 {
                        tracing::info!(topic = %topic, "first ROS 2 message received");
                    }
                    tx.send_replace(Some(Arc::new(Stamped {
                        seq,
                        stamp_ns: crate::clock::unix_now_ns(),
                        received: Instant::now(),
                        value: message(msg),
                    })));
                }
                Err(e) => {
                    if errors[kind].fetch_add(1, Ordering::Relaxed) == 0 {
                        tracing::warn!(topic = %topic, error = %e, "undecodable ROS 2 message (further ones are only counted)");
                    }
                }
            }
        }
        tracing::warn!(topic = %topic, "ROS 2 subscription stream ended");
    });
    (rx, task)
}
