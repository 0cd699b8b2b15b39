//! Shared set-up of the daemon tests: small untrained networks (clearly
//! labelled `trained_on = "untrained (test)"`), synthetic recordings written
//! by the data plane's writer, configs, and running the real binary.

#![allow(dead_code)]

use std::collections::{BTreeMap, BTreeSet};
use std::path::{Path, PathBuf};
use std::process::{Command, Output};
use std::sync::atomic::{AtomicBool, Ordering};
use std::sync::{Arc, Mutex};
use std::time::Duration;

use fall_guard_runtime::model::{cpu_device, save_model, Ablation, Emp, ModelConfig, ModelMeta};
use fall_guard_runtime::msgs::{DiagnosticArray, DiagnosticStatus};
use fall_guard_runtime::recording::{topics, Recording, RecordingWriter};
use fall_guard_runtime::robot::JointTable;
use fall_guard_testkit::emulator::PoppyBuses;
use fall_guard_testkit::recordings::learnable_episode;

/// Window and horizons of the test networks: small, so a replay is quick.
pub const N_TICKS: usize = 16;
pub const HORIZONS_TICKS: [usize; 2] = [8, 16];
/// 8 and 16 ticks at 30 Hz.
pub const HORIZONS_MS: [u32; 2] = [267, 533];
pub const FRAME_SIZE: u32 = 32;
pub const RATE_HZ: f64 = 30.0;

pub fn robot_joints() -> Vec<String> {
    JointTable::poppy_humanoid().names()
}

/// Writes untrained EMP, MP, EP and P networks for `joints` into `dir`.
pub fn write_models(dir: &Path, joints: &[String]) {
    std::fs::create_dir_all(dir).expect("models dir");
    let device = cpu_device();
    for (ablation, file) in [
        (Ablation::EMP, "emp.fgm"),
        (Ablation::MP, "mp.fgm"),
        (Ablation::EP, "ep.fgm"),
        (Ablation::P, "p.fgm"),
    ] {
        let config = ModelConfig::lite(
            N_TICKS,
            joints.len(),
            HORIZONS_TICKS.to_vec(),
            FRAME_SIZE as usize,
        );
        let mut meta = ModelMeta::new(config.clone(), ablation, RATE_HZ, joints.to_vec());
        meta.trained_on = "untrained (test)".into();
        let emp = Emp::new(&config, ablation, &device);
        save_model(&dir.join(file), &meta, &emp).expect("save model");
    }
}

/// A path in the repository.
pub fn in_repo(path: &str) -> PathBuf {
    Path::new(env!("CARGO_MANIFEST_DIR")).join(path)
}

/// `config/replay.toml` with the shipped networks' directory made absolute
/// and ROS 2 on `domain`, loopback only: the tests' live configs start
/// from it.
pub fn bundled_config_on(domain: u16) -> String {
    let text = std::fs::read_to_string(in_repo("config/replay.toml")).expect("config/replay.toml");
    let text = text
        .replace(
            "dir = \"models\"",
            &format!("dir = \"{}\"", in_repo("models").display()),
        )
        .replace(
            "[ros]\nenabled = true",
            &format!("[ros]\nenabled = true\ndomain_id = {domain}\nlocalhost_only = true"),
        );
    assert!(
        text.contains("localhost_only = true") && text.contains("joints = \"ros\""),
        "config/replay.toml changed shape"
    );
    text
}

/// `config/replay.toml` with the shipped networks' directory made absolute
/// and ROS 2 off, written to `dir/replay.toml`: the offline replays' config.
pub fn bundled_config_without_ros(dir: &Path) -> PathBuf {
    let text = std::fs::read_to_string(in_repo("config/replay.toml"))
        .expect("config/replay.toml")
        .replace(
            "dir = \"models\"",
            &format!("dir = \"{}\"", in_repo("models").display()),
        )
        .replace("[ros]\nenabled = true", "[ros]\nenabled = false");
    assert!(
        text.contains("enabled = false"),
        "config/replay.toml changed shape"
    );
    let config = dir.join("replay.toml");
    std::fs::write(&config, text).expect("config");
    config
}

/// `fall-guard replay --config CONFIG --recording RECORDING --max-speed`,
/// which must succeed: its forecast lines and its log.
pub fn replay_recording(config: &Path, recording: &Path) -> (Vec<Line>, String) {
    let out = fall_guard(&[
        "replay",
        "--config",
        config.to_str().expect("utf8"),
        "--recording",
        recording.to_str().expect("utf8"),
        "--max-speed",
    ]);
    assert!(
        out.status.success(),
        "{}: replay failed: {}",
        recording.display(),
        stderr(&out)
    );
    (parse_lines(&out.stdout), stderr(&out))
}

/// A 64 x 48 JPEG for a ROS 2 camera peer to publish, `dir/head.jpg`.
pub fn write_head_jpeg(dir: &Path) -> PathBuf {
    let path = dir.join("head.jpg");
    let frame = fall_guard_runtime::frame::Frame::solid(64, 48, [90, 120, 150]);
    std::fs::write(
        &path,
        fall_guard_runtime::frame::encode_jpeg(&frame, 90).expect("jpeg"),
    )
    .expect("write jpeg");
    path
}

/// Raw positions each motor held (id -> raws).
pub type HeldRaws = Arc<Mutex<BTreeMap<u8, BTreeSet<u16>>>>;

/// The emulated motors moving all along (a step every 40 ms, each within
/// 12 raw units of its standing pose, 0 deg: inside the shipped
/// networks' training ranges, as a standing robot sways), every raw
/// position a motor held kept in `held`.
pub struct MovingMotors {
    pub held: HeldRaws,
    moving: Arc<AtomicBool>,
    thread: std::thread::JoinHandle<()>,
}

impl MovingMotors {
    pub fn start(buses: Arc<PoppyBuses>, table: &JointTable) -> MovingMotors {
        let held: HeldRaws = Arc::default();
        let moving = Arc::new(AtomicBool::new(true));
        let joints = table.joints().to_vec();
        let thread = {
            let (held, moving) = (Arc::clone(&held), Arc::clone(&moving));
            std::thread::spawn(move || {
                let mut step = 0u16;
                while moving.load(Ordering::Relaxed) {
                    for (i, joint) in joints.iter().enumerate() {
                        let raw = joint.deg_to_raw(0.0) - 12 + step.wrapping_add(i as u16) % 24;
                        held.lock()
                            .expect("held")
                            .entry(joint.id)
                            .or_default()
                            .insert(raw);
                        buses.set_raw_position(joint.id, raw).expect("motor");
                    }
                    step = step.wrapping_add(1);
                    std::thread::sleep(Duration::from_millis(40));
                }
            })
        };
        MovingMotors {
            held,
            moving,
            thread,
        }
    }

    pub fn stop(self) {
        self.moving.store(false, Ordering::Relaxed);
        self.thread.join().expect("mover");
    }
}

/// A synthetic episode of `n_ticks` at 30 Hz (falls when `falls`).
pub fn write_recording(path: &Path, seed: u64, falls: bool, n_ticks: usize) {
    learnable_episode(seed, falls, n_ticks, &robot_joints(), RATE_HZ, FRAME_SIZE)
        .write(path)
        .expect("write recording");
}

/// A replay config in `dir` using `models/` and `recording`.
pub fn config_text(recording: &str) -> String {
    format!(
        r#"[robot]
name = "test_robot"
joints = "poppy_humanoid"

[model]
dir = "models"
emp = "emp.fgm"
mp = "mp.fgm"
ep = "ep.fgm"
p = "p.fgm"
horizon_ms = 533
trigger = 0.6
release = 0.3

[streams]
joints = "ros"
camera = "ros"
plan = "ros"
joints_stale_ms = 100
camera_stale_ms = 100
plan_stale_ms = 1500

[replay]
recording = "{recording}"
max_speed = true

[ros]
enabled = false

[output]
print_forecasts = true
diagnostics_period_ms = 1000
"#
    )
}

/// A scratch directory with models and a config; returns (dir, config path).
pub struct Scene {
    pub dir: tempfile::TempDir,
    pub config: PathBuf,
}

impl Scene {
    pub fn new(recording_name: &str) -> Scene {
        let dir = tempfile::tempdir().expect("tempdir");
        write_models(&dir.path().join("models"), &robot_joints());
        let config = dir.path().join("replay.toml");
        std::fs::write(&config, config_text(recording_name)).expect("config");
        Scene { dir, config }
    }

    pub fn path(&self, name: &str) -> PathBuf {
        self.dir.path().join(name)
    }

    /// `fall-guard replay --max-speed` on this scene's config: its forecast
    /// lines and its log.
    pub fn replay_max_speed(&self) -> (Vec<Line>, String) {
        let out = fall_guard(&[
            "replay",
            "--config",
            self.config.to_str().expect("utf8"),
            "--max-speed",
        ]);
        assert!(out.status.success(), "replay failed: {}", stderr(&out));
        (parse_lines(&out.stdout), stderr(&out))
    }
}

pub fn fall_guard(args: &[&str]) -> Output {
    Command::new(env!("CARGO_BIN_EXE_fall-guard"))
        .args(args)
        .env("RUST_LOG", "info")
        .output()
        .expect("run fall-guard")
}

/// One printed forecast line.
#[derive(Debug, Clone, PartialEq)]
pub struct Line {
    pub tick: i64,
    /// The tick's stamp, seconds (`t=`).
    pub stamp_s: f64,
    pub ablation: String,
    pub valid: bool,
    pub reason: String,
    pub probabilities: Vec<f32>,
    pub imminent: bool,
}

/// Parses `tick 120 t=4.000s EMP valid p=[0.0120 0.0340] imminent=false`.
pub fn parse_lines(stdout: &[u8]) -> Vec<Line> {
    let text = String::from_utf8_lossy(stdout);
    text.lines()
        .filter(|l| l.starts_with("tick "))
        .map(|l| {
            let tick = l
                .split_whitespace()
                .nth(1)
                .and_then(|t| t.parse().ok())
                .expect("tick");
            let stamp_s = l
                .split_whitespace()
                .nth(2)
                .and_then(|t| t.strip_prefix("t=")?.strip_suffix('s')?.parse().ok())
                .expect("t=");
            let ablation = l.split_whitespace().nth(3).expect("ablation").to_string();
            let rest = l.splitn(5, ' ').nth(4).expect("rest");
            let valid = rest.starts_with("valid");
            let reason = rest
                .strip_prefix("invalid(")
                .and_then(|r| r.split_once(") p=["))
                .map(|(r, _)| r.to_string())
                .unwrap_or_default();
            let p_text = l
                .split_once("p=[")
                .and_then(|(_, r)| r.split_once(']'))
                .expect("p")
                .0;
            let probabilities = p_text
                .split_whitespace()
                .map(|p| p.parse().expect("prob"))
                .collect();
            let imminent = l.ends_with("imminent=true");
            Line {
                tick,
                stamp_s,
                ablation,
                valid,
                reason,
                probabilities,
                imminent,
            }
        })
        .collect()
}

pub fn stderr(out: &Output) -> String {
    String::from_utf8_lossy(&out.stderr).into_owned()
}

/// `joints_gap.mcap` in SCENE: 5 s at 30 Hz (seed 4, no fall) with the
/// joint states gone from 2.0 s to 2.5 s (ticks 60..75), the servo bus
/// unplugged while the camera and the plan go on.
pub fn write_joints_gap_recording(scene: &Scene) -> PathBuf {
    let full = scene.path("full.mcap");
    write_recording(&full, 4, false, 150);
    let gap = scene.path("joints_gap.mcap");
    copy_without(
        &full,
        &gap,
        topics::JOINT_STATES,
        2_000_000_000,
        2_500_000_000,
    );
    gap
}

/// Copies `src` to `dst` without the messages of `topic`
/// ([`topics::JOINT_STATES`], [`topics::HEAD_CAMERA`] or
/// [`topics::PLANNED_TRAJECTORY`]) logged in `[from_ns, to_ns)`: a stream
/// lost for a while, the others going on.
pub fn copy_without(src: &Path, dst: &Path, topic: &str, from_ns: i64, to_ns: i64) {
    let keep = |t: &str, log_time_ns: i64| t != topic || !(from_ns..to_ns).contains(&log_time_ns);
    copy_edited(src, dst, keep, Clone::clone, joint_cdr);
}

/// A joint state as recorded: its CDR bytes.
pub fn joint_cdr(_index: usize, m: &fall_guard_runtime::msgs::JointState) -> Vec<u8> {
    fall_guard_runtime::msgs::encode_cdr(m).expect("encode")
}

/// Copies `src` to `dst` with the bytes of the `index`th joint state
/// message replaced by `bytes(index, message)` (a bad message inside a
/// sound file), the rest unchanged.
pub fn copy_with_joint_bytes(
    src: &Path,
    dst: &Path,
    bytes: impl Fn(usize, &fall_guard_runtime::msgs::JointState) -> Vec<u8>,
) {
    copy_edited(src, dst, |_, _| true, Clone::clone, bytes);
}

/// Copies `src` to `dst` with every camera message replaced by
/// `image(message)`, the rest unchanged.
pub fn copy_with_images(
    src: &Path,
    dst: &Path,
    image: impl Fn(
        &fall_guard_runtime::msgs::CompressedImage,
    ) -> fall_guard_runtime::msgs::CompressedImage,
) {
    copy_edited(src, dst, |_, _| true, image, joint_cdr);
}

fn copy_edited(
    src: &Path,
    dst: &Path,
    keep: impl Fn(&str, i64) -> bool,
    image: impl Fn(
        &fall_guard_runtime::msgs::CompressedImage,
    ) -> fall_guard_runtime::msgs::CompressedImage,
    joints: impl Fn(usize, &fall_guard_runtime::msgs::JointState) -> Vec<u8>,
) {
    let rec = Recording::open(src).expect("read");
    let mut w = RecordingWriter::create(dst).expect("create");
    let mut i = (0, 0, 0);
    loop {
        let next = [
            rec.joint_states.get(i.0).map(|m| (m.file_order, 0)),
            rec.images.get(i.1).map(|m| (m.file_order, 1)),
            rec.plans.get(i.2).map(|m| (m.file_order, 2)),
        ]
        .into_iter()
        .flatten()
        .min();
        match next {
            None => break,
            Some((_, 0)) => {
                let m = &rec.joint_states[i.0];
                if keep(topics::JOINT_STATES, m.log_time_ns) {
                    let bytes = joints(i.0, &m.msg);
                    w.write_cdr::<fall_guard_runtime::msgs::JointState>(
                        topics::JOINT_STATES,
                        m.log_time_ns,
                        &bytes,
                    )
                    .expect("write");
                }
                i.0 += 1;
            }
            Some((_, 1)) => {
                let m = &rec.images[i.1];
                if keep(topics::HEAD_CAMERA, m.log_time_ns) {
                    w.write(topics::HEAD_CAMERA, m.log_time_ns, &image(&m.msg))
                        .expect("write");
                }
                i.1 += 1;
            }
            Some(_) => {
                let m = &rec.plans[i.2];
                if keep(topics::PLANNED_TRAJECTORY, m.log_time_ns) {
                    w.write(topics::PLANNED_TRAJECTORY, m.log_time_ns, &m.msg)
                        .expect("write");
                }
                i.2 += 1;
            }
        }
    }
    w.write_episode(rec.episode().expect("meta")).expect("meta");
    w.finish().expect("finish");
}

/// The daemon as a child process whose stdout and stderr are read as they
/// come (a full pipe would block its logging and stall it).
pub struct Daemon {
    child: std::process::Child,
    readers: Vec<std::thread::JoinHandle<Vec<u8>>>,
}

impl Daemon {
    /// `fall-guard ARGS` with the default log filter, as an operator gets
    /// it: the tests check that it keeps DDS chatter out and that a stop
    /// logs no ERROR.
    pub fn start(args: &[&str]) -> Daemon {
        Daemon::spawn(Daemon::command(args))
    }

    /// The command [`Daemon::start`] runs, for a test to add to.
    pub fn command(args: &[&str]) -> Command {
        let mut command = Command::new(env!("CARGO_BIN_EXE_fall-guard"));
        command.args(args).env_remove("RUST_LOG");
        command
    }

    /// Runs `command` with its stdout and stderr read as they come.
    pub fn spawn(mut command: Command) -> Daemon {
        use std::io::Read;
        use std::process::Stdio;
        let mut child = command
            .stdin(Stdio::null())
            .stdout(Stdio::piped())
            .stderr(Stdio::piped())
            .spawn()
            .expect("start fall-guard");
        let out: Box<dyn Read + Send> = Box::new(child.stdout.take().expect("stdout"));
        let err: Box<dyn Read + Send> = Box::new(child.stderr.take().expect("stderr"));
        let readers = [out, err]
            .into_iter()
            .map(|mut pipe| {
                std::thread::spawn(move || {
                    let mut buf = Vec::new();
                    let _ = pipe.read_to_end(&mut buf);
                    buf
                })
            })
            .collect();
        Daemon { child, readers }
    }

    /// Its process id.
    pub fn pid(&self) -> u32 {
        self.child.id()
    }

    /// Whether it still runs (it has not exited, by itself or by a crash).
    pub fn running(&mut self) -> bool {
        matches!(self.child.try_wait(), Ok(None))
    }

    /// Waits for it to exit by itself: (success, stdout, stderr).
    pub fn wait(mut self) -> (bool, Vec<u8>, String) {
        let status = self.child.wait().expect("wait for fall-guard");
        let mut texts = self
            .readers
            .into_iter()
            .map(|r| r.join().unwrap_or_default());
        let stdout = texts.next().unwrap_or_default();
        let stderr = String::from_utf8_lossy(&texts.next().unwrap_or_default()).into_owned();
        (status.success(), stdout, stderr)
    }

    /// SIGTERM, as systemd stops it, then [`Daemon::wait`].
    pub fn stop(self) -> (bool, Vec<u8>, String) {
        let _ = Command::new("kill")
            .args(["-TERM", &self.child.id().to_string()])
            .status();
        self.wait()
    }
}

/// The status of `array` whose name ends with `: WHAT` (`model`, `joints`,
/// `inputs`, ...).
pub fn status<'a>(array: &'a DiagnosticArray, what: &str) -> &'a DiagnosticStatus {
    let suffix = format!(": {what}");
    array
        .status
        .iter()
        .find(|s| s.name.ends_with(&suffix))
        .unwrap_or_else(|| panic!("no {what} status in {array:?}"))
}

/// The value of `key` in `status`.
pub fn status_value(status: &DiagnosticStatus, key: &str) -> Option<String> {
    status
        .values
        .iter()
        .find(|kv| kv.key == key)
        .map(|kv| kv.value.clone())
}
