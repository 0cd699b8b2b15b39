//! The daemon's one lifecycle: the start and stop order shared by `run`,
//! `replay`, `record` and `bench-daemon`.
//!
//! A command says what the daemon runs on ([`What`]: the live sources, a
//! recording, or the live sources into a recorder), gets a [`Running`]
//! daemon from [`Running::start`], drives its inputs (the live tick, a
//! replay, the recorder) until they end or the shutdown fires, then calls
//! [`Running::stop`].
//!
//! Start, in this order:
//! 1. the config checks of the command (`Config::check_live_sources` for
//!    the live sources);
//! 2. the networks, the safety latch and the inference thread (`record`
//!    loads none);
//! 3. the recording (`replay`, `bench-daemon`);
//! 4. the shutdown trigger, fired by SIGINT / SIGTERM;
//! 5. the streams, each behind its input boundary;
//! 6. the ROS 2 node (`[ros].enabled`), then its publisher of the output
//!    bus (not for `record`: it has no bus);
//! 7. the live sources (`run`, `record`): servo reader, camera, ROS 2
//!    subscriptions;
//! 8. the tick loop (not for `record`).
//!
//! Stop, in this order: the tick loop (the last inference, the thread
//! joined); sd-notify STOPPING; the shutdown fires; the sources, the
//! command's own tasks ([`Running::join_at_stop`]) and the publisher are
//! joined; then the ROS 2 node leaves the domain ([`RosBridge::shutdown`]:
//! subscriptions, then the node), after every task that used it; last the
//! signal listener ends.

use std::path::PathBuf;
use std::sync::Arc;

use tokio::task::JoinHandle;

use crate::config::{CameraSource, Config, JointsSource, PlanSource};
use crate::msgs::CompressedImage;
use crate::outputs::OutputBus;
use crate::pipeline::forecast::{Inference, ModelSet};
use crate::pipeline::tick::{TickCounters, TickLoop};
use crate::pipeline::window::WindowSpec;
use crate::robot::JointTable;
use crate::shutdown::{Shutdown, ShutdownTrigger};
use crate::sources::dynamixel::DynamixelSource;
use crate::sources::replay::ReplayRecording;
use crate::streams::input::Gate;
use crate::streams::sample::Sample;
use crate::streams::{stream, PerStream, StreamFeed, StreamKind, StreamStats, StreamTap};

use super::ros_bridge::RosBridge;
use super::{input_limits, latch_for, robot_joints, tick_settings, LiveStreams, ServiceError};

/// What the daemon runs on: the one difference between the commands.
#[derive(Debug, Clone, PartialEq)]
pub enum What {
    /// `run`: the configured live sources, forecasts out.
    Live,
    /// `replay`, `bench-daemon`: the samples of this recording, forecasts
    /// out.
    Replay(PathBuf),
    /// `record`: the configured live sources, the camera as it comes (not
    /// decoded); no network is loaded.
    Record,
}

/// The forecasting side of a running daemon (not for `record`).
pub struct Forecasting {
    pub models: Arc<ModelSet>,
    /// Forecasts and diagnostics, to the publisher and any subscriber.
    pub bus: OutputBus,
    /// Its inference thread runs; [`Running::stop`] finishes it.
    pub tick_loop: TickLoop,
}

/// The inputs as the command drives them.
pub enum Inputs {
    /// `run`: the live streams (the tick reads `streams.taps`).
    Live(LiveStreams),
    /// `replay`, `bench-daemon`: the recording, and the input boundary of
    /// each of its streams.
    Replay {
        recording: ReplayRecording,
        gates: PerStream<Gate>,
    },
    /// `record`: joints and plan as `run` has them, the camera as received.
    Record {
        streams: LiveStreams,
        camera: StreamTap<Arc<CompressedImage>>,
    },
}

/// A started daemon.
pub struct Running {
    pub config: Config,
    /// `None` for `record`.
    pub forecasting: Option<Forecasting>,
    pub inputs: Inputs,
    trigger: Arc<ShutdownTrigger>,
    signals: JoinHandle<()>,
    ros: Option<RosBridge>,
    publisher: Option<JoinHandle<()>>,
    sources: Vec<SourceHandle>,
    tasks: Vec<JoinHandle<()>>,
}

/// What the tick loop did, once stopped (zero for `record`).
#[derive(Debug, Clone, Copy, Default, PartialEq, Eq)]
pub struct Stopped {
    pub counters: TickCounters,
    /// The inference thread had ended (a panic in the network).
    pub inference_died: bool,
}

/// The networks, loaded, with their bus and inference thread.
struct Networks {
    models: Arc<ModelSet>,
    bus: OutputBus,
    inference: Inference,
}

impl Inputs {
    /// The live streams (`run`, `record`).
    pub fn live_streams(&self) -> Option<&LiveStreams> {
        match self {
            Inputs::Live(streams) | Inputs::Record { streams, .. } => Some(streams),
            Inputs::Replay { .. } => None,
        }
    }

    /// Each stream's counters (for the tick's diagnostics).
    pub fn stats(&self) -> PerStream<Arc<StreamStats>> {
        match self {
            Inputs::Live(streams) | Inputs::Record { streams, .. } => streams.stats(),
            Inputs::Replay { gates, .. } => {
                PerStream::from_fn(|kind| Arc::clone(gates[kind].stats()))
            }
        }
    }
}

impl Running {
    /// Start the daemon on `what`, in the order of the module doc.
    pub fn start(config: Config, what: What) -> Result<Running, ServiceError> {
        // 1. The config checks of the command.
        if !matches!(what, What::Replay(_)) {
            config.check_live_sources()?;
        }
        // 2. The networks and the inference thread. `record` loads none: its
        // window spec carries only what its inputs need (the joint names,
        // the tick rate; frame size 0: the camera is not decoded, only its
        // stamps are checked).
        let joints = robot_joints(&config);
        let (spec, networks) = if what == What::Record {
            let spec = WindowSpec {
                n_ticks: 1,
                max_horizon_ticks: 0,
                rate_hz: config.robot.tick_rate_hz,
                joint_names: joints,
                frame_size: 0,
            };
            (spec, None)
        } else {
            let models = Arc::new(ModelSet::load(&config, &joints)?);
            let bus = OutputBus::new();
            let latch = latch_for(&config, &models)?;
            let inference = Inference::spawn(
                Arc::clone(&models),
                latch,
                bus.clone(),
                config.output.print_forecasts,
            )?;
            let spec = models.spec().clone();
            (
                spec,
                Some(Networks {
                    models,
                    bus,
                    inference,
                }),
            )
        };
        // 3. The recording.
        let recording = match &what {
            What::Replay(path) => Some(ReplayRecording::open(path, &spec)?),
            What::Live | What::Record => None,
        };
        // 4. The shutdown, fired by SIGINT / SIGTERM.
        let trigger = Arc::new(ShutdownTrigger::new().0);
        let signals = shutdown_on_signals(Arc::clone(&trigger));
        // 5. The streams, each behind its input boundary.
        let limits = input_limits(&config, &spec);
        let mut camera_raw = None;
        let inputs = match recording {
            Some(recording) => {
                let stats = PerStream::from_fn(|_| Arc::new(StreamStats::default()));
                let gates = PerStream::from_fn(|kind| {
                    Gate::new(kind, limits.clone(), Arc::clone(&stats[kind]))
                });
                Inputs::Replay { recording, gates }
            }
            None if what == What::Record => {
                let (feed, camera) =
                    stream::<Arc<CompressedImage>>(StreamKind::Camera, limits.clone());
                camera_raw = Some(feed);
                Inputs::Record {
                    streams: LiveStreams::new(limits),
                    camera,
                }
            }
            None => Inputs::Live(LiveStreams::new(limits)),
        };
        // 6. The ROS 2 node and its publisher of the bus.
        let mut ros = if config.ros.enabled {
            Some(RosBridge::start(&config)?)
        } else {
            None
        };
        let publisher = match (ros.as_mut(), &networks) {
            (Some(bridge), Some(n)) => {
                // `run` owns the servo bus when it reads it: what it reads
                // goes out on /joint_states.
                let joints_out = match &inputs {
                    Inputs::Live(streams) if config.streams.joints == JointsSource::Dynamixel => {
                        Some(streams.taps.joints.clone())
                    }
                    _ => None,
                };
                Some(bridge.start_outputs(
                    &config,
                    &n.models,
                    &n.bus,
                    trigger.subscribe(),
                    joints_out,
                )?)
            }
            _ => None,
        };
        // 7. The live sources.
        let sources = match inputs.live_streams() {
            Some(streams) => {
                start_sources(&config, &spec, streams, camera_raw, ros.as_mut(), &trigger)?
            }
            None => Vec::new(),
        };
        // 8. The tick loop.
        let forecasting = match networks {
            Some(n) => {
                let names = match &inputs {
                    Inputs::Replay { recording, .. } => {
                        let source = format!("replay {}", recording.path.display());
                        PerStream::from_fn(|_| (source.clone(), true))
                    }
                    Inputs::Live(_) | Inputs::Record { .. } => source_names(&config),
                };
                let settings = tick_settings(&config, names, &inputs.stats());
                let tick_loop =
                    TickLoop::new(Arc::clone(&n.models), n.inference, settings, n.bus.clone())?;
                Some(Forecasting {
                    models: n.models,
                    bus: n.bus,
                    tick_loop,
                })
            }
            None => None,
        };
        Ok(Running {
            config,
            forecasting,
            inputs,
            trigger,
            signals,
            ros,
            publisher,
            sources,
            tasks: Vec::new(),
        })
    }

    /// A listener of the daemon's shutdown (SIGINT / SIGTERM, or [`Running::stop`]).
    pub fn shutdown(&self) -> Shutdown {
        self.trigger.subscribe()
    }

    /// A task of the command that ends on [`Running::shutdown`] (a bus
    /// subscriber, a sampler): joined at stop, before the ROS 2 node goes.
    pub fn join_at_stop(&mut self, task: JoinHandle<()>) {
        self.tasks.push(task);
    }

    /// Stop the daemon, in the order of the module doc.
    pub async fn stop(self) -> Stopped {
        let Running {
            forecasting,
            trigger,
            signals,
            ros,
            publisher,
            sources,
            tasks,
            ..
        } = self;
        let mut stopped = Stopped::default();
        if let Some(f) = forecasting {
            stopped.inference_died = f.tick_loop.inference().is_dead();
            stopped.counters = f.tick_loop.finish().await;
        }
        let _ = sd_notify::notify(false, &[sd_notify::NotifyState::Stopping]);
        trigger.fire();
        for s in sources {
            s.join().await;
        }
        for t in tasks {
            let _ = t.await;
        }
        if let Some(p) = publisher {
            let _ = p.await;
        }
        // The node goes after every task that used it.
        if let Some(ros) = ros {
            ros.shutdown().await;
        }
        signals.abort();
        stopped
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

/// Start the configured live sources feeding `streams` (the ROS 2 ones on
/// `ros`; `spec`: the joint names and frame size they convert to).
/// `camera_raw` (`record`): the camera's frames as they come, not decoded,
/// go to that feed instead of `streams.feeds.camera`.
fn start_sources(
    config: &Config,
    spec: &WindowSpec,
    streams: &LiveStreams,
    camera_raw: Option<StreamFeed<Arc<CompressedImage>>>,
    ros: Option<&mut RosBridge>,
    shutdown: &ShutdownTrigger,
) -> Result<Vec<SourceHandle>, ServiceError> {
    let mut handles = Vec::new();
    if config.streams.joints == JointsSource::Dynamixel {
        handles.push(start_servo(
            config,
            streams.feeds.joints.clone(),
            shutdown.subscribe(),
        )?);
    }
    if config.streams.camera == CameraSource::V4l2 {
        handles.push(match &camera_raw {
            Some(raw) => start_camera_compressed(config, raw.clone(), shutdown.subscribe())?,
            None => start_camera(
                config,
                spec.frame_size,
                streams.feeds.camera.clone(),
                shutdown.subscribe(),
            )?,
        });
    }
    let camera_from_ros = config.streams.camera == CameraSource::Ros;
    let from_ros = PerStream {
        joints: config.streams.joints == JointsSource::Ros,
        camera: camera_from_ros && camera_raw.is_none(),
        plan: config.streams.plan == PlanSource::Ros,
    };
    let camera_raw = camera_raw.filter(|_| camera_from_ros);
    if from_ros.iter().any(|(_, &ros)| ros) || camera_raw.is_some() {
        // `Config::check_live_sources` makes sure of the node.
        let bridge = ros.ok_or_else(|| {
            ServiceError::Usage(format!(
                "{}: [streams] reads from ROS 2 but [ros].enabled = false",
                config.origin
            ))
        })?;
        let tasks = bridge.start_inputs(
            config,
            spec,
            streams,
            from_ros,
            camera_raw,
            shutdown.subscribe(),
        )?;
        handles.extend(tasks.into_iter().map(SourceHandle::Task));
    }
    Ok(handles)
}

/// Start the servo reader (`[dynamixel]`) offering into the joints `feed`
/// until `shutdown`.
fn start_servo(
    config: &Config,
    feed: StreamFeed<Sample>,
    shutdown: Shutdown,
) -> Result<SourceHandle, ServiceError> {
    let section = config
        .dynamixel
        .as_ref()
        .ok_or_else(|| ServiceError::Usage(format!("{}: [dynamixel] missing", config.origin)))?;
    DynamixelSource::spawn(
        section,
        &JointTable::poppy_humanoid(),
        feed,
        shutdown.watch(),
    )
    .map(|source| SourceHandle::Thread(source.into_thread()))
    .map_err(|e| ServiceError::Usage(format!("{}: [dynamixel].{e}", config.origin)))
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
    frame_size: u32,
    feed: StreamFeed<Sample>,
    shutdown: Shutdown,
) -> Result<SourceHandle, ServiceError> {
    crate::sources::camera::spawn_camera(camera_section(config)?, frame_size, feed, shutdown)
        .map(SourceHandle::Thread)
        .map_err(|e| ServiceError::Source(format!("cannot start the camera thread: {e}")))
}

#[cfg(feature = "camera-v4l")]
fn start_camera_compressed(
    config: &Config,
    feed: StreamFeed<Arc<CompressedImage>>,
    shutdown: Shutdown,
) -> Result<SourceHandle, ServiceError> {
    crate::sources::camera::spawn_camera_compressed(camera_section(config)?, feed, shutdown)
        .map(SourceHandle::Thread)
        .map_err(|e| ServiceError::Source(format!("cannot start the camera thread: {e}")))
}

/// `[camera]` (`Config` checks it is there with `camera = "v4l2"`).
#[cfg(feature = "camera-v4l")]
fn camera_section(config: &Config) -> Result<crate::config::CameraConfig, ServiceError> {
    config
        .camera
        .clone()
        .ok_or_else(|| ServiceError::Usage(format!("{}: [camera] missing", config.origin)))
}

#[cfg(not(feature = "camera-v4l"))]
fn start_camera(
    config: &Config,
    _frame_size: u32,
    _feed: StreamFeed<Sample>,
    _shutdown: Shutdown,
) -> Result<SourceHandle, ServiceError> {
    start_camera_unavailable(config)
}

#[cfg(not(feature = "camera-v4l"))]
fn start_camera_compressed(
    config: &Config,
    _feed: StreamFeed<Arc<CompressedImage>>,
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
