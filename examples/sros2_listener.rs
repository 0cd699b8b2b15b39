//! A listener of fall-guard's outputs with the daemon's DDS Security
//! settings (`ROS_SECURITY_ENABLE`, `ROS_SECURITY_STRATEGY`,
//! `ROS_SECURITY_KEYSTORE`, `ROS_DOMAIN_ID`,
//! `ROS_AUTOMATIC_DISCOVERY_RANGE`), to check a keystore by hand or to give
//! a secured daemon a subscriber to encrypt for (`scripts/security/bench-security.sh`).
//! Node `/fall_guard_monitor`, enclave `/fall_guard_monitor` unless
//! `ROS_SECURITY_ENCLAVE_OVERRIDE` names another; prints what it received
//! once a second for SECONDS (default 10):
//!
//! ```sh
//! ROS_SECURITY_ENABLE=true ROS_SECURITY_STRATEGY=Enforce ROS_SECURITY_KEYSTORE=out/ks \
//!   cargo run --release --features security --example sros2_listener -- 30
//! ```

use std::sync::atomic::{AtomicU64, Ordering};
use std::sync::Arc;
use std::time::{Duration, Instant};

use fall_guard_runtime::msgs::{Bool, DiagnosticArray, Float32MultiArray};
use fall_guard_runtime::ros::{qos, RosNode, RosSettings};
use futures::{pin_mut, StreamExt};

fn count<T>(
    node: &mut RosNode,
    topic: &str,
    type_name: &str,
    qos: ros2_client::QosProfile,
) -> Result<Arc<AtomicU64>, String>
where
    T: serde::de::DeserializeOwned + Send + Sync + 'static,
{
    let t = node
        .topic(topic, type_name, &qos)
        .map_err(|e| e.to_string())?;
    let sub = node
        .node_mut()
        .create_subscription::<T>(&t, Some(qos))
        .map_err(|e| format!("subscription to {topic}: {e:?}"))?;
    let n = Arc::new(AtomicU64::new(0));
    let seen = n.clone();
    tokio::spawn(async move {
        let stream = sub.async_stream();
        pin_mut!(stream);
        while let Some(sample) = stream.next().await {
            if sample.is_ok() {
                seen.fetch_add(1, Ordering::Relaxed);
            }
        }
    });
    Ok(n)
}

#[tokio::main(flavor = "multi_thread", worker_threads = 1)]
async fn main() -> Result<(), String> {
    let seconds: u64 = match std::env::args().nth(1) {
        Some(s) => s
            .parse()
            .map_err(|_| format!("SECONDS: expected a whole number, got {s:?}"))?,
        None => 10,
    };
    let settings =
        RosSettings::from_vars_in_enclave("/", "fall_guard_monitor", "/fall_guard_monitor", |v| {
            std::env::var(v).ok()
        })
        .map_err(|e| e.to_string())?;
    let mut node = RosNode::start(&settings).map_err(|e| e.to_string())?;
    let forecasts = count::<Float32MultiArray>(
        &mut node,
        "/fall_guard/forecast",
        "std_msgs/msg/Float32MultiArray",
        qos::forecast(),
    )?;
    let imminent = count::<Bool>(
        &mut node,
        "/fall_guard/fall_imminent",
        "std_msgs/msg/Bool",
        qos::fall_imminent(),
    )?;
    let diagnostics = count::<DiagnosticArray>(
        &mut node,
        "/diagnostics",
        "diagnostic_msgs/msg/DiagnosticArray",
        qos::diagnostics(),
    )?;
    let secured = settings.security.is_some(); // asked for; Permissive may still run open
    let start = Instant::now();
    for _ in 0..seconds {
        tokio::time::sleep(Duration::from_secs(1)).await;
        println!(
            "t={:.0}s secured={secured} forecast={} fall_imminent={} diagnostics={}",
            start.elapsed().as_secs_f64(),
            forecasts.load(Ordering::Relaxed),
            imminent.load(Ordering::Relaxed),
            diagnostics.load(Ordering::Relaxed)
        );
    }
    node.shutdown().await;
    Ok(())
}
