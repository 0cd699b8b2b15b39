//! Bad input on the live ROS 2 streams, against the real binary and an
//! rclpy walker (`ros_peer.py walk --fault-file`), as a subscriber sees it
//! (the input boundary, `streams/input.rs`, `docs/ros.md` "Input
//! boundary"):
//!
//! - future-stamped, then NaN `/joint_states`: every one rejected, the
//!   joints stream STALE on `/diagnostics` naming the reason
//!   (`rejected_future_stamp`, `rejected_non_finite`, `last_rejection`),
//!   the forecast NaN and `fall_imminent` asserted while it lasts, the tick
//!   clock never stalled (a forecast every tick), and every level back to
//!   OK once good input resumes;
//! - an undecodable JPEG on the camera, then empty plans: the stream STALE
//!   naming the reason (`rejected_undecodable`, `rejected_empty_plan`), the
//!   model degraded to its fallback (forecasts stay numbers), and every
//!   level back to OK after.
//!
//! Levels judge rejections over the last 10 s, so each recovery waits for
//! an all-OK message with a generous timeout; nothing asserts a timing.
//! A separate test binary from `daemon_ros.rs`, so that its daemons do not
//! run beside those on a 2-core machine.

#[path = "ros/heard.rs"]
mod heard;
#[path = "ros/support.rs"]
mod support;
use heard::{forecast_values, level, msgs, status_named, statuses, wait_diagnostics};

use std::path::{Path, PathBuf};
use std::time::Duration;

use serde_json::Value;
use support::{diag_value as kv, domain_id, rclpy_python, Peer};

mod daemon_common;
use daemon_common::{bundled_config_on, robot_joints, write_head_jpeg, Daemon};

/// The bundled config run live (joints and plan from ROS 2), on `domain`,
/// loopback only, edited by `edit`.
fn live_config(dir: &Path, domain: u16, edit: impl Fn(String) -> String) -> PathBuf {
    let text = bundled_config_on(domain);
    let path = dir.join("fall_guard.toml");
    std::fs::write(&path, edit(text)).expect("write config");
    path
}

fn last_diag(events: &[Value]) -> Option<&Value> {
    msgs(events, "/diagnostics").last()
}

/// Waits for a forecast that `want` accepts; returns every event seen.
async fn wait_forecast(
    listener: &mut Peer,
    timeout: Duration,
    want: impl Fn(&[f32]) -> bool,
) -> (bool, Vec<Value>) {
    let deadline = std::time::Instant::now() + timeout;
    let mut seen = Vec::new();
    while let Some(e) = listener
        .next_event(deadline.saturating_duration_since(std::time::Instant::now()))
        .await
    {
        let hit = e["event"] == "msg"
            && e["topic"] == "/fall_guard/forecast"
            && want(&forecast_values(&e));
        seen.push(e);
        if hit {
            return (true, seen);
        }
    }
    (false, seen)
}

/// One fault, as the walker injects it and `/diagnostics` must name it.
struct Fault {
    /// What the fault file says (`ros_peer.py walk`).
    name: &'static str,
    /// The stream status that goes STALE (`": joints"`).
    stream: &'static str,
    /// The boundary's reason (`rejected_<key>`).
    key: &'static str,
    /// The joints are lost: forecasts NaN and `fall_imminent` asserted.
    /// Otherwise the model falls back to this network, whose forecasts
    /// stay numbers.
    fallback: Option<&'static str>,
}

struct Scenario {
    listener: Peer,
    walker: Peer,
    daemon: Option<Daemon>,
    fault_file: PathBuf,
    streams: Vec<&'static str>,
    /// The last `fall_imminent` heard (published on change and latched:
    /// its current value is the last message of the whole run).
    imminent: Option<bool>,
}

impl Scenario {
    async fn start(
        python: &PathBuf,
        domain: u16,
        config: &Path,
        walk: &[&str],
        dir: &Path,
    ) -> Self {
        let listener = {
            let mut l = Peer::spawn(
                python,
                domain,
                &[
                    "listen",
                    "--sub",
                    "/diagnostics:diagnostic_msgs/msg/DiagnosticArray:diagnostics",
                    "--sub",
                    "/fall_guard/forecast:std_msgs/msg/Float32MultiArray:forecast",
                    "--sub",
                    "/fall_guard/fall_imminent:std_msgs/msg/Bool:latched",
                    "--sub",
                    "/joint_states:sensor_msgs/msg/JointState:sensor_data",
                    "--timeout",
                    "600",
                ],
            );
            let (ready, _) = l.wait_for("ready", Duration::from_secs(30)).await;
            assert!(
                ready.is_some(),
                "rclpy listener did not start: {}",
                l.stderr()
            );
            l
        };
        let daemon = Daemon::start(&["run", "--config", config.to_str().expect("utf8")]);
        let fault_file = dir.join("fault");
        let joints = robot_joints().join(",");
        let mut args = vec![
            "walk",
            "--joints",
            &joints,
            "--timeout",
            "600",
            "--fault-file",
            fault_file.to_str().expect("utf8"),
        ];
        args.extend_from_slice(walk);
        let walker = Peer::spawn(python, domain, &args);
        Scenario {
            listener,
            walker,
            daemon: Some(daemon),
            fault_file,
            streams: vec![": joints", ": plan", ": model"],
            imminent: None,
        }
    }

    fn fail(&mut self, what: &str, events: &[Value]) -> ! {
        let stderr = self.daemon.take().map(|d| d.stop().2).unwrap_or_default();
        panic!(
            "{what}\nlast diagnostics:\n{}\ndaemon: {stderr}\nwalker: {}",
            statuses(last_diag(events)),
            self.walker.stderr()
        );
    }

    /// Notes the `fall_imminent` messages among `events`.
    fn heard(&mut self, events: &[Value]) {
        if let Some(b) = msgs(events, "/fall_guard/fall_imminent")
            .filter_map(|m| m["msg"]["data"].as_bool())
            .last()
        {
            self.imminent = Some(b);
        }
    }

    /// Waits until every status this scenario watches is OK.
    async fn wait_all_ok(&mut self, what: &str) -> Value {
        let streams = self.streams.clone();
        // 10 s of rejection-free input, plus a refilled window, on a
        // loaded 2-core machine.
        let (ok, seen) = wait_diagnostics(&mut self.listener, Duration::from_secs(120), |d| {
            streams
                .iter()
                .all(|s| status_named(d, s).is_some_and(|st| level(st) == 0))
        })
        .await;
        self.heard(&seen);
        match ok {
            Some(ok) => ok,
            None => self.fail(&format!("never all OK {what}"), &seen),
        }
    }

    /// Injects `fault`, checks what a subscriber sees, removes it, and
    /// checks the recovery to OK.
    async fn check(mut self, fault: &Fault) -> Self {
        std::fs::write(&self.fault_file, fault.name).expect("fault file");
        let rejected = format!("rejected_{}", fault.key);
        let (bad, seen) = wait_diagnostics(&mut self.listener, Duration::from_secs(60), |d| {
            status_named(d, fault.stream)
                .is_some_and(|s| level(s) == 3 && kv(s, &rejected).is_some_and(|n| n != "0"))
        })
        .await;
        self.heard(&seen);
        let Some(bad) = bad else {
            self.fail(
                &format!(
                    "{}: {} never STALE with {rejected}",
                    fault.name, fault.stream
                ),
                &seen,
            );
        };
        let stream = status_named(&bad, fault.stream).expect("status");
        let message = stream["message"].as_str().unwrap_or_default().to_owned();
        let last = kv(stream, "last_rejection").unwrap_or_default();
        if !last.starts_with(fault.key) || !message.contains("rejected") {
            let what = format!(
                "{}: last_rejection {last:?}, message {message:?}",
                fault.name
            );
            self.fail(&what, &seen);
        }
        if kv(stream, "rejected_in_window").is_none_or(|n| n == "0") {
            self.fail(
                &format!("{}: no rejected_in_window in {stream}", fault.name),
                &seen,
            );
        }
        let model = status_named(&bad, ": model").expect("model status").clone();
        match fault.fallback {
            None => {
                // The joints are lost: the model says why, every forecast
                // is NaN (and keeps coming: the tick clock runs on), and
                // fall_imminent is asserted.
                if level(&model) != 1
                    || !kv(&model, "invalid_reason").is_some_and(|r| r.contains("joints"))
                {
                    self.fail(&format!("{}: model status {model}", fault.name), &seen);
                }
                tokio::time::sleep(Duration::from_millis(700)).await;
                let during = self.listener.drain();
                self.heard(&during);
                let forecasts: Vec<Vec<f32>> = msgs(&during, "/fall_guard/forecast")
                    .map(forecast_values)
                    .collect();
                if forecasts.len() < 3 || !forecasts.iter().all(|p| p.iter().all(|v| v.is_nan())) {
                    let what = format!("{}: forecasts during the fault: {forecasts:?}", fault.name);
                    self.fail(&what, &during);
                }
                if self.imminent != Some(true) {
                    let what = format!("{}: fall_imminent {:?}", fault.name, self.imminent);
                    self.fail(&what, &during);
                }
            }
            Some(fallback) => {
                // A lost plan or camera: the fallback network runs, the
                // model says it is degraded, and forecasts stay numbers.
                let (degraded, more) =
                    wait_diagnostics(&mut self.listener, Duration::from_secs(60), |d| {
                        status_named(d, ": model").is_some_and(|m| {
                            level(m) == 1 && kv(m, "active_model").as_deref() == Some(fallback)
                        })
                    })
                    .await;
                self.heard(&more);
                if degraded.is_none() {
                    let what = format!("{}: model never degraded to {fallback}", fault.name);
                    self.fail(&what, &more);
                }
                let (finite, during) =
                    wait_forecast(&mut self.listener, Duration::from_secs(60), |p| {
                        p.iter().all(|v| v.is_finite())
                    })
                    .await;
                self.heard(&during);
                if !finite {
                    let what = format!("{}: no finite forecast from {fallback}", fault.name);
                    self.fail(&what, &during);
                }
            }
        }
        std::fs::remove_file(&self.fault_file).expect("remove fault file");
        let ok = self.wait_all_ok(&format!("after {}", fault.name)).await;
        let stream = status_named(&ok, fault.stream).expect("status");
        assert_eq!(
            kv(stream, "rejected_in_window").as_deref(),
            Some("0"),
            "{stream}"
        );
        assert!(
            kv(stream, &rejected).is_some_and(|n| n.parse::<u64>().is_ok_and(|n| n > 0)),
            "{rejected} total in {stream}"
        );
        self
    }

    fn finish(self) {
        let Scenario {
            mut walker, daemon, ..
        } = self;
        drop(walker.drain());
        let (success, _stdout, stderr) = daemon.expect("daemon").stop();
        assert!(success, "daemon exit on SIGTERM: {stderr}");
        assert!(!stderr.contains("panicked"), "{stderr}");
        // Each reason is logged once, not per sample.
        for key in ["future_stamp", "non_finite", "undecodable", "empty_plan"] {
            let n = stderr
                .lines()
                .filter(|l| l.contains("sample rejected") && l.contains(key))
                .count();
            assert!(n <= 1, "{key} logged {n} times: {stderr}");
        }
    }
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn future_stamped_and_nan_joint_states_are_rejected_and_the_daemon_recovers() {
    let test = "future_stamped_and_nan_joint_states_are_rejected_and_the_daemon_recovers";
    let Some(python) = rclpy_python(test) else {
        return;
    };
    let domain = domain_id(0);
    let dir = tempfile::tempdir().expect("tempdir");
    let config = live_config(dir.path(), domain, |t| t);
    let mut s = Scenario::start(&python, domain, &config, &[], dir.path()).await;
    s.wait_all_ok("at start").await;
    let s = s
        .check(&Fault {
            name: "future",
            stream: ": joints",
            key: "future_stamp",
            fallback: None,
        })
        .await;
    let s = s
        .check(&Fault {
            name: "nan",
            stream: ": joints",
            key: "non_finite",
            fallback: None,
        })
        .await;
    s.finish();
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn undecodable_jpeg_and_empty_plan_are_rejected_and_the_daemon_recovers() {
    let test = "undecodable_jpeg_and_empty_plan_are_rejected_and_the_daemon_recovers";
    let Some(python) = rclpy_python(test) else {
        return;
    };
    let domain = domain_id(1);
    let dir = tempfile::tempdir().expect("tempdir");
    let config = live_config(dir.path(), domain, |t| {
        t.replace("camera = \"none\"", "camera = \"ros\"")
    });
    let jpeg = write_head_jpeg(dir.path());
    let walk = [
        "--camera",
        "/head_camera/image_raw/compressed",
        "--jpeg",
        jpeg.to_str().expect("utf8"),
    ];
    let mut s = Scenario::start(&python, domain, &config, &walk, dir.path()).await;
    s.streams.push(": camera");
    s.wait_all_ok("at start").await;
    let s = s
        .check(&Fault {
            name: "bad_jpeg",
            stream: ": camera",
            key: "undecodable",
            fallback: Some("MP"),
        })
        .await;
    let s = s
        .check(&Fault {
            name: "empty_plan",
            stream: ": plan",
            key: "empty_plan",
            // The camera still streams: a lost plan runs EP.
            fallback: Some("EP"),
        })
        .await;
    s.finish();
}
