//! Input streams from ROS 2: `/joint_states`, `/planned_trajectory` and
//! `/head_camera/image_raw/compressed`, each subscribed with the QoS of
//! `interfaces.md` and handed on as the latest value in a
//! `tokio::sync::watch` channel, never queued.
//!
//! Messages enter from DDS on one tokio task per topic; they leave unchanged
//! (the same `msgs.rs` structs a replay reads from MCAP, so one conversion
//! serves live and replay: the service's bridge converts them into the
//! tick's streams) wrapped in [`Received`] with the reception time and a
//! running count. Undecodable samples are counted per stream and logged once.

use std::sync::atomic::{AtomicU64, Ordering};
use std::sync::Arc;

use futures::{pin_mut, StreamExt};
use ros2_client::Subscription;
use tokio::sync::watch;

use crate::msgs::{CompressedImage, JointState, JointTrajectory};
use crate::ros::{qos, RosError, RosNode};

pub const JOINT_STATE: &str = "sensor_msgs/msg/JointState";
pub const JOINT_TRAJECTORY: &str = "trajectory_msgs/msg/JointTrajectory";
pub const COMPRESSED_IMAGE: &str = "sensor_msgs/msg/CompressedImage";

/// One message as it arrived.
#[derive(Debug, Clone, PartialEq)]
pub struct Received<T> {
    pub msg: T,
    /// System clock at reception, ns since the Unix epoch (the clock of ROS
    /// header stamps).
    pub received_ns: i64,
    /// 1 for the first message on this stream, then counting up.
    pub count: u64,
}

/// The latest message of a stream; `None` until the first one arrives.
pub type Latest<T> = watch::Receiver<Option<Arc<Received<T>>>>;

/// Which topics to subscribe to (ROS names: relative ones resolve under the
/// node namespace); `None` leaves that stream to another source (the servo
/// bus, the V4L2 camera).
#[derive(Debug, Clone, PartialEq, Eq)]
pub struct InputTopics {
    pub joint_states: Option<String>,
    pub planned_trajectory: Option<String>,
    pub camera: Option<String>,
}

impl Default for InputTopics {
    fn default() -> Self {
        InputTopics {
            joint_states: Some("joint_states".to_owned()),
            planned_trajectory: Some("planned_trajectory".to_owned()),
            camera: Some("head_camera/image_raw/compressed".to_owned()),
        }
    }
}

/// Samples per stream that arrived but could not be decoded.
#[derive(Debug, Default)]
pub struct InputErrors {
    pub joint_states: AtomicU64,
    pub planned_trajectory: AtomicU64,
    pub camera: AtomicU64,
}

/// The running subscriptions. Dropping it stops them.
pub struct RosInputs {
    pub joint_states: Option<Latest<JointState>>,
    pub planned_trajectory: Option<Latest<JointTrajectory>>,
    pub camera: Option<Latest<CompressedImage>>,
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
        let joint_states = match &topics.joint_states {
            Some(topic) => {
                let sub = subscription(node, topic, JOINT_STATE, qos::sensor_data())?;
                let (rx, task) = forward(&runtime, sub, node.resolve(topic), errors.clone(), |e| {
                    &e.joint_states
                });
                tasks.push(task);
                Some(rx)
            }
            None => None,
        };
        let planned_trajectory = match &topics.planned_trajectory {
            Some(topic) => {
                let sub = subscription(node, topic, JOINT_TRAJECTORY, qos::planned_trajectory())?;
                let (rx, task) = forward(&runtime, sub, node.resolve(topic), errors.clone(), |e| {
                    &e.planned_trajectory
                });
                tasks.push(task);
                Some(rx)
            }
            None => None,
        };
        let camera = match &topics.camera {
            Some(topic) => {
                let sub = subscription(node, topic, COMPRESSED_IMAGE, qos::sensor_data())?;
                let (rx, task) = forward(&runtime, sub, node.resolve(topic), errors.clone(), |e| {
                    &e.camera
                });
                tasks.push(task);
                Some(rx)
            }
            None => None,
        };
        Ok(RosInputs {
            joint_states,
            planned_trajectory,
            camera,
            errors,
            tasks,
        })
    }
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
    errors: Arc<InputErrors>,
    counter: fn(&InputErrors) -> &AtomicU64,
) -> (Latest<T>, tokio::task::JoinHandle<()>)
where
    T: serde::de::DeserializeOwned + Send + Sync + 'static,
{
    let (tx, rx) = watch::channel(None);
    let task = runtime.spawn(async move {
        let stream = sub.async_stream();
        pin_mut!(stream);
        let mut count = 0u64;
        while let Some(sample) = stream.next().await {
            match sample {
                Ok((msg, _info)) => {
                    count += 1;
                    if count == 1 {
                        tracing::info!(topic = %topic, "first ROS 2 message received");
                    }
                    tx.send_replace(Some(Arc::new(Received {
                        msg,
                        received_ns: crate::tick::unix_now_ns(),
                        count,
                    })));
                }
                Err(e) => {
                    if counter(&errors).fetch_add(1, Ordering::Relaxed) == 0 {
                        tracing::warn!(topic = %topic, error = %e, "undecodable ROS 2 message (further ones are only counted)");
                    }
                }
            }
        }
        tracing::warn!(topic = %topic, "ROS 2 subscription stream ended");
    });
    (rx, task)
}
