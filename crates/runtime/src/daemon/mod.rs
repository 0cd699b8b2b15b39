//! The daemon's commands: `run`, `replay`, `record` (on the one lifecycle
//! of [`lifecycle`]: start, drive the inputs, stop) and `label`.
//!
//! Each subcommand has a plain options struct and an async function here;
//! the binary (`src/cli.rs`) parses the command line into them and
//! dispatches. Shutdown is a value
//! ([`Shutdown`](crate::shutdown::Shutdown)) handed to every task;
//! SIGINT/SIGTERM, the end of a replay, or a failed task fire it.
//! sd-notify READY/WATCHDOG come from the tick loop (`tick.rs`), so a hung
//! tick gets the service restarted by systemd; STOPPING from
//! [`Running::stop`].

use std::path::{Path, PathBuf};
use std::sync::Arc;

use thiserror::Error;

use crate::clock::ReplayClock;
use crate::config::{Config, ConfigError};
use crate::daemon::replay::replay_samples;
use crate::outputs::latch::SafetyLatch;
use crate::outputs::lead::{fall_warning, FallWarning};
use crate::outputs::recorder::Recorder;
use crate::pipeline::models::{ablation_name, ForecastError, ModelSet};
use crate::pipeline::tick::{LiveTaps, StreamSlot, TickCounters, TickSettings};
use crate::recording::RecordingError;
use crate::robot::JointTable;
use crate::sources::replay::ReplayError;
use crate::streams::input::InputLimits;
use crate::streams::sample::Sample;
use crate::streams::{stream, PerStream, StreamFeed, StreamStats, StreamTap};
use crate::window::{WindowError, WindowSpec};

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

/// The robot's joint names, model order.
pub fn robot_joints(config: &Config) -> Vec<String> {
    // `[robot].joints` is validated to be the one built-in table.
    let _ = &config.robot.joints;
    JointTable::poppy_humanoid().names()
}

/// The safety latch of `[model]`, on the index of `[model].horizon_ms`.
pub fn latch_for(config: &Config, models: &ModelSet) -> Result<SafetyLatch, ServiceError> {
    let index = config.latch_horizon_index(models.horizons_ms())?;
    let hold_ticks = crate::outputs::latch::release_hold_ticks(
        config.model.release_hold_ms,
        models.spec().rate_hz,
    );
    Ok(SafetyLatch::with_pairs(index, config.latch_thresholds()?).with_release_hold(hold_ticks))
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
        joints_max_held_ticks: s.joints_max_held_ticks as usize,
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

/// `fall-guard replay`.
pub async fn replay(args: ReplayOptions) -> Result<ReplayReport, ServiceError> {
    let mut config = load_config(args.config.as_deref())?;
    let recording = config.replay_recording(args.recording.as_deref())?;
    let pacing = config.replay_pacing(args.speed, args.max_speed)?;
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
    config.output.print_forecasts &= !args.quiet;
    let mut daemon = Running::<Replay>::start(config, &recording)?;
    let mut shutdown = daemon.shutdown();
    let collector_shutdown = daemon.shutdown();
    let lead_shutdown = daemon.shutdown();
    let Replay {
        forecasting,
        recording: replayed,
    } = &mut daemon.command;
    let annotate = args.out.as_ref().map(|_| {
        crate::outputs::annotate::collect(
            &forecasting.bus,
            collector_shutdown,
            daemon.config.ros.node_name.clone(),
        )
    });
    let lead_watch = replayed.fall_onset_ns.map(|onset| {
        (
            onset,
            crate::outputs::lead::watch(&forecasting.bus, lead_shutdown),
        )
    });
    let start_ns = replayed.start_ns;
    tracing::info!(recording = %recording.display(), ?pacing, "replay started");
    let summary = replay_samples(
        &mut forecasting.tick_loop,
        replayed.samples.clone(),
        replayed.end_ns,
        pacing,
        &daemon.streams,
        &mut shutdown,
        &mut ReplayClock::new(),
    )
    .await;
    let final_ablation = ablation_name(forecasting.tick_loop.active());
    let counters = daemon.stop().await.counters;
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
    if let Some((onset_ns, watch)) = lead_watch {
        let s = |ns: i64| (ns - start_ns) as f64 / 1e9;
        let said = match watch.await.ok().flatten() {
            Some(ticks) if !summary.interrupted => match fall_warning(&ticks, onset_ns) {
                FallWarning::Warned {
                    asserted_ns,
                    lead_ns,
                } => format!(
                    "fall_imminent asserted at {:.2} s, {:.2} s ahead",
                    s(asserted_ns),
                    lead_ns as f64 / 1e9
                ),
                FallWarning::NotWarned => "fall_imminent was not asserted before it".to_string(),
                FallWarning::HeldThroughout => {
                    "fall_imminent held from the start, never released (no warning to measure)"
                        .to_string()
                }
            },
            _ => "the lead is not measured (replay interrupted or forecasts lost)".to_string(),
        };
        tracing::info!("the recording falls at {:.2} s: {said}", s(onset_ns));
    }
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
    pub feeds: PerStream<StreamFeed<Sample>>,
    pub taps: LiveTaps,
}

impl LiveStreams {
    /// The streams, each behind its boundary with `limits`.
    pub fn new(limits: InputLimits) -> LiveStreams {
        let ends = PerStream::from_fn(|kind| stream::<Sample>(kind, limits.clone()));
        LiveStreams {
            feeds: ends.clone().map(|_, (feed, _)| feed),
            taps: ends.map(|_, (_, tap)| tap),
        }
    }

    /// Each stream's counters.
    pub fn stats(&self) -> PerStream<Arc<StreamStats>> {
        PerStream::from_fn(|kind| Arc::clone(self.feeds[kind].stats()))
    }
}

/// The input boundary's limits for `config` and the windows of `spec`
/// (the loaded networks', or a recorder's).
pub fn input_limits(config: &Config, spec: &WindowSpec) -> InputLimits {
    config.streams.input_limits(
        &spec.joint_names,
        &JointTable::poppy_humanoid(),
        spec.frame_size,
    )
}

/// `fall-guard run`.
pub async fn run(args: RunOptions) -> Result<TickCounters, ServiceError> {
    let mut config = Config::load(&args.config)?;
    if let Some(ns) = &args.namespace {
        config.set_namespace(ns, "--namespace")?;
    }
    let mut daemon = Running::<Live>::start(config)?;
    let shutdown = daemon.shutdown();
    let forecasting = &mut daemon.command.forecasting;
    let spec = forecasting.models.spec();
    tracing::info!(config = %args.config.display(), rate_hz = spec.rate_hz,
        n_ticks = spec.n_ticks, "fall-guard running");
    crate::pipeline::tick::run_live(
        &mut forecasting.tick_loop,
        daemon.streams.taps.clone(),
        shutdown,
    )
    .await;
    let stopped = daemon.stop().await;
    if stopped.inference_died {
        return Err(ServiceError::Source(
            "inference stopped (the network panicked, see the log)".into(),
        ));
    }
    Ok(stopped.counters)
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
    let daemon = Running::<Record>::start(config)?;
    let created = Recorder::create(
        &args.out,
        joints,
        &daemon.config.robot.joints,
        daemon.config.robot.tick_rate_hz,
    );
    let mut recorder = match created {
        Ok(r) => r,
        Err(e) => {
            daemon.stop().await;
            return Err(e.into());
        }
    };
    let mut shutdown = daemon.shutdown();
    let deadline = args
        .duration_s
        .map(|s| tokio::time::Instant::now() + std::time::Duration::from_secs_f64(s.max(0.0)));
    let mut taps = daemon.streams.taps.clone();
    let mut camera = daemon.command.camera.clone();
    let result: Result<(), ServiceError> = loop {
        let written = tokio::select! {
            () = shutdown.recv() => break Ok(()),
            () = async { match deadline { Some(d) => tokio::time::sleep_until(d).await, None => std::future::pending().await } } => break Ok(()),
            // A servo read that lacks a motor (NaN) is not recorded: a
            // recording holds whole readings, which a replay can use.
            Some(s) = changed(&mut taps.joints) => {
                if let Sample::Joints { positions_rad, .. } = &s.value {
                    if positions_rad.iter().any(|v| !v.is_finite()) { continue; }
                }
                recorder.record(&s.value)
            }
            Some(s) = changed(&mut camera) => recorder.record_image(s.stamp_ns, &s.value),
            Some(s) = changed(&mut taps.plan) => recorder.record(&s.value),
        };
        if let Err(e) = written {
            break Err(e.into());
        }
    };
    daemon.stop().await;
    let summary = recorder.finish();
    result?;
    Ok(summary?)
}

async fn changed<T>(tap: &mut StreamTap<T>) -> Option<Arc<crate::streams::Stamped<T>>> {
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

pub mod bench;
pub mod lifecycle;
pub mod replay;
pub mod ros_bridge;

pub use lifecycle::{
    shutdown_on_signals, Command, Forecasting, Live, Record, Replay, Running, SourceHandle, Stopped,
};
