//! The daemon's one lifecycle: the start and stop order shared by `run`,
//! `replay`, `record` and `bench-daemon`.
//!
//! Each command has its type ([`Live`] for `run`, [`Replay`] for `replay`
//! and `bench-daemon`, [`Record`] for `record`) and gets a [`Running`]
//! daemon of that type from its `start` (`Running::<Live>::start`, ...),
//! which holds exactly what the command drives: the forecasting side for
//! `run` and `replay`, the recording for `replay`, the camera's images as
//! received for `record`. It drives them (the live tick, a replay, the
//! recorder) until they end or the shutdown fires, then calls
//! [`Running::stop`], the same for every command.
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
//!    subscriptions, each offering into its stream's feed (a replay offers
//!    the recording's samples into the same feeds as it runs);
//! 8. the tick loop (not for `record`).
//!
//! Stop, in this order: the tick loop (the last inference, the thread
//! joined); sd-notify STOPPING; the shutdown fires; the sources, the
//! command's own tasks ([`Running::join_at_stop`]) and the publisher are
//! joined (the ROS 2 subscriptions end with their tasks); then the ROS 2
//! node leaves the domain ([`RosBridge::shutdown`]), after every task that
//! used it; last the signal listener ends.

use std::path::Path;
use std::sync::Arc;

use tokio::task::JoinHandle;

use crate::config::{CameraSource, Config, JointsSource, PlanSource};
use crate::msgs::CompressedImage;
use crate::outputs::OutputBus;
use crate::pipeline::inference::Inference;
use crate::pipeline::models::ModelSet;
use crate::pipeline::tick::{TickCounters, TickLoop};
use crate::robot::JointTable;
use crate::shutdown::{Shutdown, ShutdownTrigger};
use crate::sources::dynamixel::DynamixelSource;
use crate::sources::replay::ReplayRecording;
use crate::streams::sample::Sample;
use crate::streams::{stream, PerStream, StreamFeed, StreamKind, StreamTap};
use crate::window::WindowSpec;

use super::ros_bridge::RosBridge;
use super::{input_limits, latch_for, robot_joints, tick_settings, LiveStreams, ServiceError};

/// The forecasting side of a running daemon (`run`, `replay`,
/// `bench-daemon`).
pub struct Forecasting {
    pub models: Arc<ModelSet>,
    /// Forecasts and diagnostics, to the publisher and any subscriber.
    pub bus: OutputBus,
    /// Its inference thread runs; [`Running::stop`] finishes it.
    pub tick_loop: TickLoop,
}

/// `run`: the configured live sources, forecasts out (the tick reads the
/// streams' taps).
pub struct Live {
    pub forecasting: Forecasting,
}

/// `replay`, `bench-daemon`: the recording's samples, offered into the
/// streams' feeds at recorded time, forecasts out.
pub struct Replay {
    pub forecasting: Forecasting,
    pub recording: ReplayRecording,
}

/// `record`: joints and plan as `run` has them, the camera as received (not
/// decoded); no network is loaded.
pub struct Record {
    pub camera: StreamTap<Arc<CompressedImage>>,
}

/// What a command drives, and how it ends: the one difference between the
/// commands on the one lifecycle.
pub trait Command {
    /// The forecasting side, to finish at stop (`None` for `record`).
    fn into_forecasting(self) -> Option<Forecasting>;
}

impl Command for Live {
    fn into_forecasting(self) -> Option<Forecasting> {
        Some(self.forecasting)
    }
}

impl Command for Replay {
    fn into_forecasting(self) -> Option<Forecasting> {
        Some(self.forecasting)
    }
}

impl Command for Record {
    fn into_forecasting(self) -> Option<Forecasting> {
        None
    }
}

/// A started daemon running command `C`.
pub struct Running<C: Command> {
    pub config: Config,
    /// The streams, each behind its input boundary: the sources (or the
    /// replay) offer into their feeds, the tick (or the recorder) reads
    /// their taps.
    pub streams: LiveStreams,
    pub command: C,
    lifetime: Lifetime,
}

/// What every command starts and stops the same way.
struct Lifetime {
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

/// The networks, loaded, with their bus and inference thread (start step 2).
struct Networks {
    models: Arc<ModelSet>,
    bus: OutputBus,
    inference: Inference,
}

impl Networks {
    fn load(config: &Config) -> Result<Networks, ServiceError> {
        let models = Arc::new(ModelSet::load(config, &robot_joints(config))?);
        let bus = OutputBus::new();
        let latch = latch_for(config, &models)?;
        let inference = Inference::spawn(
            Arc::clone(&models),
            latch,
            bus.clone(),
            config.output.print_forecasts,
            config.model.out_of_range,
        )?;
        Ok(Networks {
            models,
            bus,
            inference,
        })
    }

    /// Start step 8: the tick loop on `streams`, whose sources are `names`.
    fn into_forecasting(
        self,
        config: &Config,
        names: PerStream<(String, bool)>,
        streams: &LiveStreams,
    ) -> Result<Forecasting, ServiceError> {
        let settings = tick_settings(config, names, &streams.stats());
        let tick_loop = TickLoop::new(
            Arc::clone(&self.models),
            self.inference,
            settings,
            self.bus.clone(),
        )?;
        Ok(Forecasting {
            models: self.models,
            bus: self.bus,
            tick_loop,
        })
    }
}

impl Running<Live> {
    /// `run`: start the daemon on the live sources, in the order of the
    /// module doc.
    pub fn start(config: Config) -> Result<Running<Live>, ServiceError> {
        config.check_live_sources()?;
        let networks = Networks::load(&config)?;
        let spec = networks.models.spec().clone();
        // `run` owns the servo bus when it reads it: what it reads goes out
        // on /joint_states.
        let servo_out = config.streams.joints == JointsSource::Dynamixel;
        let (streams, mut lifetime) = Lifetime::begin(&config, &spec, Some(&networks), servo_out)?;
        lifetime.start_sources(&config, &spec, &streams, None)?;
        let forecasting = networks.into_forecasting(&config, source_names(&config), &streams)?;
        Ok(Running {
            config,
            streams,
            command: Live { forecasting },
            lifetime,
        })
    }
}

impl Running<Replay> {
    /// `replay`, `bench-daemon`: start the daemon on the recording at
    /// `path`, in the order of the module doc.
    pub fn start(config: Config, path: &Path) -> Result<Running<Replay>, ServiceError> {
        let networks = Networks::load(&config)?;
        let spec = networks.models.spec().clone();
        let recording = ReplayRecording::open(path, &spec)?;
        let (streams, lifetime) = Lifetime::begin(&config, &spec, Some(&networks), false)?;
        let source = format!("replay {}", recording.path.display());
        let names = PerStream::from_fn(|_| (source.clone(), true));
        let forecasting = networks.into_forecasting(&config, names, &streams)?;
        Ok(Running {
            config,
            streams,
            command: Replay {
                forecasting,
                recording,
            },
            lifetime,
        })
    }
}

impl Running<Record> {
    /// `record`: start the live sources into a recorder, loading no
    /// network, in the order of the module doc. The window spec carries
    /// only what the inputs need (the joint names, the tick rate; frame
    /// size 0: the camera is not decoded, only its stamps are checked).
    pub fn start(config: Config) -> Result<Running<Record>, ServiceError> {
        config.check_live_sources()?;
        let spec = WindowSpec {
            n_ticks: 1,
            max_horizon_ticks: 0,
            rate_hz: config.robot.tick_rate_hz,
            joint_names: robot_joints(&config),
            frame_size: 0,
        };
        let (streams, mut lifetime) = Lifetime::begin(&config, &spec, None, false)?;
        let (raw, camera) =
            stream::<Arc<CompressedImage>>(StreamKind::Camera, input_limits(&config, &spec));
        lifetime.start_sources(&config, &spec, &streams, Some(raw))?;
        Ok(Running {
            config,
            streams,
            command: Record { camera },
            lifetime,
        })
    }
}

impl<C: Command> Running<C> {
    /// A listener of the daemon's shutdown (SIGINT / SIGTERM, or [`Running::stop`]).
    pub fn shutdown(&self) -> Shutdown {
        self.lifetime.trigger.subscribe()
    }

    /// A task of the command that ends on [`Running::shutdown`] (a bus
    /// subscriber, a sampler): joined at stop, before the ROS 2 node goes.
    pub fn join_at_stop(&mut self, task: JoinHandle<()>) {
        self.lifetime.tasks.push(task);
    }

    /// Stop the daemon, in the order of the module doc.
    pub async fn stop(self) -> Stopped {
        let Lifetime {
            trigger,
            signals,
            ros,
            publisher,
            sources,
            tasks,
        } = self.lifetime;
        let mut stopped = Stopped::default();
        if let Some(f) = self.command.into_forecasting() {
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

impl Lifetime {
    /// Start steps 4-6: the shutdown trigger, the streams for windows of
    /// `spec`, the ROS 2 node and, with `networks`, its publisher of their
    /// bus (with `servo_out`, the joints stream goes out on /joint_states).
    fn begin(
        config: &Config,
        spec: &WindowSpec,
        networks: Option<&Networks>,
        servo_out: bool,
    ) -> Result<(LiveStreams, Lifetime), ServiceError> {
        // 4. The shutdown, fired by SIGINT / SIGTERM.
        let trigger = Arc::new(ShutdownTrigger::new().0);
        let signals = shutdown_on_signals(Arc::clone(&trigger));
        // 5. The streams, each behind its input boundary.
        let streams = LiveStreams::new(input_limits(config, spec));
        // 6. The ROS 2 node and its publisher of the bus.
        let mut ros = if config.ros.enabled {
            Some(RosBridge::start(config)?)
        } else {
            None
        };
        let publisher = match (ros.as_mut(), networks) {
            (Some(bridge), Some(n)) => Some(bridge.start_outputs(
                config,
                &n.models,
                &n.bus,
                trigger.subscribe(),
                servo_out.then(|| streams.taps.joints.clone()),
            )?),
            _ => None,
        };
        let lifetime = Lifetime {
            trigger,
            signals,
            ros,
            publisher,
            sources: Vec::new(),
            tasks: Vec::new(),
        };
        Ok((streams, lifetime))
    }

    /// Start step 7: the configured live sources feeding `streams` (the ROS
    /// 2 ones on the node; `spec`: the joint names and frame size they
    /// convert to). `camera_raw` (`record`): the camera's frames as they
    /// come, not decoded, go to that feed instead of `streams.feeds.camera`.
    fn start_sources(
        &mut self,
        config: &Config,
        spec: &WindowSpec,
        streams: &LiveStreams,
        camera_raw: Option<StreamFeed<Arc<CompressedImage>>>,
    ) -> Result<(), ServiceError> {
        let shutdown = &self.trigger;
        let handles = &mut self.sources;
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
            let bridge = self.ros.as_mut().ok_or_else(|| {
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
        Ok(())
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
