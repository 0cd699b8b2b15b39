//! What the rclpy listener heard, read by the daemon's ROS 2 tests
//! (`daemon_ros.rs`, `daemon_ros_faults.rs`, `fault_soak.rs`): messages of
//! a topic, forecast values, diagnostic statuses and their levels, waiting
//! for a status. Each test uses some of it.

#![allow(dead_code)]

use std::time::Duration;

use serde_json::Value;

use super::support::Peer;

/// The events of `events` that are messages on `topic`.
pub fn msgs<'a>(events: &'a [Value], topic: &'a str) -> impl Iterator<Item = &'a Value> + 'a {
    events
        .iter()
        .filter(move |e| e["event"] == "msg" && e["topic"] == topic)
}

/// The probabilities of one `/fall_guard/forecast` message event (NaN for
/// the listener's "NaN").
pub fn forecast_values(event: &Value) -> Vec<f32> {
    event["msg"]["data"]
        .as_array()
        .expect("data")
        .iter()
        .map(|v| v.as_f64().map_or(f32::NAN, |x| x as f32))
        .collect()
}

/// The `DiagnosticStatus` whose name ends with `suffix` (`": model"`,
/// `": joints"`) in one received `/diagnostics` message event.
pub fn status_named<'a>(diag: &'a Value, suffix: &str) -> Option<&'a Value> {
    diag["msg"]["status"]
        .as_array()?
        .iter()
        .find(|s| s["name"].as_str().is_some_and(|n| n.ends_with(suffix)))
}

/// The `level` byte of a `DiagnosticStatus` (rclpy gives a `byte` as bytes).
pub fn level(status: &Value) -> u64 {
    status["level"]
        .as_u64()
        .or_else(|| {
            status["level"]
                .as_array()
                .and_then(|b| b.first())
                .and_then(Value::as_u64)
        })
        .unwrap_or_else(|| panic!("level of {status}"))
}

/// Waits for a `/diagnostics` message that `want` accepts; returns it with
/// every event seen meanwhile.
pub async fn wait_diagnostics(
    listener: &mut Peer,
    timeout: Duration,
    want: impl Fn(&Value) -> bool,
) -> (Option<Value>, Vec<Value>) {
    let deadline = std::time::Instant::now() + timeout;
    let mut seen = Vec::new();
    while let Some(e) = listener
        .next_event(deadline.saturating_duration_since(std::time::Instant::now()))
        .await
    {
        if e["event"] == "msg" && e["topic"] == "/diagnostics" && want(&e) {
            return (Some(e), seen);
        }
        seen.push(e);
    }
    (None, seen)
}

/// Name, level and message of every status of `diag`, for failure messages.
pub fn statuses(diag: Option<&Value>) -> String {
    diag.and_then(|d| d["msg"]["status"].as_array())
        .map(|st| {
            st.iter()
                .map(|s| format!("{} [{}] {}", s["name"], level(s), s["message"]))
                .collect::<Vec<_>>()
                .join("\n")
        })
        .unwrap_or_else(|| "no diagnostics".into())
}
