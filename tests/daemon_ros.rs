//! The daemon (the real binary, with the networks shipped in `models/`)
//! against real rclpy peers on loopback DDS:
//!
//! - replaying the bundled falling fixture, it publishes one forecast per
//!   tick; every forecast after the ring fills reaches an rclpy subscriber,
//!   equal to what `fall-guard-lab eval --recording` computes offline for the
//!   same ticks, and `/fall_guard/fall_imminent` (asserted while the ring
//!   fills) is on from a real warning before the fall;
//! - run live with `/joint_states` and `/planned_trajectory` coming from an
//!   rclpy publisher (no camera), it forecasts with the MP network and says
//!   so on `/diagnostics`;
//!   a SIGTERM stops it with no ERROR and no DDS chatter in its log;
//! - a joints gap in a replay: NaN on `/fall_guard/forecast` from the
//!   first tick whose joints are older than `joints_stale_ms` until N fresh
//!   ticks have refilled the window, and `fall_imminent` asserted meanwhile;
//! - `record` then `label` then `replay` of live ROS 2 streams; `record`
//!   keeps the camera's messages byte for byte (a 320x240 JPEG) and runs
//!   with a config whose network files do not exist;
//! - run on the Dynamixel servo buses (both emulated on pseudo-terminals):
//!   faults (no reply, bad checksums, garbage, an error bit, an unplugged
//!   adapter) make the forecast not valid on `/diagnostics`, the daemon
//!   keeps running and recovers;
//! - one servo that does not answer (and a plain, non-USB2AX adapter on the
//!   other bus): `/joint_states` goes on with the other 24 joints, the
//!   forecast is NaN once its last value is older than `joints_stale_ms`
//!   and `fall_imminent` asserted, `/diagnostics` names the motor on the
//!   joints and the bus status; when it answers again, and after garbage on
//!   the bus, every level returns to OK;
//! - both buses noisy (seeded faults of each motor's reply: 5% dropped, 2%
//!   bad checksums, 5% garbage before it) with a ROS 2 planner: at least
//!   95% of the forecasts valid on held joint values, no joint gap waited
//!   out (a brief one, of a loaded machine's late thread, is bridged and
//!   counted in the share), every position on
//!   `/joint_states` one a motor held, each motor's age and missed-read
//!   share on its bus status and the failing ones named at WARN; a bus
//!   unplugged makes every forecast from 0.5 s on NaN.

#[path = "ros/heard.rs"]
mod heard;
#[path = "ros/support.rs"]
mod support;
use heard::{forecast_values, level, msgs, status_named, statuses, wait_diagnostics};

use std::path::{Path, PathBuf};
use std::process::Command;
use std::time::Duration;

/// The two emulated-bus tests run one at a time: each has a daemon reading
/// two pty buses with 20 ms timeouts, and on a 2-core machine running both
/// beside the other tests' daemons starved the reads (timeouts counted as
/// bus errors, so the levels never returned to OK within the wait).
static SERVO_BUSES: tokio::sync::Mutex<()> = tokio::sync::Mutex::const_new(());

use serde_json::Value;
use support::{diag_value as kv, domain_id, rclpy_python, Peer};

mod daemon_common;
use daemon_common::{
    parse_lines, robot_joints, write_joints_gap_recording, Daemon, Line, MovingMotors, Scene,
    N_TICKS,
};

/// The noisy-bus test measures availability, which a neighbour's daemon
/// competing for the same cores would lower: it runs alone (write), the
/// others side by side (read).
static ALONE: tokio::sync::RwLock<()> = tokio::sync::RwLock::const_new(());

/// The bundled replay's episode: a ball hits the robot, which falls at 5.07 s.
const FALLING_FIXTURE: &str = "tests/fixtures/episode_00007.mcap";

fn repo(path: &str) -> PathBuf {
    Path::new(env!("CARGO_MANIFEST_DIR")).join(path)
}

/// The bundled replay config, pointed at absolute paths, on `domain`, loopback only.
fn replay_config(dir: &Path, domain: u16, edit: impl Fn(String) -> String) -> PathBuf {
    let text = std::fs::read_to_string(repo("config/replay.toml")).expect("config/replay.toml");
    let models = repo("models");
    let text = text
        .replace(
            "dir = \"models\"",
            &format!("dir = \"{}\"", models.display()),
        )
        .replace(
            &format!("recording = \"{FALLING_FIXTURE}\""),
            &format!("recording = \"{}\"", repo(FALLING_FIXTURE).display()),
        )
        .replace(
            "[ros]\nenabled = true",
            &format!("[ros]\nenabled = true\ndomain_id = {domain}\nlocalhost_only = true"),
        );
    assert!(
        text.contains("localhost_only = true"),
        "config/replay.toml changed shape"
    );
    let text = edit(text);
    let path = dir.join("fall_guard.toml");
    std::fs::write(&path, text).expect("write config");
    path
}

/// An rclpy listener (`ros_peer.py listen` with `args`) that has subscribed.
async fn listen(python: &PathBuf, domain: u16, args: &[&str]) -> Peer {
    let mut all = vec!["listen"];
    all.extend_from_slice(args);
    let mut listener = Peer::spawn(python, domain, &all);
    let (ready, _) = listener.wait_for("ready", Duration::from_secs(30)).await;
    assert!(
        ready.is_some(),
        "rclpy listener did not start: {}",
        listener.stderr()
    );
    listener
}

/// An rclpy listener of `/fall_guard/forecast` (every message logged) and
/// the latched `/fall_guard/fall_imminent`, for TIMEOUT_S seconds.
async fn listen_forecasts(python: &PathBuf, domain: u16, timeout_s: &str) -> Peer {
    listen(
        python,
        domain,
        &[
            "--sub",
            "/fall_guard/forecast:std_msgs/msg/Float32MultiArray:forecast_log",
            "--sub",
            "/fall_guard/fall_imminent:std_msgs/msg/Bool:latched",
            "--timeout",
            timeout_s,
        ],
    )
    .await
}

/// `fall-guard replay --config CONFIG` run to its end in real time, then
/// what LISTENER received up to 1.5 s later: (stdout, stderr, events).
async fn replay_heard_by(config: &Path, listener: &mut Peer) -> (Vec<u8>, String, Vec<Value>) {
    let daemon = Daemon::start(&["replay", "--config", config.to_str().expect("utf8")]);
    let (success, stdout, stderr) = tokio::task::spawn_blocking(move || daemon.wait())
        .await
        .expect("join");
    assert!(success, "replay failed: {stderr}");
    tokio::time::sleep(Duration::from_millis(1500)).await;
    (stdout, stderr, listener.drain())
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn replay_publishes_every_forecast_to_rclpy_and_warns_before_the_fall() {
    let _side_by_side = ALONE.read().await;
    let test = "replay_publishes_every_forecast_to_rclpy_and_warns_before_the_fall";
    let Some(python) = rclpy_python(test) else {
        return;
    };
    let domain = domain_id(0);
    let dir = tempfile::tempdir().expect("tempdir");
    let config = replay_config(dir.path(), domain, |t| t);

    let mut listener = listen_forecasts(&python, domain, "120").await;

    // Real time: the ring fills for 2 s, long enough for discovery.
    let (stdout, stderr, events) = replay_heard_by(&config, &mut listener).await;

    // What the daemon computed, tick by tick. A tick whose inference would
    // overrun (a loaded machine) is skipped and counted, never queued.
    let lines = parse_lines(&stdout);
    let finished = stderr
        .lines()
        .find(|l| l.contains("replay finished"))
        .unwrap_or_else(|| panic!("no summary in: {stderr}"));
    let count = |key: &str| -> usize {
        let at = finished.find(&format!(" {key}=")).expect("key") + key.len() + 2;
        finished[at..]
            .split(|c: char| !c.is_ascii_digit())
            .next()
            .and_then(|n| n.parse().ok())
            .unwrap_or_else(|| panic!("{key} in {finished}"))
    };
    let (ticks, dispatched, overruns) = (count("ticks"), count("dispatched"), count("overruns"));
    assert_eq!(ticks, dispatched + overruns, "{finished}");
    // Every tick is printed: a dispatched one with its forecast, a skipped
    // one as NaN with the reason.
    assert_eq!(lines.len(), ticks, "one line per tick");
    let skipped = lines
        .iter()
        .filter(|l| l.reason.starts_with("skipped"))
        .count();
    assert_eq!(skipped, overruns, "each overrun printed as a skipped tick");
    let valid: Vec<_> = lines.iter().filter(|l| l.valid).collect();
    assert!(
        valid.len() > 50,
        "{} valid ticks of {ticks} ({overruns} overran)",
        valid.len()
    );
    let first_valid = valid[0].tick;
    let onset_ns = fall_guard_runtime::recording::Recording::open(repo(FALLING_FIXTURE))
        .expect("falling fixture reads")
        .episode()
        .expect("episode metadata")
        .fall_onset_ns
        .expect("the falling fixture falls");
    let onset_tick = (onset_ns as f64 * 30.0 / 1e9).round() as i64;
    // Valid from the first full window to the fall (a skipped tick aside);
    // after it the robot lies on the floor, outside the training ranges,
    // where the guard may hold.
    assert!(lines.iter().all(|l| l.valid
        || l.tick < first_valid
        || l.tick >= onset_tick
        || l.reason.starts_with("skipped")));

    // The same episode offline, through the lab's `eval` (what
    // `fall-guard-lab eval --recording --per-tick-out` runs).
    let per_tick = dir.path().join("eval.jsonl");
    fall_guard_lab::commands::run_eval(
        &fall_guard_lab::commands::EvalOptions::per_tick(
            repo("models/emp.bpk"),
            repo(FALLING_FIXTURE),
            per_tick.clone(),
            // The input projection and the trajectory convolutions held as the
            // daemon holds them by default.
            fall_guard_runtime::model::ProjectionWeights::Int8,
        )
        .with_convolutions(fall_guard_runtime::model::Convolutions::Int8),
    )
    .expect("offline per-tick forecasts");
    let offline: std::collections::HashMap<i64, Vec<f32>> = std::fs::read_to_string(&per_tick)
        .expect("per-tick output")
        .lines()
        .map(|l| {
            let v: Value = serde_json::from_str(l).expect("json line");
            let p = v["probabilities"]
                .as_array()
                .expect("probabilities")
                .iter()
                .map(|x| x.as_f64().expect("number") as f32)
                .collect();
            (v["tick"].as_i64().expect("tick"), p)
        })
        .collect();
    assert_eq!(
        offline.keys().min().copied(),
        Some(first_valid),
        "offline and the daemon fill the window at the same tick"
    );

    // rclpy got every forecast the daemon computed, in order (NaN while the
    // ring filled), each equal to the offline one for its tick.
    let received: Vec<(f64, Vec<f32>)> = msgs(&events, "/fall_guard/forecast")
        .map(|e| (e["t"].as_f64().expect("t"), forecast_values(e)))
        .collect();
    let numbers: Vec<&(f64, Vec<f32>)> = received
        .iter()
        .filter(|(_, p)| p.iter().all(|v| !v.is_nan()))
        .collect();
    assert!(
        received.len() > numbers.len(),
        "the forecast is published while the ring fills too (NaN)"
    );
    assert_eq!(
        numbers.len(),
        valid.len(),
        "every forecast after the ring filled reached rclpy"
    );
    for (line, (_, got)) in valid.iter().zip(&numbers) {
        let want = &offline[&line.tick];
        assert_eq!(got.len(), 4, "one probability per horizon");
        for (g, w) in got.iter().zip(want) {
            assert!(
                (g - w).abs() <= 1e-5,
                "tick {}: rclpy got {got:?}, eval computed {want:?}",
                line.tick
            );
        }
    }

    // The safety signal: asserted while the ring fills (no valid forecast),
    // then a real warning before the fall onset (the recording's metadata, on
    // the 30 Hz grid): a valid forecast at the latch's horizon (1 s, index 1)
    // at or above EMP's trigger, with the latch on.
    let trigger = std::fs::read_to_string(repo("config/replay.toml"))
        .expect("config/replay.toml")
        .lines()
        .find_map(|l| {
            l.strip_prefix("emp = [")?
                .split(',')
                .next()?
                .trim()
                .parse::<f32>()
                .ok()
        })
        .expect("[model.thresholds].emp in config/replay.toml");
    // Not valid: asserted (a skipped tick leaves the latch as it was).
    assert!(lines
        .iter()
        .filter(|l| !l.valid && !l.reason.starts_with("skipped"))
        .all(|l| l.imminent));
    let first_warned = valid
        .iter()
        .find(|l| l.probabilities[1] >= trigger)
        .expect("no valid forecast reached the trigger on a falling episode");
    assert!(first_warned.imminent, "{first_warned:?}");
    assert!(
        first_warned.tick < onset_tick,
        "warned at tick {}, after the onset (tick {onset_tick})",
        first_warned.tick
    );
    // rclpy: the last fall_imminent received before the onset tick's
    // forecast is true.
    let onset_forecast_at = valid
        .iter()
        .zip(&numbers)
        .find(|(l, _)| l.tick >= onset_tick)
        .map(|(_, (t, _))| *t)
        .expect("a forecast at or after the onset");
    let at_onset = msgs(&events, "/fall_guard/fall_imminent")
        .filter(|e| e["t"].as_f64().is_some_and(|t| t <= onset_forecast_at))
        .last()
        .map(|e| e["msg"]["data"].clone());
    assert_eq!(
        at_onset,
        Some(Value::Bool(true)),
        "fall_imminent at the onset as rclpy saw it"
    );
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn rclpy_joint_states_and_plan_drive_the_daemon() {
    let _side_by_side = ALONE.read().await;
    let test = "rclpy_joint_states_and_plan_drive_the_daemon";
    let Some(python) = rclpy_python(test) else {
        return;
    };
    let domain = domain_id(1);
    let dir = tempfile::tempdir().expect("tempdir");
    // The same config, run live: joints and plan from ROS 2, no camera.
    let config = replay_config(dir.path(), domain, |t| t);
    let text = std::fs::read_to_string(&config).expect("config");
    assert!(text.contains("joints = \"ros\"") && text.contains("plan = \"ros\""));
    assert!(text.contains("camera = \"none\""));

    let mut listener = listen(
        &python,
        domain,
        &[
            "--sub",
            "/fall_guard/forecast:std_msgs/msg/Float32MultiArray:forecast",
            "--sub",
            "/diagnostics:diagnostic_msgs/msg/DiagnosticArray:diagnostics",
            // Numbers once the ring is full: wait for 60 of them, not for a
            // fixed message count. On a loaded machine the walker can miss
            // the 100 ms staleness limit, and the daemon then rightly
            // publishes NaN until the window refills with fresh ticks.
            "--count-finite",
            "/fall_guard/forecast=60",
            "--count",
            "/diagnostics=4",
            "--timeout",
            "90",
        ],
    )
    .await;

    let daemon = Daemon::start(&["run", "--config", config.to_str().expect("utf8")]);
    let joints = robot_joints().join(",");
    let mut walker = Peer::spawn(
        &python,
        domain,
        &["walk", "--joints", &joints, "--timeout", "90"],
    );

    let (done, seen) = listener.wait_for("done", Duration::from_secs(90)).await;
    drop(walker.drain());
    let (success, stdout, stderr) = tokio::task::spawn_blocking(move || daemon.stop())
        .await
        .expect("join");
    assert!(
        done.is_some(),
        "listener did not get its messages: {:?}\ndaemon: {stderr}\nwalker: {}",
        seen.last(),
        walker.stderr()
    );
    assert!(success, "daemon exit on SIGTERM: {stderr}");
    // Quiet logs with an rclpy peer on loopback: no per-sample DDS warning,
    // and a clean stop (no ERROR from leaving the DDS domain).
    assert!(
        !stderr.contains("No locators"),
        "DDS chatter in the default log: {stderr}"
    );
    let errors: Vec<&str> = stderr.lines().filter(|l| l.contains(" ERROR ")).collect();
    assert!(errors.is_empty(), "ERROR lines after SIGTERM: {errors:#?}");

    // Forecasts: numbers once the ring is full, from the MP network.
    let forecasts: Vec<Vec<f32>> = msgs(&seen, "/fall_guard/forecast")
        .map(forecast_values)
        .collect();
    let numeric = forecasts
        .iter()
        .filter(|p| p.iter().all(|v| v.is_finite()))
        .count();
    assert!(
        numeric >= 60,
        "{numeric} of {} forecasts were numbers",
        forecasts.len()
    );
    let lines = parse_lines(&stdout);
    assert!(
        lines.iter().any(|l| l.valid && l.ablation == "MP"),
        "no valid MP forecast printed"
    );

    // Diagnostics: the streams are seen at their rate, the model is MP and
    // valid. The latest message that says valid is judged: on a loaded
    // machine the walker can miss the 100 ms staleness limit once, and the
    // daemon then rightly reports that tick invalid.
    let diagnostics: Vec<&serde_json::Value> = msgs(&seen, "/diagnostics").collect();
    assert!(!diagnostics.is_empty(), "no diagnostics");
    let last = diagnostics
        .iter()
        .rev()
        .copied()
        .find(|d| {
            status_named(d, ": model")
                .and_then(|m| kv(m, "valid"))
                .as_deref()
                == Some("true")
        })
        .unwrap_or_else(|| {
            panic!(
                "no diagnostics message says the forecast is valid; last: {}",
                diagnostics[diagnostics.len() - 1]
            )
        });
    let named = |suffix: &str| {
        status_named(last, suffix).unwrap_or_else(|| panic!("no '{suffix}' status in {last}"))
    };
    let joints_rate: f64 = kv(named(": joints"), "rate_hz")
        .and_then(|r| r.parse().ok())
        .expect("joints rate");
    assert!(
        joints_rate > 15.0,
        "joint states at {joints_rate} Hz: {last}"
    );
    let plan_age = kv(named(": plan"), "age_ms").expect("plan age");
    assert_ne!(plan_age, "never", "plan never seen: {last}");
    let model = named(": model");
    assert_eq!(kv(model, "active_model").as_deref(), Some("MP"), "{last}");
    assert_eq!(kv(model, "valid").as_deref(), Some("true"), "{last}");
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn record_label_and_replay_live_ros_streams() {
    let _side_by_side = ALONE.read().await;
    let test = "record_label_and_replay_live_ros_streams";
    let Some(python) = rclpy_python(test) else {
        return;
    };
    let domain = domain_id(2);
    let dir = tempfile::tempdir().expect("tempdir");
    let config = replay_config(dir.path(), domain, |t| t);
    let out = dir.path().join("walk.mcap");
    let joints = robot_joints().join(",");
    // The walker's camera: a 320x240 JPEG, not the networks' 64x64.
    let jpeg_path = dir.path().join("camera.jpg");
    let jpeg = camera_jpeg(320, 240);
    std::fs::write(&jpeg_path, &jpeg).expect("write jpeg");
    let walker = Peer::spawn(
        &python,
        domain,
        &[
            "walk",
            "--joints",
            &joints,
            "--timeout",
            "30",
            "--camera-jpeg",
            jpeg_path.to_str().expect("utf8"),
        ],
    );
    // A second recorder beside it, on the camera too, with a config whose
    // network files do not exist: `record` loads no network.
    let no_models_dir = dir.path().join("no_models");
    std::fs::create_dir_all(&no_models_dir).expect("mkdir");
    let no_models = replay_config(&no_models_dir, domain, |t| {
        let models = format!("dir = \"{}\"", repo("models").display());
        assert!(t.contains(&models), "config/replay.toml changed shape");
        t.replace(&models, "dir = \"/nonexistent/fall-guard-models\"")
            .replace("camera = \"none\"", "camera = \"ros\"")
    });
    let camera_out = dir.path().join("camera.mcap");
    // 8 s of recording time: the recording starts at the first message, which
    // comes once the walker is discovered (seconds on a loaded machine), and
    // must still reach past the fall labelled at 4 s below.
    let record = |config: &Path, out: &Path| {
        Daemon::start(&[
            "record",
            "--config",
            config.to_str().expect("utf8"),
            "--out",
            out.to_str().expect("utf8"),
            "--duration-s",
            "8",
        ])
    };
    let daemon = record(&config, &out);
    let camera_daemon = record(&no_models, &camera_out);
    let (success, _, stderr) = tokio::task::spawn_blocking(move || daemon.wait())
        .await
        .expect("join");
    let (camera_success, _, camera_stderr) =
        tokio::task::spawn_blocking(move || camera_daemon.wait())
            .await
            .expect("join");
    drop(walker);
    assert!(success, "record failed: {stderr}");
    assert!(
        camera_success,
        "record without network files failed: {camera_stderr}"
    );

    // The camera as published: the same bytes, format and header.
    let rec = fall_guard_runtime::recording::Recording::open(&camera_out).expect("recording reads");
    assert!(rec.images.len() > 60, "{} frames", rec.images.len());
    assert!(
        rec.joint_states.len() > 60,
        "{} joint states",
        rec.joint_states.len()
    );
    for m in &rec.images {
        assert!(
            m.msg.data == jpeg,
            "recorded camera bytes differ from the published ones"
        );
        assert_eq!(m.msg.format, "jpeg");
        assert_eq!(m.msg.header.frame_id, "head_camera");
        assert_eq!(
            m.msg.header.stamp.to_ns(),
            m.log_time_ns,
            "logged at the header stamp"
        );
    }
    assert_eq!(
        rec.episode().expect("episode").rate_hz,
        30.0,
        "[robot].tick_rate_hz"
    );

    // The recording holds what the walker published, in the recording format.
    let rec = fall_guard_runtime::recording::Recording::open(&out).expect("recording reads");
    assert!(
        rec.joint_states.len() > 60,
        "{} joint states",
        rec.joint_states.len()
    );
    assert!(!rec.plans.is_empty(), "no plan recorded");
    assert!(rec.images.is_empty(), "no camera configured, no frames");
    assert_eq!(rec.joint_states[0].msg.name, robot_joints());
    assert!(rec
        .episode
        .as_ref()
        .is_some_and(|e| e.fall_onset_ns.is_none()));

    // Label a fall 4 s in, then replay it: the MP network forecasts it.
    let label = Command::new(env!("CARGO_BIN_EXE_fall-guard"))
        .args(["label", out.to_str().expect("utf8"), "--fall-at", "4"])
        .output()
        .expect("run label");
    assert!(
        label.status.success(),
        "{}",
        String::from_utf8_lossy(&label.stderr)
    );
    let rec =
        fall_guard_runtime::recording::Recording::open(&out).expect("labelled recording reads");
    let start = rec.start_ns().expect("messages");
    let onset = rec
        .episode()
        .expect("episode")
        .fall_onset_ns
        .expect("onset");
    assert_eq!(onset - start, 4_000_000_000);

    let replay = Command::new(env!("CARGO_BIN_EXE_fall-guard"))
        .args([
            "replay",
            "--config",
            config.to_str().expect("utf8"),
            "--max-speed",
        ])
        .args(["--recording", out.to_str().expect("utf8")])
        .env("RUST_LOG", "warn")
        .env("ROS_DOMAIN_ID", domain.to_string())
        .output()
        .expect("run replay");
    assert!(
        replay.status.success(),
        "{}",
        String::from_utf8_lossy(&replay.stderr)
    );
    let lines = parse_lines(&replay.stdout);
    assert!(
        lines.iter().any(|l| l.valid && l.ablation == "MP"),
        "no valid MP forecast from the recorded streams"
    );
}

/// A `width` x `height` JPEG of a colour gradient.
fn camera_jpeg(width: u32, height: u32) -> Vec<u8> {
    let rgb = (0..height)
        .flat_map(|y| (0..width).flat_map(move |x| [(x % 256) as u8, (y % 256) as u8, 90]))
        .collect();
    let frame = fall_guard_runtime::frame::Frame::from_rgb(width, height, rgb).expect("frame");
    fall_guard_runtime::frame::encode_jpeg(&frame, 85).expect("jpeg")
}

/// Waits for a `/diagnostics` message whose model status says `valid` =
/// `want`; returns it with the messages seen meanwhile.
async fn wait_validity(
    listener: &mut Peer,
    want: bool,
    timeout: Duration,
) -> (Option<Value>, Vec<Value>) {
    let want = if want { "true" } else { "false" };
    wait_diagnostics(listener, timeout, |e| {
        status_named(e, ": model")
            .and_then(|m| kv(m, "valid"))
            .as_deref()
            == Some(want)
    })
    .await
}

fn joints_status(diag: &Value) -> &Value {
    status_named(diag, ": joints").unwrap_or_else(|| panic!("no joints status in {diag}"))
}

/// The real robot's config shape: joints from the two emulated buses, no
/// camera, no plan (the P network); `lower_keys` and `upper_keys` are added
/// to each bus's table.
fn servo_config(
    dir: &Path,
    domain: u16,
    buses: &fall_guard_testkit::emulator::PoppyBuses,
    lower_keys: &str,
    upper_keys: &str,
) -> PathBuf {
    let tables = format!(
        "\n[dynamixel]\nrate_hz = 50.0\n\n[dynamixel.buses.lower]\nport = \"{}\"\n{lower_keys}\n[dynamixel.buses.upper]\nport = \"{}\"\n{upper_keys}",
        buses.lower.port_path().display(),
        buses.upper.port_path().display()
    );
    replay_config(dir, domain, move |t| {
        t.replace("joints = \"ros\"", "joints = \"dynamixel\"")
            .replace("plan = \"ros\"", "plan = \"none\"")
            + &tables
    })
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn servo_faults_make_forecasts_not_valid_and_the_daemon_recovers() {
    let _side_by_side = ALONE.read().await;
    let _one_at_a_time = SERVO_BUSES.lock().await;
    use fall_guard_runtime::robot::JointTable;
    use fall_guard_testkit::emulator::{Fault, PoppyBuses};

    let test = "servo_faults_make_forecasts_not_valid_and_the_daemon_recovers";
    let Some(python) = rclpy_python(test) else {
        return;
    };
    let domain = domain_id(3);
    let dir = tempfile::tempdir().expect("tempdir");
    let table = JointTable::poppy_humanoid();
    let buses = PoppyBuses::start(&table, dir.path()).expect("emulated buses");
    buses.stand(&table).expect("standing pose");
    // The lower bus uses the USB2AX sync read, the upper one per-motor reads
    // (the only ones that carry each motor's error bits).
    let config = servo_config(
        dir.path(),
        domain,
        &buses,
        "timeout_ms = 20\n",
        "timeout_ms = 20\nsync_read = false\n",
    );
    let mut listener = listen(
        &python,
        domain,
        &[
            "--sub",
            "/diagnostics:diagnostic_msgs/msg/DiagnosticArray:diagnostics",
            "--sub",
            "/joint_states:sensor_msgs/msg/JointState:sensor_data",
            "--timeout",
            "120",
        ],
    )
    .await;
    let daemon = Daemon::start(&["run", "--config", config.to_str().expect("utf8")]);
    let long = Duration::from_secs(30);

    // Healthy buses: valid forecasts once the ring is full (2 s), and the
    // daemon publishes what it reads on /joint_states.
    let (ok, seen) = wait_validity(&mut listener, true, long).await;
    let ok = ok.unwrap_or_else(|| panic!("never valid: {:?}", seen.last()));
    let joint_states: Vec<&Value> = msgs(&seen, "/joint_states").collect();
    assert!(
        !joint_states.is_empty(),
        "no /joint_states from the servo source"
    );
    let names: Vec<String> = joint_states[0]["msg"]["name"]
        .as_array()
        .expect("names")
        .iter()
        .map(|n| n.as_str().expect("name").to_owned())
        .collect();
    assert_eq!(names, robot_joints());
    let errors_before: u64 = kv(joints_status(&ok), "errors")
        .and_then(|e| e.parse().ok())
        .expect("errors key");

    // Faults that stop the reads: not valid while they last, valid again after.
    type Switch<'a> = Box<dyn Fn(bool) + 'a>;
    let faults: Vec<(&str, Switch)> = vec![
        (
            "no reply",
            Box::new(|on| buses.lower.set_fault(on.then_some(Fault::NoReply))),
        ),
        (
            "bad checksums",
            Box::new(|on| buses.upper.set_fault(on.then_some(Fault::BadChecksum))),
        ),
        (
            "unplugged adapter",
            Box::new(|on| {
                if on {
                    buses.upper.unplug().expect("unplug")
                } else {
                    buses.upper.replug().expect("replug")
                }
            }),
        ),
    ];
    for (name, fault) in &faults {
        fault(true);
        let (bad, seen) = wait_validity(&mut listener, false, long).await;
        assert!(
            bad.is_some(),
            "{name}: forecasts stayed valid: {:?}",
            seen.last()
        );
        fault(false);
        let (good, seen) = wait_validity(&mut listener, true, long).await;
        if good.is_none() {
            let (_, _, stderr) = daemon.stop();
            panic!("{name}: no recovery: {:?}\ndaemon: {stderr}", seen.last());
        }
    }
    tokio::time::sleep(Duration::from_millis(600)).await;
    drop(listener.drain());
    let (now, _) = wait_validity(&mut listener, true, long).await;
    let errors_now: u64 = kv(joints_status(&now.expect("valid")), "errors")
        .and_then(|e| e.parse().ok())
        .expect("errors key");
    assert!(
        errors_now > errors_before,
        "faults not counted: {errors_before} -> {errors_now}"
    );

    // Faults the reader works through: garbage before the replies (skipped
    // up to the next FF FF header) and an error bit (overheating) on one
    // motor. Both are counted; the readings go on.
    buses
        .lower
        .set_fault(Some(Fault::Garbage(vec![0x13, 0x00, 0x42])));
    buses.upper.set_error_bits(37, 0x04).expect("error bit");
    tokio::time::sleep(Duration::from_millis(1500)).await;
    buses.lower.set_fault(None);
    buses.upper.set_error_bits(37, 0).expect("clear");
    // Reports from before are queued: skip them, then take the second one
    // (the servo counters reach the diagnostics every 500 ms).
    tokio::time::sleep(Duration::from_millis(600)).await;
    drop(listener.drain());
    let _ = wait_validity(&mut listener, true, long).await;
    let (after, seen) = wait_validity(&mut listener, true, long).await;
    let after = after.unwrap_or_else(|| {
        panic!(
            "not valid after garbage and an error bit: {:?}",
            seen.last()
        )
    });
    let errors_after: u64 = kv(joints_status(&after), "errors")
        .and_then(|e| e.parse().ok())
        .expect("errors key");
    assert!(
        errors_after > errors_now,
        "garbage and error bit not counted on /diagnostics: {errors_now} -> {errors_after}"
    );

    let (success, stdout, stderr) = tokio::task::spawn_blocking(move || daemon.stop())
        .await
        .expect("join");
    assert!(success, "daemon exit: {stderr}");
    assert!(!stderr.contains("panicked"), "{stderr}");
    let lines = parse_lines(&stdout);
    assert!(lines.iter().any(|l| l.valid && l.ablation == "P"));
    assert!(
        lines
            .iter()
            .any(|l| !l.valid && l.reason.contains("joints")),
        "no invalid line naming the joints"
    );
}

/// Name, level and message of every status of the last `/diagnostics`
/// message in `events`, for failure messages.
fn last_statuses(events: &[Value]) -> String {
    statuses(msgs(events, "/diagnostics").last())
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn one_missing_servo_degrades_per_motor_and_diagnostics_recover_to_ok() {
    let _side_by_side = ALONE.read().await;
    let _one_at_a_time = SERVO_BUSES.lock().await;
    use fall_guard_runtime::robot::JointTable;
    use fall_guard_testkit::emulator::{Fault, PoppyBuses};

    let test = "one_missing_servo_degrades_per_motor_and_diagnostics_recover_to_ok";
    let Some(python) = rclpy_python(test) else {
        return;
    };
    let domain = domain_id(5);
    let dir = tempfile::tempdir().expect("tempdir");
    let table = JointTable::poppy_humanoid();
    let buses = PoppyBuses::start(&table, dir.path()).expect("emulated buses");
    buses.stand(&table).expect("standing pose");
    // The upper bus is a plain USB-serial adapter: the USB2AX sync read is
    // configured (the default) but never answered, so the reader falls back
    // to one READ_DATA per motor. A mode, not a fault.
    buses.upper.set_sync_read_supported(false);
    let upper_port = buses.upper.port_path().display().to_string();
    let config = servo_config(dir.path(), domain, &buses, "", "");
    let mut listener = listen(
        &python,
        domain,
        &[
            "--sub",
            "/diagnostics:diagnostic_msgs/msg/DiagnosticArray:diagnostics",
            "--sub",
            "/joint_states:sensor_msgs/msg/JointState:sensor_data",
            "--sub",
            "/fall_guard/forecast:std_msgs/msg/Float32MultiArray:forecast",
            "--sub",
            "/fall_guard/fall_imminent:std_msgs/msg/Bool:latched",
            "--timeout",
            "300",
        ],
    )
    .await;
    let daemon = Daemon::start(&["run", "--config", config.to_str().expect("utf8")]);
    let long = Duration::from_secs(30);
    // Every level OK needs 10 s without a single error on either bus: on a
    // loaded 2-core machine a per-motor read can time out now and then.
    let ok_wait = Duration::from_secs(120);
    let stop = |daemon: Daemon| daemon.stop().2;
    let status = |d: &Value, suffix: &str| -> Value {
        status_named(d, suffix)
            .unwrap_or_else(|| panic!("no '{suffix}' status in {d}"))
            .clone()
    };
    let all_ok = |d: &Value| {
        [
            ": joints",
            ": servo bus lower",
            ": servo bus upper",
            ": model",
        ]
        .iter()
        .all(|s| status_named(d, s).is_some_and(|st| level(st) == 0))
    };

    // Healthy, with the plain adapter: every status OK (the model runs P,
    // which is what plan = "none" and camera = "none" ask for).
    let (ok, seen) = wait_diagnostics(&mut listener, ok_wait, all_ok).await;
    let Some(ok) = ok else {
        let stderr = stop(daemon);
        panic!("never all OK: {}\ndaemon: {stderr}", last_statuses(&seen));
    };
    let upper_bus = status(&ok, ": servo bus upper");
    assert_eq!(
        kv(&upper_bus, "adapter_mode").as_deref(),
        Some("read_data_fallback")
    );
    assert_eq!(upper_bus["hardware_id"], upper_port);
    assert_eq!(
        kv(&status(&ok, ": servo bus lower"), "adapter_mode").as_deref(),
        Some("usb2ax_sync_read")
    );
    assert_eq!(
        kv(&status(&ok, ": model"), "active_model").as_deref(),
        Some("P")
    );

    // Motor 36 (head_z) stops answering.
    buses.upper.set_present(36, false).expect("motor 36");
    let (missing, seen) = wait_diagnostics(&mut listener, long, |d| {
        status_named(d, ": model")
            .and_then(|m| kv(m, "invalid_reason"))
            .is_some_and(|r| r.contains("head_z"))
    })
    .await;
    let Some(missing) = missing else {
        let stderr = stop(daemon);
        panic!(
            "missing motor not named: {:?}\ndaemon: {stderr}",
            seen.last()
        );
    };
    // Its last value held until older than joints_stale_ms: the joints
    // stream is then STALE for that joint alone.
    let joints = status(&missing, ": joints");
    assert_eq!(level(&joints), 3, "{joints}");
    assert_eq!(kv(&joints, "joints_stale").as_deref(), Some("head_z"));
    assert_eq!(kv(&joints, "joints_not_read").as_deref(), Some(""));
    assert!(
        joints["message"]
            .as_str()
            .is_some_and(|m| m.contains("head_z")),
        "{joints}"
    );
    let upper_bus = status(&missing, ": servo bus upper");
    assert_eq!(level(&upper_bus), 1, "{upper_bus}");
    assert_eq!(kv(&upper_bus, "missing_ids").as_deref(), Some("[36]"));
    assert_eq!(kv(&upper_bus, "missing_joints").as_deref(), Some("head_z"));
    assert_eq!(level(&status(&missing, ": servo bus lower")), 0);
    // Meanwhile: /joint_states goes on with the other 24 joints, the
    // forecast is NaN and fall_imminent asserted.
    tokio::time::sleep(Duration::from_millis(500)).await;
    let during = listener.drain();
    let partial: Vec<Vec<String>> = msgs(&during, "/joint_states")
        .map(|m| {
            m["msg"]["name"]
                .as_array()
                .expect("names")
                .iter()
                .map(|n| n.as_str().expect("name").to_owned())
                .collect()
        })
        .collect();
    assert!(
        partial.len() >= 5,
        "{} joint states in 0.5 s",
        partial.len()
    );
    let expected: Vec<String> = robot_joints()
        .into_iter()
        .filter(|n| n != "head_z")
        .collect();
    assert!(
        partial.iter().all(|names| *names == expected),
        "{:?}",
        partial.last()
    );
    let forecasts: Vec<Vec<f32>> = msgs(&during, "/fall_guard/forecast")
        .map(forecast_values)
        .collect();
    assert!(!forecasts.is_empty());
    assert!(
        forecasts.iter().all(|p| p.iter().all(|v| v.is_nan())),
        "{forecasts:?}"
    );
    let imminent: Vec<bool> = msgs(&seen, "/fall_guard/fall_imminent")
        .chain(msgs(&during, "/fall_guard/fall_imminent"))
        .map(|m| m["msg"]["data"].as_bool().expect("Bool"))
        .collect();
    assert_eq!(imminent.last(), Some(&true), "{imminent:?}");

    // It answers again: valid after a refilled window, then every level
    // back to OK once the missing reads left the 10 s error window.
    buses.upper.set_present(36, true).expect("motor 36");
    let (back, seen) = wait_diagnostics(&mut listener, ok_wait, all_ok).await;
    if back.is_none() {
        let stderr = stop(daemon);
        panic!(
            "no recovery to OK: {}\ndaemon: {stderr}",
            last_statuses(&seen)
        );
    }
    let names: Vec<&Value> = msgs(&seen, "/joint_states").collect();
    let last = names.last().expect("joint states");
    assert_eq!(
        last["msg"]["name"].as_array().map(Vec::len),
        Some(25),
        "{last}"
    );

    // Garbage on the lower bus: counted, WARN while within the window, OK after.
    buses
        .lower
        .set_fault(Some(Fault::Garbage(vec![0x13, 0x00, 0x42])));
    let (garbage, seen) = wait_diagnostics(&mut listener, long, |d| {
        status_named(d, ": servo bus lower").is_some_and(|b| {
            level(b) == 1 && kv(b, "garbage_bytes_per_s").is_some_and(|g| g != "0.00")
        })
    })
    .await;
    buses.lower.set_fault(None);
    if garbage.is_none() {
        let stderr = stop(daemon);
        panic!("garbage not reported: {:?}\ndaemon: {stderr}", seen.last());
    }
    let (clean, seen) = wait_diagnostics(&mut listener, ok_wait, all_ok).await;
    let (success, _, stderr) = tokio::task::spawn_blocking(move || daemon.stop())
        .await
        .expect("join");
    assert!(
        clean.is_some(),
        "no recovery after garbage: {:?}\ndaemon: {stderr}",
        seen.last()
    );
    assert!(success, "daemon exit: {stderr}");
    assert!(!stderr.contains("panicked"), "{stderr}");
}

/// Lengths of the runs of NaN (`true`) and number (`false`) forecasts.
fn nan_runs(forecasts: &[Vec<f32>]) -> Vec<(bool, usize)> {
    let mut runs: Vec<(bool, usize)> = Vec::new();
    for p in forecasts {
        let nan = p.iter().all(|v| v.is_nan());
        assert!(
            nan || p.iter().all(|v| v.is_finite()),
            "a forecast mixes NaN and numbers: {p:?}"
        );
        match runs.last_mut() {
            Some((n, len)) if *n == nan => *len += 1,
            _ => runs.push((nan, 1)),
        }
    }
    runs
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn joints_gap_publishes_nan_forecasts_until_the_window_refills() {
    let _side_by_side = ALONE.read().await;
    let test = "joints_gap_publishes_nan_forecasts_until_the_window_refills";
    let Some(python) = rclpy_python(test) else {
        return;
    };
    let domain = domain_id(4);
    // Small test networks, replayed in real time; thresholds no untrained
    // network reaches, so the latch is off whenever the forecast is valid.
    let scene = Scene::new("joints_gap.mcap");
    let config = std::fs::read_to_string(&scene.config)
        .expect("config")
        .replace(
            "trigger = 0.6\nrelease = 0.3",
            "trigger = 0.999\nrelease = 0.998",
        )
        .replace("max_speed = true", "max_speed = false")
        .replace(
            "[ros]\nenabled = false",
            &format!("[ros]\nenabled = true\ndomain_id = {domain}\nlocalhost_only = true"),
        );
    assert!(config.contains("trigger = 0.999") && config.contains("enabled = true"));
    std::fs::write(&scene.config, config).expect("config");
    // 5 s at 30 Hz; joint states gone from 2.0 s to 2.5 s.
    write_joints_gap_recording(&scene);

    let mut listener = listen_forecasts(&python, domain, "60").await;
    let (stdout, _, events) = replay_heard_by(&scene.config, &mut listener).await;

    // What the daemon decided, per dispatched tick: valid, then the gap
    // (stale, then refilling), then valid again.
    let lines = parse_lines(&stdout);
    let first_valid = lines.iter().position(|l| l.valid).expect("a valid tick");
    let gap_start = first_valid
        + lines[first_valid..]
            .iter()
            .position(|l| !l.valid)
            .expect("the joints gap makes ticks invalid");
    let gap_len = lines[gap_start..]
        .iter()
        .position(|l| l.valid)
        .expect("valid again after the gap");
    let gap: &[Line] = &lines[gap_start..gap_start + gap_len];
    let after = &lines[gap_start + gap_len..];
    assert!(gap[0].reason.contains("joints stale"), "{:?}", gap[0]);
    let refilling: Vec<&Line> = gap
        .iter()
        .filter(|l| l.reason.contains("joints back, window refilling"))
        .collect();
    assert!(!refilling.is_empty(), "no refilling tick: {gap:?}");
    // Fresh again from the first refilling tick: valid N ticks later, not before.
    let back = refilling[0].tick;
    assert_eq!(
        after[0].tick,
        back + N_TICKS as i64 - 1,
        "first valid tick after the gap"
    );
    assert!(after.iter().all(|l| l.valid), "one gap only");
    assert!(gap.iter().all(|l| l.imminent) && !after[0].imminent);

    // What rclpy read on /fall_guard/forecast: numbers, then NaN for exactly
    // the gap's ticks, then numbers for every tick after it.
    let forecasts: Vec<Vec<f32>> = msgs(&events, "/fall_guard/forecast")
        .map(forecast_values)
        .collect();
    let runs = nan_runs(&forecasts);
    assert!(runs.len() >= 3, "runs of NaN/numbers: {runs:?}");
    let tail = &runs[runs.len() - 3..];
    assert_eq!(
        tail,
        [(false, tail[0].1), (true, gap.len()), (false, after.len())],
        "NaN exactly while the daemon said not valid; runs {runs:?}"
    );

    // fall_imminent as documented: off while valid and low, asserted
    // through the gap, off again once the window has refilled.
    let imminent: Vec<bool> = msgs(&events, "/fall_guard/fall_imminent")
        .map(|e| e["msg"]["data"].as_bool().expect("bool"))
        .collect();
    assert!(
        imminent.ends_with(&[false, true, false]),
        "fall_imminent received: {imminent:?}"
    );
}

/// The seeded reply faults of the noisy-bus check, as measured on a bus
/// that lost every forecast to NaN under the rule that a cycle missing
/// any motor is a gap: 5% of each motor's replies dropped, 2% with a bad
/// checksum, 5% with garbage bytes before them.
fn bus_noise(seed: u64) -> fall_guard_testkit::emulator::ReplyNoise {
    fall_guard_testkit::emulator::ReplyNoise {
        seed,
        p_drop: 0.05,
        p_corrupt: 0.02,
        p_garbage: 0.05,
    }
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn a_noisy_servo_bus_keeps_the_forecast_and_publishes_only_values_read() {
    let _alone = ALONE.write().await;
    let _one_at_a_time = SERVO_BUSES.lock().await;
    use std::sync::Arc;

    use fall_guard_runtime::robot::JointTable;
    use fall_guard_testkit::emulator::PoppyBuses;

    let test = "a_noisy_servo_bus_keeps_the_forecast_and_publishes_only_values_read";
    let Some(python) = rclpy_python(test) else {
        return;
    };
    let domain = domain_id(6);
    let dir = tempfile::tempdir().expect("tempdir");
    let table = JointTable::poppy_humanoid();
    let buses = Arc::new(PoppyBuses::start(&table, dir.path()).expect("emulated buses"));
    buses.stand(&table).expect("standing pose");
    // Both buses read with the USB2AX sync read (the default); a motor's
    // lost reply gives FF bytes in the adapter's answer (12% of them), and
    // the reader asks again for those motors in the same cycle (1.4% lost
    // twice). A failing-motor share below that: the motors are named at
    // WARN while the forecast stays valid on the values held.
    buses.lower.set_noise(Some(bus_noise(11)));
    buses.upper.set_noise(Some(bus_noise(12)));
    let tables = format!(
        "\n[dynamixel]\nrate_hz = 50.0\nwarn_missed_share = 0.005\n\n[dynamixel.buses.lower]\nport = \"{}\"\n\n[dynamixel.buses.upper]\nport = \"{}\"\n",
        buses.lower.port_path().display(),
        buses.upper.port_path().display()
    );
    // Joints from the buses, the plan from a ROS 2 planner, no camera: MP.
    let config = replay_config(dir.path(), domain, move |t| {
        t.replace("joints = \"ros\"", "joints = \"dynamixel\"") + &tables
    });

    // The motors move all along; every raw position a motor held is kept.
    let motors = MovingMotors::start(Arc::clone(&buses), &table);
    let held = Arc::clone(&motors.held);

    let mut listener = listen(
        &python,
        domain,
        &[
            "--sub",
            "/diagnostics:diagnostic_msgs/msg/DiagnosticArray:diagnostics",
            "--sub",
            "/joint_states:sensor_msgs/msg/JointState:sensor_data",
            "--sub",
            "/fall_guard/forecast:std_msgs/msg/Float32MultiArray:forecast_log",
            "--timeout",
            "120",
        ],
    )
    .await;
    let daemon = Daemon::start(&["run", "--config", config.to_str().expect("utf8")]);
    // The planner's own joint states go elsewhere: /joint_states is the
    // daemon's, from the buses.
    let joints = robot_joints().join(",");
    let mut planner = Peer::spawn(
        &python,
        domain,
        &[
            "walk",
            "--joints",
            &joints,
            "--joint-states",
            "/planner/joint_states",
            "--timeout",
            "120",
        ],
    );

    // Valid forecasts on the noisy buses once the ring is full and the
    // plan has come (discovery), then 20 s of them.
    let (first, seen) = wait_validity(&mut listener, true, Duration::from_secs(60)).await;
    if first.is_none() {
        let (_, _, stderr) = daemon.stop();
        panic!(
            "never valid on the noisy buses: {}\ndaemon: {stderr}\nplanner: {}",
            last_statuses(&seen),
            planner.stderr()
        );
    }
    let mut events = seen;
    let noisy_until = std::time::Instant::now() + Duration::from_secs(20);
    while let Some(e) = listener
        .next_event(noisy_until.saturating_duration_since(std::time::Instant::now()))
        .await
    {
        events.push(e);
    }
    let noisy_diag = msgs(&events, "/diagnostics")
        .last()
        .cloned()
        .expect("diagnostics");

    // The lower bus unplugged: no joint of it is read any more.
    let unplugged_s = std::time::SystemTime::now()
        .duration_since(std::time::UNIX_EPOCH)
        .expect("clock")
        .as_secs_f64();
    buses.lower.unplug().expect("unplug");
    tokio::time::sleep(Duration::from_millis(1500)).await;
    events.extend(listener.drain());
    motors.stop();
    drop(planner.drain());
    let (success, stdout, stderr) = tokio::task::spawn_blocking(move || daemon.stop())
        .await
        .expect("join");
    assert!(success, "daemon exit: {stderr}");

    // What the daemon decided per tick: after the ring first filled and
    // before the unplug, at least 95% valid (on held joint values; P until
    // the plan comes, MP from then on).
    let lines = parse_lines(&stdout);
    let filled = lines
        .iter()
        .position(|l| !l.reason.contains("ring filling"))
        .expect("the ring filled");
    let noisy: Vec<&Line> = lines[filled..]
        .iter()
        .filter(|l| l.stamp_s < unplugged_s)
        .collect();
    // 20 s of noise from the first valid diagnostics on: about 600 ticks
    // after the ring filled (the diagnostics come at 1 Hz, so the first
    // valid one may come with the first valid tick); a few ticks less when
    // the machine is slow to hand over the listener's events.
    assert!(
        noisy.len() >= 570,
        "{} ticks on the noisy buses (at least 19 s)",
        noisy.len()
    );
    // A joint older than joints_stale_ms makes its ticks NaN. Each
    // position is stamped when its bus was asked for it and the bound is
    // 150 ms (three lost read cycles in a row plus the hand-over), so the
    // noise alone makes none; under the former 100 ms bound and cycle-start
    // stamps, two lost cycles in a row made 118 and 132 ms in one of seven
    // idle runs, each a 2 s refill. A brief gap (a late thread) is bridged:
    // its own ticks NaN, counted in the share. A gap that has to be waited
    // out (the window refilling) fails.
    let stale = |i: usize| noisy[i].reason.starts_with("joints stale");
    let gaps: Vec<usize> = (0..noisy.len())
        .filter(|&i| stale(i) && (i == 0 || !stale(i - 1)))
        .collect();
    let stale_ticks = (0..noisy.len()).filter(|&i| stale(i)).count();
    let refilling: Vec<&str> = noisy
        .iter()
        .filter(|l| l.reason.contains("joints back, window refilling"))
        .map(|l| l.reason.as_str())
        .collect();
    let valid = noisy.iter().filter(|l| l.valid).count();
    eprintln!(
        "noisy buses: {valid} of {} forecasts valid after the ring filled ({:.1}%), {} joint gaps ({stale_ticks} stale ticks: {:?}), {} ticks refilling",
        noisy.len(),
        100.0 * valid as f64 / noisy.len() as f64,
        gaps.len(),
        gaps.iter().map(|&i| noisy[i].reason.as_str()).collect::<Vec<_>>(),
        refilling.len()
    );
    assert!(
        refilling.is_empty(),
        "a joint gap on the noisy buses was waited out: {:?}",
        &refilling[..refilling.len().min(3)]
    );
    let invalid: Vec<&str> = noisy
        .iter()
        .filter(|l| !l.valid)
        .map(|l| l.reason.as_str())
        .collect();
    assert!(
        valid as f64 >= 0.95 * noisy.len() as f64,
        "{valid} of {} forecasts valid on the noisy buses; not valid: {:?}",
        noisy.len(),
        &invalid[..invalid.len().min(20)]
    );
    assert!(
        noisy.iter().any(|l| l.valid && l.ablation == "MP"),
        "no valid MP forecast: the plan never came"
    );
    // What rclpy read: numbers for (at least) 95% of the forecasts after
    // the first number.
    let forecasts: Vec<Vec<f32>> = msgs(&events, "/fall_guard/forecast")
        .map(forecast_values)
        .collect();
    let runs = nan_runs(&forecasts);
    let first_number = forecasts
        .iter()
        .position(|p| p.iter().all(|v| v.is_finite()))
        .expect("a number on /fall_guard/forecast");
    let heard = &forecasts[first_number..];
    let numbers = heard
        .iter()
        .filter(|p| p.iter().all(|v| v.is_finite()))
        .count();
    // The tail holds the NaN of the unplugged bus (1.5 s, 45 ticks).
    assert!(
        numbers as f64 >= 0.95 * (heard.len().saturating_sub(45)) as f64,
        "{numbers} numbers of {} forecasts heard; runs {runs:?}",
        heard.len()
    );

    // Unplugged: every forecast stamped 0.5 s after the unplug or later is
    // NaN, naming the lower bus's joints as too old.
    let after: Vec<&Line> = lines
        .iter()
        .filter(|l| l.stamp_s >= unplugged_s + 0.5)
        .collect();
    assert!(after.len() >= 15, "{} ticks after the unplug", after.len());
    assert!(
        after.iter().all(|l| !l.valid
            && l.reason.contains("joints stale")
            && l.reason.contains("l_knee_y")),
        "{:?}",
        after
            .iter()
            .find(|l| l.valid || !l.reason.contains("l_knee_y"))
    );

    // /joint_states: only positions a bus served, each one a raw position
    // its motor held (no held or made-up value), with the joints a cycle
    // missed left out.
    let held = held.lock().expect("held");
    let mut states = 0;
    let mut partial = 0;
    for m in msgs(&events, "/joint_states") {
        states += 1;
        let names = m["msg"]["name"].as_array().expect("names");
        let positions = m["msg"]["position"].as_array().expect("positions");
        assert_eq!(names.len(), positions.len());
        partial += usize::from(names.len() < 25);
        for (name, position) in names.iter().zip(positions) {
            let name = name.as_str().expect("name");
            let joint = &table.joints()[table.index_of(name).expect("a robot joint")];
            let got = position.as_f64().expect("position");
            // The f32 the daemon read, as an f64 (JSON's parse may be off
            // by an ulp; raw positions are 1.5 mrad apart).
            assert!(
                held[&joint.id]
                    .iter()
                    .any(|&raw| (f64::from(joint.raw_to_rad(raw) as f32) - got).abs() < 1e-9),
                "{name} = {got} rad on /joint_states: no raw position motor {} held",
                joint.id
            );
        }
    }
    assert!(states >= 500, "{states} joint states heard");
    assert!(partial > 0, "no cycle missed a motor: is the noise on?");

    // /diagnostics on the noisy buses: per motor the age of its value and
    // its share of missed reads; every motor above the 0.5% share is named
    // at WARN while the forecast is valid.
    let model = status_named(&noisy_diag, ": model").expect("model status");
    let lower = status_named(&noisy_diag, ": servo bus lower").expect("lower bus status");
    assert_eq!(kv(model, "valid").as_deref(), Some("true"), "{model}");
    // The joints stream counts the gaps: none waited out.
    let joints_status = status_named(&noisy_diag, ": joints").expect("joints status");
    assert_eq!(kv(joints_status, "max_held_ticks").as_deref(), Some("3"));
    assert_eq!(
        kv(joints_status, "gaps_refilled").as_deref(),
        Some("0"),
        "{joints_status}"
    );
    assert_eq!(level(lower), 1, "{lower}");
    assert!(
        lower["message"]
            .as_str()
            .is_some_and(|m| m.contains("reads failing persistently")),
        "{lower}"
    );
    let failing = kv(lower, "failing_motors").unwrap_or_default();
    for joint in table.joints().iter().filter(|j| j.bus == "lower") {
        let share: f64 = kv(lower, &format!("missed_share.{}", joint.name))
            .and_then(|s| s.parse().ok())
            .unwrap_or_else(|| panic!("no missed share of {}: {lower}", joint.name));
        assert!((0.0..=0.1).contains(&share), "{}: {share}", joint.name);
        let age: f64 = kv(lower, &format!("age_ms.{}", joint.name))
            .and_then(|s| s.parse().ok())
            .unwrap_or_else(|| panic!("no age of {}: {lower}", joint.name));
        assert!(age >= 0.0, "{}: {age}", joint.name);
        if share > 0.005 {
            assert!(
                failing.contains(&format!("{} ({})", joint.id, joint.name)),
                "{} missed {share} of its reads, not named: {failing}",
                joint.name
            );
        }
    }
    let counts = buses.upper.noise_counts();
    assert!(
        counts.dropped > 0 && counts.corrupted > 0 && counts.garbage > 0,
        "{counts:?}"
    );
}
