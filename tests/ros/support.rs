//! Shared by the `tests/ros_*.rs` interop tests: finds the rclpy venv, picks a
//! DDS domain per test, and runs `tests/ros/ros_peer.py` as a child process
//! whose JSON-lines stdout the test reads.
//!
//! All DDS traffic stays on 127.0.0.1: the child gets
//! `ROS_AUTOMATIC_DISCOVERY_RANGE=LOCALHOST`, the Rust node is built with
//! `DiscoveryRange::Localhost`.
#![allow(dead_code)]

use std::io::{BufRead, BufReader, Read, Write};
use std::path::PathBuf;
use std::process::{Child, Command, Stdio};
use std::sync::mpsc;
use std::time::{Duration, Instant};

use fall_guard_runtime::ros::{RosSettings, DISCOVERY_RANGE_ENV, DOMAIN_ID_ENV};
use serde_json::Value;

pub const REQUIRE_ENV: &str = "FALL_GUARD_REQUIRE_ROS";
pub const PYTHON_ENV: &str = "FALL_GUARD_ROS_PYTHON";

/// The venv's python, or `None` (after a loud message) when the venv is
/// absent and `FALL_GUARD_REQUIRE_ROS` is unset. With it set, a missing venv
/// fails the test.
pub fn rclpy_python(test: &str) -> Option<PathBuf> {
    let python = std::env::var_os(PYTHON_ENV)
        .map(PathBuf::from)
        .unwrap_or_else(|| PathBuf::from(env!("CARGO_MANIFEST_DIR")).join(".venv/bin/python"));
    let usable = python.is_file()
        && Command::new(&python)
            .args(["-c", "import rclpy, std_msgs.msg, sensor_msgs.msg, trajectory_msgs.msg, diagnostic_msgs.msg"])
            .stdout(Stdio::null())
            .stderr(Stdio::null())
            .status()
            .is_ok_and(|s| s.success());
    if usable {
        return Some(python);
    }
    let why = format!(
        "{test}: no rclpy at {} (create it with `bash tests/ros/setup_venv.sh`)",
        python.display()
    );
    if std::env::var_os(REQUIRE_ENV).is_some() {
        panic!("{why}; {REQUIRE_ENV} is set, so the ROS 2 interop tests must run");
    }
    // Straight to the process's stderr: libtest captures `eprintln!` of a
    // passing test, and a skip must be seen.
    let bar = "=".repeat(72);
    let _ = writeln!(
        std::io::stderr().lock(),
        "\n{bar}\nSKIPPED ROS 2 INTEROP TEST {why}\nSet {REQUIRE_ENV}=1 to make this a failure.\n{bar}\n"
    );
    None
}

/// The value of `key` in one `DiagnosticStatus` as `ros_peer.py` prints it.
pub fn diag_value(status: &Value, key: &str) -> Option<String> {
    status["values"]
        .as_array()?
        .iter()
        .find(|kv| kv["key"] == key)
        .and_then(|kv| kv["value"].as_str().map(str::to_owned))
}

/// A DDS domain for one test: distinct per test `index` (0..8) within this
/// process, and spread by process id so that two checkouts testing at once
/// on this machine do not hear each other (10..=225, under ROS's 232).
pub fn domain_id(index: u16) -> u16 {
    assert!(index < 8, "domain index {index} out of range");
    10 + (std::process::id() % 27) as u16 * 8 + index
}

/// Node settings through the same environment parsing the daemon uses.
pub fn localhost_settings(domain: u16, namespace: &str, node: &str) -> RosSettings {
    let domain = domain.to_string();
    RosSettings::from_vars(namespace, node, |var| match var {
        v if v == DOMAIN_ID_ENV => Some(domain.clone()),
        v if v == DISCOVERY_RANGE_ENV => Some("LOCALHOST".to_owned()),
        _ => None,
    })
    .expect("valid test ROS settings")
}

/// A running `ros_peer.py`; killed on drop.
pub struct Peer {
    child: Child,
    events: mpsc::Receiver<Value>,
    stderr: std::sync::Arc<std::sync::Mutex<String>>,
    pub started: Instant,
}

impl Peer {
    pub fn spawn(python: &PathBuf, domain: u16, args: &[&str]) -> Peer {
        let script = PathBuf::from(env!("CARGO_MANIFEST_DIR")).join("tests/ros/ros_peer.py");
        let mut child = Command::new(python)
            .arg(&script)
            .args(args)
            .env(DOMAIN_ID_ENV, domain.to_string())
            .env(DISCOVERY_RANGE_ENV, "LOCALHOST")
            .env_remove("ROS_LOCALHOST_ONLY")
            .env_remove("ROS_STATIC_PEERS")
            .env_remove("RMW_IMPLEMENTATION")
            .env("PYTHONUNBUFFERED", "1")
            .stdin(Stdio::null())
            .stdout(Stdio::piped())
            .stderr(Stdio::piped())
            .spawn()
            .expect("spawn ros_peer.py");
        let stdout = child.stdout.take().expect("piped stdout");
        let (tx, events) = mpsc::channel();
        std::thread::spawn(move || {
            for line in BufReader::new(stdout).lines() {
                let Ok(line) = line else { break };
                match serde_json::from_str::<Value>(&line) {
                    Ok(v) => {
                        if tx.send(v).is_err() {
                            break;
                        }
                    }
                    Err(_) => eprintln!("ros_peer.py: {line}"),
                }
            }
        });
        let stderr = std::sync::Arc::new(std::sync::Mutex::new(String::new()));
        let mut err_pipe = child.stderr.take().expect("piped stderr");
        let sink = stderr.clone();
        std::thread::spawn(move || {
            let mut text = String::new();
            let _ = err_pipe.read_to_string(&mut text);
            if let Ok(mut s) = sink.lock() {
                s.push_str(&text);
            }
        });
        Peer {
            child,
            events,
            stderr,
            started: Instant::now(),
        }
    }

    /// The next event, waiting at most `timeout` without blocking the runtime.
    pub async fn next_event(&mut self, timeout: Duration) -> Option<Value> {
        let deadline = Instant::now() + timeout;
        loop {
            match self.events.try_recv() {
                Ok(v) => return Some(v),
                Err(mpsc::TryRecvError::Disconnected) => return None,
                Err(mpsc::TryRecvError::Empty) => {}
            }
            if Instant::now() >= deadline {
                return None;
            }
            tokio::time::sleep(Duration::from_millis(5)).await;
        }
    }

    /// Every event available now.
    pub fn drain(&mut self) -> Vec<Value> {
        self.events.try_iter().collect()
    }

    /// Waits for an event with `"event": name`, returning the ones before it too.
    pub async fn wait_for(&mut self, name: &str, timeout: Duration) -> (Option<Value>, Vec<Value>) {
        let deadline = Instant::now() + timeout;
        let mut seen = Vec::new();
        while let Some(v) = self
            .next_event(deadline.saturating_duration_since(Instant::now()))
            .await
        {
            if v["event"] == name {
                return (Some(v), seen);
            }
            seen.push(v);
        }
        (None, seen)
    }

    /// The child's stderr so far (for failure messages).
    pub fn stderr(&mut self) -> String {
        if let Ok(Some(_)) = self.child.try_wait() {
            std::thread::sleep(Duration::from_millis(50));
        }
        self.stderr.lock().map(|s| s.clone()).unwrap_or_default()
    }
}

impl Drop for Peer {
    fn drop(&mut self) {
        let _ = self.child.kill();
        let _ = self.child.wait();
    }
}
