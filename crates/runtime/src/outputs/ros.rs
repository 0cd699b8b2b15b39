//! What the daemon publishes on ROS 2: the forecast every tick, the latched
//! safety signal, `/diagnostics` and, when the daemon owns the servo bus,
//! `/joint_states`.
//!
//! Values enter as plain Rust from the service (probabilities per horizon, a
//! bool, a [`DiagnosticsSnapshot`], a `JointState`; the service's bridge reads them
//! off its output bus); they leave as the standard messages of
//! `docs/ros.md` with the QoS of [`crate::ros::qos`]. Publishing never
//! blocks: a reliable send window that is full fails at once and is counted,
//! the next tick carries a newer value.
//!
//! The forecast is a `std_msgs/Float32MultiArray` with one dimension,
//! `layout.dim[0] = {label: "horizon_ms", size: K, stride: K}`, and
//! `data[k]` = fall probability within horizon k. Which horizon k is, in
//! milliseconds, is published once, latched (transient local), on
//! `fall_guard/horizons_ms`: a `Float32MultiArray` with the same layout whose
//! `data[k]` is horizon k in ms. A subscriber reads it once (it arrives even
//! when the subscriber starts late) and then indexes the forecasts.

use std::sync::atomic::{AtomicU64, Ordering};
use std::sync::Mutex;

use ros2_client::Publisher;

use crate::msgs::{
    Bool, DiagnosticArray, DiagnosticStatus, Float32MultiArray, Header, JointState, KeyValue,
    MultiArrayDimension, MultiArrayLayout, Time,
};
use crate::outputs::{
    CounterWindow, DeviceDiagnostics, DiagnosticLevel, DiagnosticsSnapshot, ERROR_WINDOW_S,
};
use crate::ros::{qos, RosError, RosNode};

/// `layout.dim[0].label` of the forecast and of the horizons topic.
pub const HORIZON_DIM_LABEL: &str = "horizon_ms";

/// ROS type names of what this module publishes.
pub const FLOAT32_MULTI_ARRAY: &str = "std_msgs/msg/Float32MultiArray";
pub const BOOL: &str = "std_msgs/msg/Bool";
pub const DIAGNOSTIC_ARRAY: &str = "diagnostic_msgs/msg/DiagnosticArray";
pub const JOINT_STATE: &str = "sensor_msgs/msg/JointState";

/// Topic names (ROS names: relative ones resolve under the node namespace).
#[derive(Debug, Clone, PartialEq, Eq)]
pub struct OutputTopics {
    pub forecast: String,
    pub horizons_ms: String,
    pub fall_imminent: String,
    pub diagnostics: String,
    /// `Some` when the daemon reads the servos itself and republishes them.
    pub joint_states: Option<String>,
}

impl Default for OutputTopics {
    fn default() -> Self {
        OutputTopics {
            forecast: "fall_guard/forecast".to_owned(),
            horizons_ms: "fall_guard/horizons_ms".to_owned(),
            fall_imminent: "fall_guard/fall_imminent".to_owned(),
            // diagnostic_aggregator listens on the absolute name.
            diagnostics: "/diagnostics".to_owned(),
            joint_states: None,
        }
    }
}

/// Counters of what could not be sent (a full reliable window, a closed participant).
#[derive(Debug, Default)]
pub struct PublishFailures {
    pub forecast: AtomicU64,
    pub fall_imminent: AtomicU64,
    pub diagnostics: AtomicU64,
    pub joint_states: AtomicU64,
}

/// The daemon's publishers. Create once after [`RosNode::start`]; the
/// methods are synchronous and cheap, callable from the tick loop.
pub struct RosOutputs {
    forecast: Publisher<Float32MultiArray>,
    fall_imminent: Publisher<Bool>,
    diagnostics: Publisher<DiagnosticArray>,
    joint_states: Option<Publisher<JointState>>,
    // Kept alive so that late joiners keep receiving the latched horizons.
    _horizons: Publisher<Float32MultiArray>,
    horizons_ms: Vec<f32>,
    topics: ResolvedTopics,
    /// Name prefix of every DiagnosticStatus, ROS style `node: stream`.
    status_prefix: String,
    pub failures: PublishFailures,
    /// Failure totals at past `/diagnostics` reports (tick time), for the
    /// figures over the last [`ERROR_WINDOW_S`].
    failure_history: Mutex<CounterWindow<i64, [u64; 4]>>,
}

#[derive(Debug, Clone)]
struct ResolvedTopics {
    forecast: String,
    fall_imminent: String,
    diagnostics: String,
    joint_states: String,
}

impl RosOutputs {
    /// Creates the publishers and publishes the latched horizons.
    /// `horizons_ms` are the model's horizons in milliseconds, in the order
    /// of the probabilities passed to [`RosOutputs::publish_forecast`].
    pub fn new(
        node: &mut RosNode,
        topics: &OutputTopics,
        horizons_ms: &[f32],
    ) -> Result<RosOutputs, RosError> {
        let forecast = publisher(node, &topics.forecast, FLOAT32_MULTI_ARRAY, qos::forecast())?;
        let horizons = publisher(
            node,
            &topics.horizons_ms,
            FLOAT32_MULTI_ARRAY,
            qos::horizons(),
        )?;
        let fall_imminent = publisher(node, &topics.fall_imminent, BOOL, qos::fall_imminent())?;
        let diagnostics = publisher(
            node,
            &topics.diagnostics,
            DIAGNOSTIC_ARRAY,
            qos::diagnostics(),
        )?;
        let joint_states = match &topics.joint_states {
            Some(t) => Some(publisher(node, t, JOINT_STATE, qos::sensor_data())?),
            None => None,
        };
        horizons
            .publish(forecast_message(horizons_ms))
            .map_err(|e| RosError::Publish {
                topic: node.resolve(&topics.horizons_ms),
                reason: e.to_string(),
            })?;
        let resolved = ResolvedTopics {
            forecast: node.resolve(&topics.forecast),
            fall_imminent: node.resolve(&topics.fall_imminent),
            diagnostics: node.resolve(&topics.diagnostics),
            joint_states: topics
                .joint_states
                .as_deref()
                .map(|t| node.resolve(t))
                .unwrap_or_default(),
        };
        tracing::info!(
            forecast = %resolved.forecast,
            fall_imminent = %resolved.fall_imminent,
            diagnostics = %resolved.diagnostics,
            horizons_ms = ?horizons_ms,
            "ROS 2 publishers ready"
        );
        Ok(RosOutputs {
            forecast,
            fall_imminent,
            diagnostics,
            joint_states,
            _horizons: horizons,
            horizons_ms: horizons_ms.to_vec(),
            topics: resolved,
            status_prefix: node.settings().node_name.clone(),
            failures: PublishFailures::default(),
            failure_history: Mutex::new(CounterWindow::default()),
        })
    }

    pub fn horizons_ms(&self) -> &[f32] {
        &self.horizons_ms
    }

    /// Publishes one forecast: `probabilities[k]` for horizon k.
    pub fn publish_forecast(&self, probabilities: &[f32]) -> Result<(), RosError> {
        if probabilities.len() != self.horizons_ms.len() {
            return Err(RosError::Publish {
                topic: self.topics.forecast.clone(),
                reason: format!(
                    "{} probabilities for {} horizons",
                    probabilities.len(),
                    self.horizons_ms.len()
                ),
            });
        }
        let result = self.forecast.publish(forecast_message(probabilities));
        count(result, &self.failures.forecast, &self.topics.forecast)
    }

    /// Publishes the safety signal (latched: late subscribers get the last
    /// value). Publish it on change; the latch keeps it for late joiners.
    pub fn publish_fall_imminent(&self, imminent: bool) -> Result<(), RosError> {
        let result = self.fall_imminent.publish(Bool { data: imminent });
        count(
            result,
            &self.failures.fall_imminent,
            &self.topics.fall_imminent,
        )
    }

    /// Publishes one `/diagnostics` report: the snapshot's statuses, names
    /// prefixed with the node name.
    /// A `fall_guard: publishers` status is added after the devices: the
    /// publish failures per topic, in the last [`ERROR_WINDOW_S`] and since
    /// start.
    pub fn publish_diagnostics(&self, snapshot: &DiagnosticsSnapshot) -> Result<(), RosError> {
        let mut snapshot = snapshot.clone();
        snapshot
            .devices
            .push(self.publishers_status(snapshot.stamp_ns, &snapshot.hardware_id));
        let msg = diagnostic_array(&self.status_prefix, &snapshot);
        let result = self.diagnostics.publish(msg);
        count(result, &self.failures.diagnostics, &self.topics.diagnostics)
    }

    /// The publish failures as a device status, at tick time `stamp_ns`.
    fn publishers_status(&self, stamp_ns: i64, hardware_id: &str) -> DeviceDiagnostics {
        let f = &self.failures;
        let now = [
            &f.forecast,
            &f.fall_imminent,
            &f.diagnostics,
            &f.joint_states,
        ]
        .map(|c| c.load(Ordering::Relaxed));
        let window_ns = ERROR_WINDOW_S as i64 * 1_000_000_000;
        let mut history = self
            .failure_history
            .lock()
            .unwrap_or_else(|e| e.into_inner());
        history.push(stamp_ns, window_ns, now);
        // All failures since start while the run is younger than the window.
        let base = history
            .window_start(stamp_ns, window_ns)
            .map_or([0; 4], |&(_, totals)| totals);
        let recent: [u64; 4] = std::array::from_fn(|i| now[i].saturating_sub(base[i]));
        let t = &self.topics;
        let topics = [
            t.forecast.as_str(),
            t.fall_imminent.as_str(),
            t.diagnostics.as_str(),
            t.joint_states.as_str(),
        ];
        publishers_status(&topics, &now, &recent, hardware_id)
    }

    /// Republishes a servo read; a no-op when no `joint_states` topic was configured.
    pub fn publish_joint_states(&self, msg: JointState) -> Result<(), RosError> {
        match &self.joint_states {
            Some(p) => count(
                p.publish(msg),
                &self.failures.joint_states,
                &self.topics.joint_states,
            ),
            None => Ok(()),
        }
    }
}

fn publisher<M: serde::Serialize>(
    node: &mut RosNode,
    topic: &str,
    type_name: &str,
    qos: ros2_client::QosProfile,
) -> Result<Publisher<M>, RosError> {
    let t = node.publisher_topic(topic, type_name, &qos)?;
    let resolved = node.resolve(topic);
    node.node_mut()
        .create_publisher(&t, Some(qos))
        .map_err(|e| RosError::Endpoint {
            kind: "publisher",
            topic: resolved,
            reason: e.to_string(),
        })
}

fn count<M>(
    result: Result<(), ros2_client::ros2::WriteError<M>>,
    failures: &AtomicU64,
    topic: &str,
) -> Result<(), RosError> {
    result.map_err(|e| {
        if failures.fetch_add(1, Ordering::Relaxed) == 0 {
            tracing::warn!(topic, error = %e, "ROS 2 publish failed (further failures are only counted)");
        }
        RosError::Publish {
            topic: topic.to_owned(),
            reason: e.to_string(),
        }
    })
}

/// The forecast message (also the horizons message): one `horizon_ms`
/// dimension of `values.len()` entries.
pub fn forecast_message(values: &[f32]) -> Float32MultiArray {
    let k = u32::try_from(values.len()).unwrap_or(u32::MAX);
    Float32MultiArray {
        layout: MultiArrayLayout {
            dim: vec![MultiArrayDimension {
                label: HORIZON_DIM_LABEL.to_owned(),
                size: k,
                stride: k,
            }],
            data_offset: 0,
        },
        data: values.to_vec(),
    }
}

/// `builtin_interfaces/Time` from ns since the epoch (negative ns round down).
pub fn ros_time(stamp_ns: i64) -> Time {
    let sec = stamp_ns.div_euclid(1_000_000_000);
    let nanosec = stamp_ns.rem_euclid(1_000_000_000) as u32;
    Time {
        sec: i32::try_from(sec).unwrap_or(if sec < 0 { i32::MIN } else { i32::MAX }),
        nanosec,
    }
}

/// The `publishers` status: OK, or WARN while a publish failed in the last
/// [`ERROR_WINDOW_S`] (a full reliable send window: a subscriber that does
/// not acknowledge). `topics[i]` has `totals[i]` failures since start,
/// `recent[i]` in the window; a topic with no name (no `/joint_states`
/// output) is left out.
pub fn publishers_status(
    topics: &[&str],
    totals: &[u64],
    recent: &[u64],
    hardware_id: &str,
) -> DeviceDiagnostics {
    let mut values = Vec::new();
    let mut failing = Vec::new();
    for ((topic, total), recent) in topics.iter().zip(totals).zip(recent) {
        if topic.is_empty() {
            continue;
        }
        values.push((format!("failures_in_window {topic}"), recent.to_string()));
        values.push((format!("failures {topic}"), total.to_string()));
        if *recent > 0 {
            failing.push(format!("{topic}: {recent}"));
        }
    }
    values.push(("error_window_s".to_string(), ERROR_WINDOW_S.to_string()));
    let (level, message) = if failing.is_empty() {
        (DiagnosticLevel::Ok, "publishing".to_string())
    } else {
        (
            DiagnosticLevel::Warn,
            format!(
                "publish failed in the last {ERROR_WINDOW_S} s ({}): a subscriber is not acknowledging",
                failing.join(", ")
            ),
        )
    };
    DeviceDiagnostics {
        name: "publishers".to_string(),
        hardware_id: hardware_id.to_string(),
        level,
        message,
        values,
    }
}

/// Builds the `/diagnostics` message from a snapshot: its
/// [`DiagnosticsSnapshot::statuses`], named `<prefix>: <stream>`, stamped
/// with the snapshot's tick time.
pub fn diagnostic_array(prefix: &str, snapshot: &DiagnosticsSnapshot) -> DiagnosticArray {
    let status = snapshot
        .statuses(prefix)
        .into_iter()
        .map(|s| DiagnosticStatus {
            level: s.level.as_byte(),
            name: s.name,
            message: s.message,
            hardware_id: s.hardware_id,
            values: s
                .values
                .into_iter()
                .map(|(key, value)| KeyValue { key, value })
                .collect(),
        })
        .collect();
    DiagnosticArray {
        header: Header {
            stamp: ros_time(snapshot.stamp_ns),
            frame_id: String::new(),
        },
        status,
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn publish_failures_warn_while_recent_and_name_the_topic() {
        let topics = ["/fall_guard/forecast", "/fall_guard/fall_imminent", ""];
        let ok = publishers_status(&topics, &[3, 0, 9], &[0, 0, 9], "poppy");
        assert_eq!(ok.level, DiagnosticLevel::Ok);
        assert!(ok.values.iter().all(|(k, _)| !k.ends_with(' ')));
        assert!(ok
            .values
            .contains(&("failures /fall_guard/forecast".to_string(), "3".to_string())));
        let warn = publishers_status(&topics, &[3, 2, 0], &[0, 2, 0], "poppy");
        assert_eq!(warn.level, DiagnosticLevel::Warn);
        assert!(
            warn.message.contains("/fall_guard/fall_imminent: 2"),
            "{}",
            warn.message
        );
    }

    #[test]
    fn forecast_layout_names_the_horizon_dimension() {
        let m = forecast_message(&[0.1, 0.5, 0.9]);
        assert_eq!(m.layout.dim.len(), 1);
        assert_eq!(m.layout.dim[0].label, "horizon_ms");
        assert_eq!(m.layout.dim[0].size, 3);
        assert_eq!(m.layout.dim[0].stride, 3);
        assert_eq!(m.layout.data_offset, 0);
        assert_eq!(m.data, vec![0.1, 0.5, 0.9]);
    }

    #[test]
    fn ros_time_splits_ns() {
        assert_eq!(
            ros_time(1_500_000_001),
            Time {
                sec: 1,
                nanosec: 500_000_001
            }
        );
        assert_eq!(ros_time(0), Time { sec: 0, nanosec: 0 });
        assert_eq!(
            ros_time(-1),
            Time {
                sec: -1,
                nanosec: 999_999_999
            }
        );
    }
}
