//! The daemon assembled: config -> networks -> sources -> tick -> inference
//! thread -> outputs, for the subcommands `run`, `replay`, `record` and
//! `label`.
//!
//! Each subcommand has a plain options struct and an async function here;
//! the binary (`src/cli.rs`) parses the command line into them and
//! dispatches. Shutdown is a value
//! ([`Shutdown`]) handed to every task; SIGINT/SIGTERM, the end of a replay,
//! or a failed task fire it. sd-notify READY/WATCHDOG come from the tick
//! loop (`tick.rs`), so a hung tick gets the service restarted by systemd.

use std::path::{Path, PathBuf};
use std::sync::Arc;

use thiserror::Error;
use tokio::task::JoinHandle;

use crate::config::{CameraSource, Config, ConfigError, JointsSource, PlanSource};
use crate::forecast::{ablation_name, ForecastError, Inference, ModelSet};
use crate::frame::Frame;
use crate::msgs::CompressedImage;
use crate::outputs::latch::{LatchError, SafetyLatch};
use crate::outputs::recorder::Recorder;
use crate::outputs::OutputBus;
use crate::recording::RecordingError;
use crate::robot::JointTable;
use crate::shutdown::{Shutdown, ShutdownTrigger};
use crate::sources::input::{Gate, InputLimits};
use crate::sources::replay::{replay_samples, Pacing, ReplayError, ReplayRecording};
use crate::sources::{stream, PerStream, StreamFeed, StreamKind, StreamStats, StreamTap};
use crate::tick::{LiveTaps, StreamSlot, TickCounters, TickLoop, TickSettings};
use crate::window::{Plan, Sample, WindowError, WindowSpec};

#[derive(Debug, Error)]
pub enum ServiceError {
    #[error(transparent)]
    Config(#[from] ConfigError),
    #[error(transparent)]
    Forecast(#[from] ForecastError),
    #[error(transparent)]
    Replay(#[from] ReplayError),
    #[error(transparent)]
    Recording(#[from] RecordingError),
    #[error(transparent)]
    Window(#[from] WindowError),
    #[error("{key}: {source}")]
    Latch {
        key: &'static str,
        #[source]
        source: LatchError,
    },
    #[error("{0}")]
    Source(String),
    #[error("{0}")]
    Usage(String),
}

/// `fall-guard run`: the onboard daemon.
#[derive(Debug, Clone, Default)]
pub struct RunOptions {
    /// The config file (see config/poppy_humanoid.toml).
    pub config: PathBuf,
    /// ROS namespace for every relative topic (overrides `[ros].namespace`).
    pub namespace: Option<String>,
}

/// `fall-guard replay`: the daemon on a recording, with recorded time.
#[derive(Debug, Clone, Default)]
pub struct ReplayOptions {
    /// Config file; without it, the embedded config/replay.toml.
    pub config: Option<PathBuf>,
    /// MCAP recording; without it, `[replay].recording` of the config.
    pub recording: Option<PathBuf>,
    /// Recorded time runs this many times faster than real time.
    pub speed: Option<f64>,
    /// As fast as inference allows (every tick forecast, none skipped).
    pub max_speed: bool,
    /// Do not print one line per forecast on stdout.
    pub quiet: bool,
    /// Also write the recording with the daemon's outputs merged in
    /// (`/fall_guard/forecast`, `/fall_guard/fall_imminent`, `/diagnostics`
    /// at recorded time), e.g. to open in Foxglove with
    /// `docs/foxglove/fall-guard.json`.
    pub out: Option<PathBuf>,
}

/// `fall-guard record`: record the live streams as an MCAP recording.
#[derive(Debug, Clone, Default)]
pub struct RecordOptions {
    pub config: PathBuf,
    /// Output file (.mcap).
    pub out: PathBuf,
    /// Stop after this many seconds (default: until Ctrl-C / SIGTERM).
    pub duration_s: Option<f64>,
}

/// `fall-guard label`: mark the fall onset of a recording, in place.
#[derive(Debug, Clone, Default)]
pub struct LabelOptions {
    /// The recording to label.
    pub recording: PathBuf,
    /// Seconds after the recording's first message when the fall starts.
    pub fall_at: Option<f64>,
    /// The episode does not fall.
    pub no_fall: bool,
}

/// Load a config file, or the embedded replay default.
pub fn load_config(path: Option<&Path>) -> Result<Config, ConfigError> {
    match path {
        Some(p) => Config::load(p),
        None => Config::embedded_replay(),
    }
}

/// Fire `trigger` on SIGINT or SIGTERM.
pub fn shutdown_on_signals(trigger: Arc<ShutdownTrigger>) -> JoinHandle<()> {
    tokio::spawn(async move {
        let terminate = async {
            match tokio::signal::unix::signal(tokio::signal::unix::SignalKind::terminate()) {
                Ok(mut s) => {
                    s.recv().await;
                }
                Err(e) => {
                    tracing::warn!(error = %e, "cannot listen for SIGTERM");
                    std::future::pending::<()>().await;
                }
            }
        };
        tokio::select! {
            _ = tokio::signal::ctrl_c() => tracing::info!("SIGINT: shutting down"),
            () = terminate => tracing::info!("SIGTERM: shutting down"),
        }
        trigger.fire();
    })
}

/// The robot's joint names, model order.
pub fn robot_joints(config: &Config) -> Vec<String> {
    // `[robot].joints` is validated to be the one built-in table.
    let _ = &config.robot.joints;
    JointTable::poppy_humanoid().names()
}

/// The safety latch of `[model]`, on the index of `[model].horizon_ms`.
pub fn latch_for(config: &Config, models: &ModelSet) -> Result<SafetyLatch, ServiceError> {
    let index = models
        .horizons_ms()
        .iter()
        .position(|&h| h == config.model.horizon_ms)
        .ok_or_else(|| {
            ServiceError::Usage(format!(
                "{}: [model].horizon_ms {} is not a model horizon",
                config.origin, config.model.horizon_ms
            ))
        })?;
    SafetyLatch::new(index, config.model.trigger, config.model.release).map_err(|source| {
        ServiceError::Latch {
            key: "[model].release",
            source,
        }
    })
}

/// The tick settings of `config` for streams with these sources
/// (name, configured) and stats.
pub fn tick_settings(
    config: &Config,
    sources: PerStream<(String, bool)>,
    stats: &PerStream<Arc<StreamStats>>,
) -> TickSettings {
    let s = &config.streams;
    let stale_ms = PerStream {
        joints: s.joints_stale_ms,
        camera: s.camera_stale_ms,
        plan: s.plan_stale_ms,
    };
    let streams = sources.map(|kind, (source, configured)| StreamSlot {
        kind,
        source,
        configured,
        stale_ns: i64::from(stale_ms[kind]) * 1_000_000,
        stats: Arc::clone(&stats[kind]),
    });
    TickSettings {
        streams,
        diagnostics_period_ns: i64::from(config.output.diagnostics_period_ms) * 1_000_000,
        hardware_id: config.robot.name.clone(),
        latch_horizon_ms: config.model.horizon_ms,
    }
}

/// What a replay did.
#[derive(Debug, Clone, PartialEq)]
pub struct ReplayReport {
    pub recording: PathBuf,
    pub samples: u64,
    pub counters: TickCounters,
    pub final_ablation: &'static str,
    pub interrupted: bool,
}

/// Everything a replay needs, set up (used by `replay` and the bench).
pub struct ReplaySetup {
    pub config: Config,
    pub models: Arc<ModelSet>,
    pub recording: ReplayRecording,
    pub bus: OutputBus,
    /// The input boundary of each replayed stream.
    pub gates: PerStream<Gate>,
    pub tick_loop: TickLoop,
}

/// A replay's ROS 2 node and the task publishing the bus on it.
pub type ReplayRos = (Option<RosBridge>, Option<tokio::task::JoinHandle<()>>);

impl ReplaySetup {
    /// The ROS 2 node and its publisher task, when `[ros].enabled`; the
    /// publisher stops on `trigger`.
    pub fn start_ros(&self, trigger: &ShutdownTrigger) -> Result<ReplayRos, ServiceError> {
        if !self.config.ros.enabled {
            return Ok((None, None));
        }
        let mut bridge = RosBridge::start(&self.config)?;
        let publisher = bridge.start_outputs(
            &self.config,
            &self.models,
            &self.bus,
            trigger.subscribe(),
            None,
        )?;
        Ok((Some(bridge), Some(publisher)))
    }

    /// Load networks and recording, start the inference thread.
    pub fn new(config: Config, recording: &Path, print: bool) -> Result<ReplaySetup, ServiceError> {
        let joints = robot_joints(&config);
        let models = Arc::new(ModelSet::load(&config, &joints)?);
        let recording = ReplayRecording::open(recording, models.spec())?;
        let bus = OutputBus::new();
        let latch = latch_for(&config, &models)?;
        let inference = Inference::spawn(Arc::clone(&models), latch, bus.clone(), print)?;
        let stats = PerStream::from_fn(|_| Arc::new(StreamStats::default()));
        let limits = input_limits(&config, &models);
        let gates = PerStream::from_fn(|kind| Gate::new(kind, limits, Arc::clone(&stats[kind])));
        let source = format!("replay {}", recording.path.display());
        let settings = tick_settings(
            &config,
            PerStream::from_fn(|_| (source.clone(), true)),
            &stats,
        );
        let tick_loop = TickLoop::new(Arc::clone(&models), inference, settings, bus.clone())?;
        Ok(ReplaySetup {
            config,
            models,
            recording,
            bus,
            gates,
            tick_loop,
        })
    }
}

/// `fall-guard replay`.
pub async fn replay(args: ReplayOptions) -> Result<ReplayReport, ServiceError> {
    let config = load_config(args.config.as_deref())?;
    let replay_defaults = config.replay.clone();
    let recording = match (&args.recording, &replay_defaults) {
        (Some(p), _) => p.clone(),
        (None, Some(r)) => config.resolve(&r.recording),
        (None, None) => {
            return Err(ServiceError::Usage(format!(
                "{}: no recording: pass --recording PATH or set [replay].recording",
                config.origin
            )))
        }
    };
    let pacing = if args.max_speed
        || replay_defaults.as_ref().is_some_and(|r| r.max_speed) && args.speed.is_none()
    {
        Pacing::MaxSpeed
    } else {
        let speed = args
            .speed
            .or(replay_defaults.map(|r| r.speed))
            .unwrap_or(1.0);
        if !(speed.is_finite() && speed > 0.0) {
            return Err(ServiceError::Usage(format!(
                "--speed {speed}: expected a positive factor"
            )));
        }
        Pacing::Speed(speed)
    };
    if let Some(out) = &args.out {
        let dir = match out.parent() {
            Some(d) if !d.as_os_str().is_empty() => d,
            _ => Path::new("."),
        };
        if !dir.is_dir() {
            return Err(ServiceError::Usage(format!(
                "--out {}: directory {} does not exist",
                out.display(),
                dir.display()
            )));
        }
    }
    let print = config.output.print_forecasts && !args.quiet;
    let mut setup = ReplaySetup::new(config, &recording, print)?;
    let trigger = Arc::new(ShutdownTrigger::new().0);
    let mut shutdown = trigger.subscribe();
    let signals = shutdown_on_signals(Arc::clone(&trigger));
    let (ros, publisher) = setup.start_ros(&trigger)?;
    let annotate = args.out.as_ref().map(|_| {
        crate::outputs::annotate::collect(
            &setup.bus,
            trigger.subscribe(),
            setup.config.ros.node_name.clone(),
        )
    });
    tracing::info!(recording = %recording.display(), ?pacing, "replay started");
    let samples = setup.recording.samples.clone();
    let summary = replay_samples(
        &mut setup.tick_loop,
        samples,
        setup.recording.end_ns,
        pacing,
        &setup.gates,
        &mut shutdown,
    )
    .await;
    let final_ablation = ablation_name(setup.tick_loop.active());
    let counters = setup.tick_loop.finish().await;
    trigger.fire();
    if let Some(p) = publisher {
        let _ = p.await;
    }
    if let Some(ros) = ros {
        ros.shutdown().await;
    }
    signals.abort();
    if let (Some(out), Some(collector)) = (&args.out, annotate) {
        let collected = collector
            .await
            .map_err(|e| ServiceError::Source(format!("{}: {e}", out.display())))?;
        let forecasts = collected.forecasts();
        crate::outputs::annotate::write(&recording, out, collected)
            .map_err(|e| ServiceError::Source(e.to_string()))?;
        tracing::info!(out = %out.display(), forecasts, "replay with outputs written");
    }
    if summary.inference_failed {
        return Err(ServiceError::Source(format!(
            "{}: inference stopped at tick {} (the network panicked, see the log)",
            recording.display(),
            counters.ticks
        )));
    }
    tracing::info!(
        ticks = counters.ticks,
        dispatched = counters.dispatched,
        overruns = counters.overruns,
        "replay finished"
    );
    Ok(ReplayReport {
        recording,
        samples: summary.samples,
        counters,
        final_ablation,
        interrupted: summary.interrupted,
    })
}

/// The live streams: the source ends (for the sources) and the tick ends.
pub struct LiveStreams {
    pub joints: StreamFeed<Vec<f32>>,
    pub camera: StreamFeed<Arc<Frame>>,
    pub plan: StreamFeed<Arc<Plan>>,
    pub taps: LiveTaps,
}

impl LiveStreams {
    /// The three streams, each behind its boundary with `limits`.
    pub fn new(limits: InputLimits) -> LiveStreams {
        let (joints, joints_tap) = stream(StreamKind::Joints, limits);
        let (camera, camera_tap) = stream(StreamKind::Camera, limits);
        let (plan, plan_tap) = stream(StreamKind::Plan, limits);
        LiveStreams {
            joints,
            camera,
            plan,
            taps: LiveTaps {
                joints: joints_tap,
                camera: camera_tap,
                plan: plan_tap,
            },
        }
    }

    /// Each stream's counters.
    pub fn stats(&self) -> PerStream<Arc<StreamStats>> {
        PerStream {
            joints: Arc::clone(self.joints.stats()),
            camera: Arc::clone(self.camera.stats()),
            plan: Arc::clone(self.plan.stats()),
        }
    }
}

/// The input boundary's limits for `config` and the loaded networks.
pub fn input_limits(config: &Config, models: &ModelSet) -> InputLimits {
    let spec = models.spec();
    config
        .streams
        .input_limits(spec.joint_names.len(), spec.frame_size)
}

/// Names of the live sources, for diagnostics.
fn source_names(config: &Config) -> PerStream<(String, bool)> {
    let topics = &config.ros.topics;
    let joints = match config.streams.joints {
        JointsSource::Dynamixel => {
            let ports: Vec<String> = config
                .dynamixel
                .as_ref()
                .map(|d| d.buses.values().map(|b| b.port.clone()).collect())
                .unwrap_or_default();
            format!("dynamixel {}", ports.join(" "))
        }
        JointsSource::Ros => format!("ros {}", topics.joint_states),
    };
    let camera = match config.streams.camera {
        CameraSource::V4l2 => (
            format!(
                "v4l2 {}",
                config
                    .camera
                    .as_ref()
                    .map(|c| c.device.display().to_string())
                    .unwrap_or_default()
            ),
            true,
        ),
        CameraSource::Ros => (format!("ros {}", topics.camera), true),
        CameraSource::None => ("none".to_string(), false),
    };
    let plan = match config.streams.plan {
        PlanSource::Ros => (format!("ros {}", topics.planned_trajectory), true),
        PlanSource::None => ("none".to_string(), false),
    };
    PerStream {
        joints: (joints, true),
        camera,
        plan,
    }
}

/// Start the configured live sources feeding `streams` (ROS 2 ones on `ros`).
fn start_sources(
    config: &Config,
    models: &ModelSet,
    streams: &LiveStreams,
    ros: Option<&mut RosBridge>,
    shutdown: &ShutdownTrigger,
) -> Result<Vec<SourceHandle>, ServiceError> {
    let mut handles = Vec::new();
    if config.streams.joints == JointsSource::Dynamixel {
        handles.push(servo_bridge::start(
            config,
            streams.joints.clone(),
            shutdown.subscribe(),
        )?);
    }
    if config.streams.camera == CameraSource::V4l2 {
        handles.push(start_camera(
            config,
            models,
            streams.camera.clone(),
            shutdown.subscribe(),
        )?);
    }
    let from_ros = PerStream {
        joints: config.streams.joints == JointsSource::Ros,
        camera: config.streams.camera == CameraSource::Ros,
        plan: config.streams.plan == PlanSource::Ros,
    };
    if from_ros.iter().any(|(_, &ros)| ros) {
        let bridge = ros.ok_or_else(|| {
            ServiceError::Usage(format!(
                "{}: [streams] reads from ROS 2 but [ros].enabled = false",
                config.origin
            ))
        })?;
        let tasks = bridge.start_inputs(
            config,
            models.spec(),
            streams,
            from_ros,
            None,
            shutdown.subscribe(),
        )?;
        handles.extend(tasks.into_iter().map(SourceHandle::Task));
    }
    Ok(handles)
}

/// A running source.
pub enum SourceHandle {
    Thread(std::thread::JoinHandle<()>),
    Task(JoinHandle<()>),
}

impl SourceHandle {
    async fn join(self) {
        match self {
            SourceHandle::Thread(t) => {
                let _ = tokio::task::spawn_blocking(move || t.join()).await;
            }
            SourceHandle::Task(t) => {
                let _ = t.await;
            }
        }
    }
}

#[cfg(feature = "camera-v4l")]
fn start_camera(
    config: &Config,
    models: &ModelSet,
    feed: StreamFeed<Arc<Frame>>,
    shutdown: Shutdown,
) -> Result<SourceHandle, ServiceError> {
    let camera = config
        .camera
        .clone()
        .ok_or_else(|| ServiceError::Usage(format!("{}: [camera] missing", config.origin)))?;
    crate::sources::camera::spawn_camera(camera, models.spec().frame_size, feed, shutdown)
        .map(SourceHandle::Thread)
        .map_err(|e| ServiceError::Source(format!("cannot start the camera thread: {e}")))
}

#[cfg(not(feature = "camera-v4l"))]
fn start_camera(
    config: &Config,
    _models: &ModelSet,
    _feed: StreamFeed<Arc<Frame>>,
    _shutdown: Shutdown,
) -> Result<SourceHandle, ServiceError> {
    start_camera_unavailable(config)
}

#[cfg(not(feature = "camera-v4l"))]
fn start_camera_unavailable(config: &Config) -> Result<SourceHandle, ServiceError> {
    Err(ServiceError::Usage(format!(
        "{}: [streams].camera = \"v4l2\" needs a build with cargo feature `camera-v4l`",
        config.origin
    )))
}

/// `fall-guard run`.
pub async fn run(args: RunOptions) -> Result<TickCounters, ServiceError> {
    let mut config = Config::load(&args.config)?;
    if let Some(ns) = &args.namespace {
        config.set_namespace(ns, "--namespace")?;
    }
    let joints = robot_joints(&config);
    let models = Arc::new(ModelSet::load(&config, &joints)?);
    let bus = OutputBus::new();
    let latch = latch_for(&config, &models)?;
    let inference = Inference::spawn(
        Arc::clone(&models),
        latch,
        bus.clone(),
        config.output.print_forecasts,
    )?;
    let trigger = Arc::new(ShutdownTrigger::new().0);
    let signals = shutdown_on_signals(Arc::clone(&trigger));
    let streams = LiveStreams::new(input_limits(&config, &models));
    let settings = tick_settings(&config, source_names(&config), &streams.stats());
    let mut ros = if config.ros.enabled {
        Some(RosBridge::start(&config)?)
    } else {
        None
    };
    let publisher = match ros.as_mut() {
        Some(bridge) => {
            // The daemon owns the servo bus: what it reads goes out on /joint_states.
            let joints_out = (config.streams.joints == JointsSource::Dynamixel)
                .then(|| streams.taps.joints.clone());
            Some(bridge.start_outputs(&config, &models, &bus, trigger.subscribe(), joints_out)?)
        }
        None => None,
    };
    let sources = start_sources(&config, &models, &streams, ros.as_mut(), &trigger)?;
    let tick_loop = TickLoop::new(Arc::clone(&models), inference, settings, bus.clone())?;
    tracing::info!(config = %args.config.display(), rate_hz = models.spec().rate_hz,
        n_ticks = models.spec().n_ticks, "fall-guard running");
    let (counters, inference_died) =
        crate::tick::run_live(tick_loop, streams.taps.clone(), trigger.subscribe()).await;
    let _ = sd_notify::notify(false, &[sd_notify::NotifyState::Stopping]);
    trigger.fire();
    for s in sources {
        s.join().await;
    }
    if let Some(p) = publisher {
        let _ = p.await;
    }
    if let Some(ros) = ros {
        ros.shutdown().await;
    }
    signals.abort();
    if inference_died {
        return Err(ServiceError::Source(
            "inference stopped (the network panicked, see the log)".into(),
        ));
    }
    Ok(counters)
}

/// `fall-guard record`: the live streams into an MCAP recording, loading
/// no network. What it needs comes from the config (`[robot].tick_rate_hz`
/// as the recording's `rate_hz`, the robot's joint names, the sources and
/// topics); the camera is kept as the camera gave it ([`Recorder::record_image`]).
pub async fn record(
    args: RecordOptions,
) -> Result<crate::outputs::recorder::RecordSummary, ServiceError> {
    let config = Config::load(&args.config)?;
    let joints = robot_joints(&config);
    let trigger = Arc::new(ShutdownTrigger::new().0);
    let signals = shutdown_on_signals(Arc::clone(&trigger));
    // The camera's own frames are not decoded: the limits' frame size
    // does not apply to them (only their stamps are checked).
    let limits = config.streams.input_limits(joints.len(), 0);
    let streams = LiveStreams::new(limits);
    let (camera_feed, mut camera) = stream::<Arc<CompressedImage>>(StreamKind::Camera, limits);
    let mut ros = if config.ros.enabled {
        Some(RosBridge::start(&config)?)
    } else {
        None
    };
    let sources = start_record_sources(
        &config,
        &joints,
        &streams,
        camera_feed,
        ros.as_mut(),
        &trigger,
    )?;
    let mut recorder = Recorder::create(
        &args.out,
        joints,
        &config.robot.joints,
        config.robot.tick_rate_hz,
    )?;
    let mut shutdown = trigger.subscribe();
    let deadline = args
        .duration_s
        .map(|s| tokio::time::Instant::now() + std::time::Duration::from_secs_f64(s.max(0.0)));
    let LiveTaps {
        mut joints,
        camera: _,
        mut plan,
    } = streams.taps.clone();
    let result: Result<(), ServiceError> = loop {
        let written = tokio::select! {
            () = shutdown.recv() => break Ok(()),
            () = async { match deadline { Some(d) => tokio::time::sleep_until(d).await, None => std::future::pending().await } } => break Ok(()),
            // A servo read that lacks a motor (NaN) is not recorded: a
            // recording holds whole readings, which a replay can use.
            Some(s) = changed(&mut joints) => {
                if s.value.iter().any(|v| !v.is_finite()) { continue; }
                recorder.record(&Sample::Joints { stamp_ns: s.stamp_ns, positions_rad: s.value.clone() })
            }
            Some(s) = changed(&mut camera) => recorder.record_image(s.stamp_ns, &s.value),
            Some(s) = changed(&mut plan) => recorder.record(&Sample::Plan { stamp_ns: s.stamp_ns, plan: Arc::clone(&s.value) }),
        };
        if let Err(e) = written {
            break Err(e.into());
        }
    };
    trigger.fire();
    let summary = recorder.finish();
    for s in sources {
        s.join().await;
    }
    if let Some(ros) = ros {
        ros.shutdown().await;
    }
    signals.abort();
    result?;
    Ok(summary?)
}

/// The sources of `record`: joints and plan as `run` has them, the camera
/// not decoded (`camera`: the ROS message as received, or the V4L2 buffer).
fn start_record_sources(
    config: &Config,
    joints: &[String],
    streams: &LiveStreams,
    camera: StreamFeed<Arc<CompressedImage>>,
    ros: Option<&mut RosBridge>,
    shutdown: &ShutdownTrigger,
) -> Result<Vec<SourceHandle>, ServiceError> {
    let mut handles = Vec::new();
    if config.streams.joints == JointsSource::Dynamixel {
        handles.push(servo_bridge::start(
            config,
            streams.joints.clone(),
            shutdown.subscribe(),
        )?);
    }
    if config.streams.camera == CameraSource::V4l2 {
        handles.push(start_camera_compressed(
            config,
            camera.clone(),
            shutdown.subscribe(),
        )?);
    }
    let from_ros = PerStream {
        joints: config.streams.joints == JointsSource::Ros,
        camera: false,
        plan: config.streams.plan == PlanSource::Ros,
    };
    let camera_raw = (config.streams.camera == CameraSource::Ros).then_some(camera);
    if from_ros.iter().any(|(_, &ros)| ros) || camera_raw.is_some() {
        let bridge = ros.ok_or_else(|| {
            ServiceError::Usage(format!(
                "{}: [streams] reads from ROS 2 but [ros].enabled = false",
                config.origin
            ))
        })?;
        // Only the joint names and the tick rate matter to the inputs
        // without a decoded camera: no network, no window.
        let spec = WindowSpec {
            n_ticks: 1,
            max_horizon_ticks: 0,
            rate_hz: config.robot.tick_rate_hz,
            joint_names: joints.to_vec(),
            frame_size: 0,
        };
        let tasks = bridge.start_inputs(
            config,
            &spec,
            streams,
            from_ros,
            camera_raw,
            shutdown.subscribe(),
        )?;
        handles.extend(tasks.into_iter().map(SourceHandle::Task));
    }
    Ok(handles)
}

#[cfg(feature = "camera-v4l")]
fn start_camera_compressed(
    config: &Config,
    feed: StreamFeed<Arc<CompressedImage>>,
    shutdown: Shutdown,
) -> Result<SourceHandle, ServiceError> {
    let camera = config
        .camera
        .clone()
        .ok_or_else(|| ServiceError::Usage(format!("{}: [camera] missing", config.origin)))?;
    crate::sources::camera::spawn_camera_compressed(camera, feed, shutdown)
        .map(SourceHandle::Thread)
        .map_err(|e| ServiceError::Source(format!("cannot start the camera thread: {e}")))
}

#[cfg(not(feature = "camera-v4l"))]
fn start_camera_compressed(
    config: &Config,
    _feed: StreamFeed<Arc<CompressedImage>>,
    _shutdown: Shutdown,
) -> Result<SourceHandle, ServiceError> {
    start_camera_unavailable(config)
}

async fn changed<T>(tap: &mut StreamTap<T>) -> Option<Arc<crate::sources::Stamped<T>>> {
    tap.changed().await
}

/// `fall-guard label`.
pub fn label(args: &LabelOptions) -> Result<Option<i64>, ServiceError> {
    let fall_at = if args.no_fall { None } else { args.fall_at };
    if !args.no_fall && fall_at.is_none() {
        return Err(ServiceError::Usage(
            "label: pass --fall-at SECONDS or --no-fall".into(),
        ));
    }
    Ok(crate::recording::label(&args.recording, fall_at)?)
}

pub mod ros_bridge;
pub mod servo_bridge;

use ros_bridge::RosBridge;
