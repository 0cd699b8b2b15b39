//! DDS Security (SROS2, cargo feature `security`): the daemon (the real
//! binary) started with `ROS_SECURITY_ENABLE=true`,
//! `ROS_SECURITY_STRATEGY=Enforce` and a keystore made by
//! `scripts/security/sros2-keystore.sh`, against secured ros2-client peers in this
//! process (their own enclaves), all on 127.0.0.1, one DDS domain per test:
//!
//! - a peer permitted to read the outputs receives the forecasts (numbers,
//!   as the replay computes them) and the latched safety signal;
//! - a peer of the same keystore without permission for the forecast topic
//!   cannot create its reader there, yet reads `/diagnostics`, which it may;
//! - a peer whose identity and permissions come from another CA is not
//!   matched: it receives nothing at all, nor does an open peer;
//! - an unsecured publisher on `/joint_states` is ignored (the joints stay
//!   never seen on `/diagnostics`), while a permitted secured one drives the
//!   joints;
//! - with `Enforce`, a missing or invalid enclave file stops the daemon at
//!   start with an error naming the file; `Permissive` without the enclave
//!   runs open, with a WARN (and the same decision without the daemon).

mod daemon_common;
use daemon_common::{bundled_config_on, status_value, Daemon};

#[path = "ros/support.rs"]
mod support;

use std::path::{Path, PathBuf};
use std::process::Command;
use std::sync::{Arc, Mutex};
use std::time::{Duration, Instant};

use fall_guard_runtime::msgs::{DiagnosticArray, Float32MultiArray, JointState};
use fall_guard_runtime::robot::JointTable;
use fall_guard_runtime::ros::security::{
    check_enclave_files, plan, Plan, SecuritySettings, Strategy,
};
use fall_guard_runtime::ros::{qos, RosNode, RosSettings};
use futures::{pin_mut, StreamExt};
use support::{domain_id, localhost_settings};

fn repo(path: &str) -> PathBuf {
    Path::new(env!("CARGO_MANIFEST_DIR")).join(path)
}

fn keystore_script(args: &[&str]) {
    let out = Command::new("bash")
        .arg(repo("scripts/security/sros2-keystore.sh"))
        .args(args)
        .output()
        .expect("run scripts/security/sros2-keystore.sh");
    assert!(
        out.status.success(),
        "sros2-keystore.sh {args:?}: {}",
        String::from_utf8_lossy(&out.stderr)
    );
}

/// A keystore with the daemon's, the monitor's and the driver's enclaves,
/// plus `/no_forecast`: may read `/diagnostics` only.
fn keystore(dir: &Path) -> PathBuf {
    let ks = dir.join("keystore");
    let ks_s = ks.to_str().expect("utf8");
    keystore_script(&["fall-guard", ks_s]);
    keystore_script(&[
        "enclave",
        ks_s,
        "/no_forecast",
        "--subscribe",
        "/diagnostics",
    ]);
    ks
}

/// Another keystore: the same enclave names, other CAs.
fn foreign_keystore(dir: &Path) -> PathBuf {
    let ks = dir.join("foreign");
    keystore_script(&["fall-guard", ks.to_str().expect("utf8")]);
    ks
}

/// Settings of an in-process peer: node `name` in the root namespace,
/// secured with the enclave `/<name>` of `keystore` (Enforce), or open.
fn peer_settings(domain: u16, name: &str, keystore: Option<&Path>) -> RosSettings {
    let mut s = localhost_settings(domain, "/", name);
    s.security = keystore.map(|ks| SecuritySettings {
        strategy: Strategy::Enforce,
        keystore: Some(ks.to_path_buf()),
        enclave: format!("/{name}"),
    });
    s
}

/// Every message a subscription receives, gathered by a task.
struct Heard<T> {
    msgs: Arc<Mutex<Vec<T>>>,
    task: tokio::task::JoinHandle<()>,
}

impl<T: Clone> Heard<T> {
    fn all(&self) -> Vec<T> {
        self.msgs.lock().expect("heard").clone()
    }
}

impl<T> Drop for Heard<T> {
    fn drop(&mut self) {
        self.task.abort();
    }
}

fn subscribe<T>(
    node: &mut RosNode,
    topic: &str,
    type_name: &str,
    qos: ros2_client::QosProfile,
) -> Result<Heard<T>, String>
where
    T: serde::de::DeserializeOwned + Send + Sync + 'static,
{
    let t = node
        .topic(topic, type_name, &qos)
        .map_err(|e| e.to_string())?;
    let sub = node
        .node_mut()
        .create_subscription::<T>(&t, Some(qos))
        .map_err(|e| format!("{e:?}"))?;
    let msgs = Arc::new(Mutex::new(Vec::new()));
    let sink = msgs.clone();
    let task = tokio::spawn(async move {
        let stream = sub.async_stream();
        pin_mut!(stream);
        while let Some(sample) = stream.next().await {
            if let Ok((msg, _)) = sample {
                sink.lock().expect("heard").push(msg);
            }
        }
    });
    Ok(Heard { msgs, task })
}

/// The bundled replay config on `domain`, loopback only, the ROS inputs of
/// `run` (joints and plan; no camera).
///
/// `/diagnostics` every 200 ms instead of every second: each peer's secure
/// handshake with the daemon (authentication, then the exchange of crypto
/// tokens) can take seconds on a loaded machine, and a peer matched late
/// should still hear several.
fn config(dir: &Path, domain: u16) -> PathBuf {
    let text = bundled_config_on(domain)
        .replace(
            "recording = \"tests/fixtures/episode_00007.mcap\"",
            &format!(
                "recording = \"{}\"",
                repo("tests/fixtures/episode_00007.mcap").display()
            ),
        )
        .replace(
            "diagnostics_period_ms = 1000",
            "diagnostics_period_ms = 200",
        );
    assert!(
        text.contains("diagnostics_period_ms = 200"),
        "config/replay.toml changed shape"
    );
    let path = dir.join("fall_guard.toml");
    std::fs::write(&path, text).expect("write config");
    path
}

/// The daemon with DDS Security from `keystore` (strategy `strategy`).
fn secured_daemon(args: &[&str], keystore: &Path, strategy: &str) -> Daemon {
    let mut command = Daemon::command(args);
    command
        .env_remove("ROS_SECURITY_ENCLAVE_OVERRIDE")
        .env("ROS_SECURITY_ENABLE", "true")
        .env("ROS_SECURITY_STRATEGY", strategy)
        .env("ROS_SECURITY_KEYSTORE", keystore);
    Daemon::spawn(command)
}

/// The value of `key` in the status whose name ends with `suffix`.
fn diag_value(d: &DiagnosticArray, suffix: &str, key: &str) -> Option<String> {
    let status = d.status.iter().find(|s| s.name.ends_with(suffix))?;
    status_value(status, key)
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn secured_peers_receive_only_what_their_permissions_and_ca_allow() {
    let domain = domain_id(0);
    let dir = tempfile::tempdir().expect("tempdir");
    let ks = keystore(dir.path());
    let foreign = foreign_keystore(dir.path());

    // The permitted monitor: forecasts, the latched safety signal.
    let mut monitor =
        RosNode::start(&peer_settings(domain, "fall_guard_monitor", Some(&ks))).expect("monitor");
    let forecasts: Heard<Float32MultiArray> = subscribe(
        &mut monitor,
        "/fall_guard/forecast",
        "std_msgs/msg/Float32MultiArray",
        qos::forecast(),
    )
    .expect("the monitor may read the forecast");
    let horizons: Heard<Float32MultiArray> = subscribe(
        &mut monitor,
        "/fall_guard/horizons_ms",
        "std_msgs/msg/Float32MultiArray",
        qos::horizons(),
    )
    .expect("the monitor may read the horizons");

    // Same keystore, no permission for the forecast: its own access control
    // refuses the reader; /diagnostics, which it may read, arrives.
    let mut no_forecast =
        RosNode::start(&peer_settings(domain, "no_forecast", Some(&ks))).expect("no_forecast");
    let refused = subscribe::<Float32MultiArray>(
        &mut no_forecast,
        "/fall_guard/forecast",
        "std_msgs/msg/Float32MultiArray",
        qos::forecast(),
    );
    let Err(why) = refused else {
        panic!("a peer without permission for /fall_guard/forecast created a reader there");
    };
    let allowed_diagnostics: Heard<DiagnosticArray> = subscribe(
        &mut no_forecast,
        "/diagnostics",
        "diagnostic_msgs/msg/DiagnosticArray",
        qos::diagnostics(),
    )
    .expect("no_forecast may read /diagnostics");

    // Another CA: a complete, valid enclave of a keystore the daemon does
    // not trust. It may read everything by its own permissions.
    let mut stranger = RosNode::start(&peer_settings(domain, "fall_guard_monitor", Some(&foreign)))
        .expect("stranger");
    let stranger_forecasts: Heard<Float32MultiArray> = subscribe(
        &mut stranger,
        "/fall_guard/forecast",
        "std_msgs/msg/Float32MultiArray",
        qos::forecast(),
    )
    .expect("stranger reader");
    let stranger_diagnostics: Heard<DiagnosticArray> = subscribe(
        &mut stranger,
        "/diagnostics",
        "diagnostic_msgs/msg/DiagnosticArray",
        qos::diagnostics(),
    )
    .expect("stranger reader");

    // An open participant: sees no secured traffic at all.
    let mut open = RosNode::start(&peer_settings(domain, "open_listener", None)).expect("open");
    let open_forecasts: Heard<Float32MultiArray> = subscribe(
        &mut open,
        "/fall_guard/forecast",
        "std_msgs/msg/Float32MultiArray",
        qos::forecast(),
    )
    .expect("open reader");

    // The daemon replays the bundled episode at half speed (~20 s), so that
    // every peer's handshake has time to finish while it publishes.
    let config = config(dir.path(), domain);
    let daemon = secured_daemon(
        &[
            "replay",
            "--speed",
            "0.5",
            "--config",
            config.to_str().expect("utf8"),
        ],
        &ks,
        "Enforce",
    );
    let (success, _stdout, stderr) = tokio::task::spawn_blocking(move || daemon.wait())
        .await
        .expect("join");
    assert!(success, "secured replay failed: {stderr}");
    assert!(
        stderr.contains("DDS Security on"),
        "the daemon did not say it runs secured: {stderr}"
    );
    tokio::time::sleep(Duration::from_millis(1500)).await;

    let got = forecasts.all();
    let numbers = got
        .iter()
        .filter(|f| !f.data.is_empty() && f.data.iter().all(|p| p.is_finite()))
        .count();
    assert!(
        numbers >= 60,
        "the permitted monitor got {} forecasts, {numbers} of them numbers: {stderr}",
        got.len()
    );
    assert!(
        got.iter()
            .flat_map(|f| &f.data)
            .all(|p| p.is_nan() || (0.0..=1.0).contains(p)),
        "forecast values out of [0, 1]"
    );
    assert_eq!(
        horizons.all().last().map(|h| h.data.len()),
        got.last().map(|f| f.data.len()),
        "the latched horizons did not reach the monitor"
    );
    assert!(
        !allowed_diagnostics.all().is_empty(),
        "no_forecast is authenticated and may read /diagnostics, yet got none (refused forecast: {why})"
    );
    assert!(
        stranger_forecasts.all().is_empty() && stranger_diagnostics.all().is_empty(),
        "a peer of another CA was matched: {} forecasts, {} diagnostics",
        stranger_forecasts.all().len(),
        stranger_diagnostics.all().len()
    );
    assert!(
        open_forecasts.all().is_empty(),
        "an open participant received {} secured forecasts",
        open_forecasts.all().len()
    );
    drop((forecasts, horizons, allowed_diagnostics, open_forecasts));
    drop((stranger_forecasts, stranger_diagnostics));
    monitor.shutdown().await;
    no_forecast.shutdown().await;
    stranger.shutdown().await;
    open.shutdown().await;
}

/// Publishes the robot's joints at 50 Hz on `/joint_states` from `node`
/// until the task is aborted.
fn walk(node: &mut RosNode) -> tokio::task::JoinHandle<()> {
    let t = node
        .topic(
            "/joint_states",
            "sensor_msgs/msg/JointState",
            &qos::sensor_data(),
        )
        .expect("topic");
    let publisher = node
        .node_mut()
        .create_publisher::<JointState>(&t, Some(qos::sensor_data()))
        .expect("joint_states publisher");
    let names = JointTable::poppy_humanoid().names();
    tokio::spawn(async move {
        let mut tick = tokio::time::interval(Duration::from_millis(20));
        loop {
            tick.tick().await;
            let msg = JointState {
                name: names.clone(),
                position: vec![0.0; names.len()],
                ..Default::default()
            };
            let _ = publisher.publish(msg);
        }
    })
}

/// Waits until a `/diagnostics` message satisfies `want`.
async fn wait_for(
    heard: &Heard<DiagnosticArray>,
    timeout: Duration,
    want: impl Fn(&DiagnosticArray) -> bool,
) -> Option<DiagnosticArray> {
    let deadline = Instant::now() + timeout;
    while Instant::now() < deadline {
        if let Some(d) = heard.all().into_iter().rev().find(|d| want(d)) {
            return Some(d);
        }
        tokio::time::sleep(Duration::from_millis(100)).await;
    }
    None
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn an_unsecured_joint_states_publisher_is_ignored() {
    let domain = domain_id(1);
    let dir = tempfile::tempdir().expect("tempdir");
    let ks = keystore(dir.path());

    let mut monitor =
        RosNode::start(&peer_settings(domain, "fall_guard_monitor", Some(&ks))).expect("monitor");
    let diagnostics: Heard<DiagnosticArray> = subscribe(
        &mut monitor,
        "/diagnostics",
        "diagnostic_msgs/msg/DiagnosticArray",
        qos::diagnostics(),
    )
    .expect("monitor reader");
    // An open participant publishing the joints as a driver would.
    let mut open = RosNode::start(&peer_settings(domain, "intruder", None)).expect("open node");
    let intruder = walk(&mut open);

    let config = config(dir.path(), domain);
    let daemon = secured_daemon(
        &["run", "--config", config.to_str().expect("utf8")],
        &ks,
        "Enforce",
    );
    // Several diagnostics while only the open publisher publishes: the
    // joints are never seen.
    let joints_age = |d: &DiagnosticArray| diag_value(d, ": joints", "age_ms");
    let first = wait_for(&diagnostics, Duration::from_secs(40), |_| true).await;
    let seen_after = Instant::now();
    tokio::time::sleep(Duration::from_secs(4)).await;
    let before = diagnostics.all();
    // Then the permitted driver: the joints arrive.
    let mut driver =
        RosNode::start(&peer_settings(domain, "fall_guard_driver", Some(&ks))).expect("driver");
    let walker = walk(&mut driver);
    let fresh = wait_for(&diagnostics, Duration::from_secs(30), |d| {
        joints_age(d).is_some_and(|a| a != "never")
    })
    .await;
    walker.abort();
    intruder.abort();
    let (success, _stdout, stderr) = tokio::task::spawn_blocking(move || daemon.stop())
        .await
        .expect("join");
    assert!(first.is_some(), "the monitor got no /diagnostics: {stderr}");
    assert!(
        before.len() >= 3,
        "{} diagnostics in the {:?} with only the open publisher: {stderr}",
        before.len(),
        seen_after.elapsed()
    );
    for d in &before {
        assert_eq!(
            joints_age(d).as_deref(),
            Some("never"),
            "the daemon took joints from an unsecured publisher: {d:?}"
        );
        let joints = d
            .status
            .iter()
            .find(|s| s.name.ends_with(": joints"))
            .expect("joints status");
        assert_eq!(
            joints.level,
            fall_guard_runtime::msgs::DiagnosticStatus::STALE,
            "{joints:?}"
        );
    }
    let fresh = fresh.unwrap_or_else(|| {
        panic!("the permitted driver's joints never reached the daemon: {stderr}")
    });
    let rate: f64 = diag_value(&fresh, ": joints", "rate_hz")
        .and_then(|r| r.parse().ok())
        .expect("joints rate_hz");
    assert!(rate > 0.0, "{fresh:?}");
    assert!(success, "daemon exit on SIGTERM: {stderr}");
    drop(diagnostics);
    monitor.shutdown().await;
    open.shutdown().await;
    driver.shutdown().await;
}

/// `fall-guard run` with `Enforce` and a broken enclave: (exit ok, stderr).
async fn run_with(
    dir: &Path,
    domain: u16,
    ks: &Path,
    strategy: &str,
    args: &[&str],
) -> (bool, String) {
    let config = config(dir, domain);
    let mut all: Vec<&str> = args.to_vec();
    all.extend(["--config", config.to_str().expect("utf8")]);
    let daemon = secured_daemon(&all, ks, strategy);
    let waited = tokio::time::timeout(
        Duration::from_secs(60),
        tokio::task::spawn_blocking(move || {
            let (success, _stdout, stderr) = daemon.wait();
            (success, stderr)
        }),
    )
    .await;
    waited.expect("the daemon did not exit").expect("join")
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn enforce_refuses_to_start_on_a_missing_or_invalid_enclave_file() {
    let domain = domain_id(2);
    let dir = tempfile::tempdir().expect("tempdir");
    let ks = keystore(dir.path());
    let foreign = foreign_keystore(dir.path());
    let enclave = ks.join("enclaves/fall_guard");

    // Each breakage, and the file the error must name.
    let permissions = enclave.join("permissions.p7s");
    let cert = enclave.join("cert.pem");
    let saved_permissions = std::fs::read(&permissions).expect("permissions.p7s");
    let saved_cert = std::fs::read(&cert).expect("cert.pem");
    // (what, how to break it, the file named, the reason given)
    type Breakage<'a> = (&'a str, Box<dyn Fn() + 'a>, &'a Path, &'a str);
    let cases: Vec<Breakage> = vec![
        (
            "missing",
            Box::new(|| std::fs::remove_file(&permissions).expect("rm")),
            &permissions,
            "missing",
        ),
        (
            "signed by another permissions CA",
            Box::new(|| {
                std::fs::copy(
                    foreign.join("enclaves/fall_guard/permissions.p7s"),
                    &permissions,
                )
                .expect("cp");
            }),
            &permissions,
            "not signed by the permissions CA",
        ),
        (
            "not a certificate",
            Box::new(|| std::fs::write(&cert, b"not a certificate\n").expect("write")),
            &cert,
            "not a PEM X.509 certificate",
        ),
        (
            "issued by another identity CA",
            Box::new(|| {
                std::fs::copy(foreign.join("enclaves/fall_guard/cert.pem"), &cert).expect("cp");
            }),
            &cert,
            "not issued by the identity CA",
        ),
    ];
    for (what, breaks, file, reason) in cases {
        breaks();
        let (success, stderr) = run_with(dir.path(), domain, &ks, "Enforce", &["run"]).await;
        assert!(
            !success,
            "{what}: the daemon started with Enforce: {stderr}"
        );
        assert!(
            stderr.contains(&file.display().to_string()) && stderr.contains(reason),
            "{what}: the error does not name {} ({reason}): {stderr}",
            file.display()
        );
        std::fs::write(&permissions, &saved_permissions).expect("restore");
        std::fs::write(&cert, &saved_cert).expect("restore");
    }

    // No enclave at all: Enforce refuses, Permissive runs open (a replay at
    // full speed) and says so.
    std::fs::rename(&enclave, dir.path().join("moved")).expect("mv enclave");
    let (success, stderr) = run_with(dir.path(), domain, &ks, "Enforce", &["run"]).await;
    assert!(!success, "started without its enclave: {stderr}");
    assert!(stderr.contains("enclave /fall_guard not found"), "{stderr}");
    let (success, stderr) = run_with(
        dir.path(),
        domain,
        &ks,
        "Permissive",
        &["replay", "--max-speed", "--quiet"],
    )
    .await;
    assert!(success, "Permissive without the enclave: {stderr}");
    assert!(
        stderr.contains("the participant is open") && !stderr.contains("DDS Security on"),
        "{stderr}"
    );
}

fn enabled(strategy: Strategy, keystore: Option<&Path>) -> SecuritySettings {
    SecuritySettings {
        strategy,
        keystore: keystore.map(Path::to_path_buf),
        enclave: "/fall_guard".to_owned(),
    }
}

/// The decision before any file is read, and the first file check.
#[test]
fn enforce_needs_a_keystore_and_the_enclave() {
    let e = plan(Some(&enabled(Strategy::Enforce, None))).expect_err("no keystore");
    assert!(e.to_string().contains("ROS_SECURITY_KEYSTORE"), "{e}");
    let dir = tempfile::tempdir().unwrap();
    let e = plan(Some(&enabled(Strategy::Enforce, Some(dir.path())))).expect_err("no enclave");
    assert!(e.to_string().contains("enclaves/fall_guard"), "{e}");
    // Permissive: open, with the reason.
    let p = plan(Some(&enabled(Strategy::Permissive, Some(dir.path())))).unwrap();
    assert!(matches!(p, Plan::Open { why: Some(w) } if w.contains("not found")));
    // An enclave directory that exists is used, whatever the strategy.
    std::fs::create_dir_all(dir.path().join("enclaves/fall_guard")).unwrap();
    for strategy in [Strategy::Enforce, Strategy::Permissive] {
        let p = plan(Some(&enabled(strategy, Some(dir.path())))).unwrap();
        assert!(matches!(p, Plan::Secure { .. }), "{p:?}");
    }
    // ... and its files must be there: the first one missing is named.
    let e = check_enclave_files(&dir.path().join("enclaves/fall_guard")).expect_err("empty");
    assert!(
        e.to_string().contains("identity_ca.cert.pem") && e.to_string().contains("missing"),
        "{e}"
    );
}
