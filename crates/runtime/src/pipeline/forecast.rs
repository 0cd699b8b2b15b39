//! Per-tick inference: which network runs (degradation when a stream is
//! lost), the inference thread, its latency statistics, and the validity of
//! each forecast.
//!
//! Data enters as one [`InferenceJob`] per dispatched tick (built by
//! `tick.rs`: the window of the last N ticks for the chosen ablation, whether
//! it is valid and why not). The inference thread runs the network through
//! one [`StreamingForecaster`] per ablation (per-frame work done once per
//! frame, equal to the whole-window forward to 1e-5), feeds the [`SafetyLatch`], and sends
//! one [`ForecastOutput`] per job to the [`OutputBus`] (and to stdout when
//! asked). A job is only handed over while the thread is idle: an inference
//! that overruns makes the tick loop skip ticks and count them, never queue.
//!
//! Model choice ([`ModelChoice`]): camera lost -> MP, plan lost -> EP, both
//! -> P; a lost camera counts as back once it has been fresh for a whole
//! window (N ticks), so that the bigger network never sees a window holding
//! stale frames; a lost plan as soon as a fresh plan message is there (the
//! window's plan is cut from the newest tick's message alone). The same rule
//! makes a forecast valid again after a stale input the active network
//! reads ([`ModelChoice::refilled`]): the joints, too, need N fresh ticks,
//! except after a brief gap: a run of at most `[streams].joints_max_held_ticks`
//! ticks whose joints were all held (every joint read, some older than the
//! bound) is bridged, and the forecast is valid again on the first fresh
//! tick, while the window holds no more than that many such ticks
//! ([`ModelChoice::stale_ticks`]). Each switch is logged and counted.

use std::collections::VecDeque;
use std::io::Write;
use std::path::{Path, PathBuf};
use std::sync::atomic::{AtomicBool, Ordering};
use std::sync::mpsc;
use std::sync::{Arc, Mutex};
use std::thread::JoinHandle;
use std::time::Instant;

use thiserror::Error;
use tokio::sync::Notify;

use crate::config::{Config, ConfigError, FallbackLoading, ModelFacts};
use crate::model::{
    Ablation, LoadedModel, ModelError, ProjectionWeights, StreamingForecaster, TrajectoryInput,
};
use crate::outputs::latch::SafetyLatch;
use crate::outputs::{ForecastOutput, OutputBus};
use crate::streams::StreamKind;
use crate::window::{TickInput, WindowSpec};

#[derive(Debug, Error)]
pub enum ForecastError {
    #[error("{key}: {file}: {source}")]
    Load {
        key: String,
        file: PathBuf,
        #[source]
        source: ModelError,
    },
    #[error("{key}: {file} holds a {found} network, expected {expected}")]
    WrongAblation {
        key: String,
        file: PathBuf,
        found: Ablation,
        expected: Ablation,
    },
    #[error("{key}: {file} does not fit this robot: {source}")]
    Incompatible {
        key: String,
        file: PathBuf,
        #[source]
        source: ModelError,
    },
    #[error("{key}: {file}: {what} differs from [model].emp ({emp}): the fallbacks must share the window")]
    Mismatch {
        key: String,
        file: PathBuf,
        what: &'static str,
        emp: String,
    },
    #[error("{key}: {file} was trained with the {trajectory} trajectory input (a paper ablation for the model card): the daemon runs networks that read the planned trajectory only; configure a model trained with `fall-guard-lab train --trajectory planned`")]
    Trajectory {
        key: String,
        file: PathBuf,
        trajectory: TrajectoryInput,
    },
    #[error(transparent)]
    Config(#[from] ConfigError),
    #[error("cannot start the inference thread: {0}")]
    Thread(std::io::Error),
}

/// The name of an ablation as published ("EMP", "MP", ...).
pub fn ablation_name(ablation: Ablation) -> &'static str {
    match ablation {
        Ablation::P => "P",
        Ablation::MP => "MP",
        Ablation::EP => "EP",
        Ablation::EMP => "EMP",
    }
}

/// The networks of one configuration: EMP and the fallbacks that are
/// configured, all on the same window. With `[model].fallbacks =
/// "when_needed"` a fallback is checked at start, released, and loaded again
/// at its first use ([`ModelSet::model`]), then kept.
#[derive(Debug)]
pub struct ModelSet {
    slots: Vec<ModelSlot>,
    spec: WindowSpec,
    horizons_ms: Vec<u32>,
    robot_joints: Vec<String>,
    /// `[model].projection`, applied to every network as it is loaded.
    projection: ProjectionWeights,
}

/// One configured network: its file, and the network while in memory.
#[derive(Debug)]
struct ModelSlot {
    key: &'static str,
    ablation: Ablation,
    path: PathBuf,
    loaded: Mutex<Option<LoadedModel>>,
}

impl ModelSlot {
    fn loaded(&self) -> std::sync::MutexGuard<'_, Option<LoadedModel>> {
        self.loaded.lock().unwrap_or_else(|e| e.into_inner())
    }
}

/// Loads `path` for `key` and refuses a file that is not the ablation its
/// key names, does not fit the robot's joints, or (for a fallback) does not
/// share EMP's window.
fn load_checked(
    key: &str,
    path: &Path,
    expected: Ablation,
    robot_joints: &[String],
    emp: Option<&LoadedModel>,
) -> Result<LoadedModel, ForecastError> {
    let model = LoadedModel::load(path).map_err(|source| ForecastError::Load {
        key: key.to_string(),
        file: path.to_path_buf(),
        source,
    })?;
    let meta = &model.meta;
    if meta.ablation != expected {
        return Err(ForecastError::WrongAblation {
            key: key.to_string(),
            file: path.to_path_buf(),
            found: meta.ablation,
            expected,
        });
    }
    // The stream freshness and fallback rules below are written for
    // networks whose trajectory encoder reads the plan stream.
    if meta.config.trajectory != TrajectoryInput::Planned {
        return Err(ForecastError::Trajectory {
            key: key.to_string(),
            file: path.to_path_buf(),
            trajectory: meta.config.trajectory,
        });
    }
    meta.check_compatible_with(
        robot_joints,
        meta.rate_hz,
        meta.n_ticks,
        meta.config.max_horizon_ticks(),
        meta.frame_size,
    )
    .map_err(|source| ForecastError::Incompatible {
        key: key.to_string(),
        file: path.to_path_buf(),
        source,
    })?;
    if let Some(emp) = emp {
        let e = &emp.meta;
        let what = if e.n_ticks != meta.n_ticks {
            Some("window length N")
        } else if (e.rate_hz - meta.rate_hz).abs() > 1e-9 {
            Some("tick rate")
        } else if e.horizons_ticks != meta.horizons_ticks {
            Some("horizons")
        } else {
            None
        };
        if let Some(what) = what {
            return Err(ForecastError::Mismatch {
                key: key.to_string(),
                file: path.to_path_buf(),
                what,
                emp: emp.path.display().to_string(),
            });
        }
    }
    Ok(model)
}

impl ModelSet {
    /// Loads `[model].emp` and the configured fallbacks, refusing a file
    /// that is not the ablation its key names, does not fit the robot's
    /// joints, or does not share EMP's window; checks `[model].horizon_ms`.
    /// With `[model].fallbacks = "when_needed"` the fallbacks are released
    /// once checked.
    pub fn load(config: &Config, robot_joints: &[String]) -> Result<ModelSet, ForecastError> {
        let m = &config.model;
        let entries = [
            ("[model].emp", Some(&m.emp), Ablation::EMP),
            ("[model].mp", m.mp.as_ref(), Ablation::MP),
            ("[model].ep", m.ep.as_ref(), Ablation::EP),
            ("[model].p", m.p.as_ref(), Ablation::P),
        ];
        let mut slots: Vec<ModelSlot> = Vec::new();
        let mut emp: Option<LoadedModel> = None;
        for (key, file, expected) in entries {
            let Some(file) = file else { continue };
            let path = config.model_path(file);
            let model = load_checked(key, &path, expected, robot_joints, emp.as_ref())?
                .with_projection(m.projection);
            let meta = &model.meta;
            tracing::info!(key, file = %path.display(), ablation = ablation_name(meta.ablation),
                trained_on = %meta.trained_on, best_epoch = meta.best_epoch,
                projection = m.projection.name(),
                projection_mb = format!("{:.1}", model.network.projection_bytes() as f64 / 1e6),
                "network ready");
            if emp.is_none() {
                emp = Some(model.clone());
            }
            let keep = expected == Ablation::EMP || m.fallbacks == FallbackLoading::AtStart;
            if !keep {
                tracing::info!(key, "checked; released until it is first needed ([model].fallbacks = \"when_needed\")");
            }
            slots.push(ModelSlot {
                key,
                ablation: expected,
                path,
                loaded: Mutex::new(keep.then_some(model)),
            });
        }
        let emp = emp.expect("[model].emp is required");
        let horizons_ms = emp.meta.horizons_ms();
        config.check_against_model(
            &ModelFacts {
                horizons_ms: horizons_ms.clone(),
                joint_names: emp.meta.joint_names.clone(),
                rate_hz: emp.meta.rate_hz,
                n_ticks: emp.meta.n_ticks,
            },
            robot_joints,
        )?;
        let spec = emp.meta.window_spec();
        drop(emp);
        release_freed_memory();
        Ok(ModelSet {
            slots,
            spec,
            horizons_ms,
            robot_joints: robot_joints.to_vec(),
            projection: m.projection,
        })
    }

    /// Wraps networks already in memory (tests, benches); the first is EMP.
    pub fn from_models(models: Vec<LoadedModel>) -> ModelSet {
        let emp = &models[0].meta;
        let spec = emp.window_spec();
        let horizons_ms = emp.horizons_ms();
        let robot_joints = emp.joint_names.clone();
        ModelSet {
            spec,
            horizons_ms,
            robot_joints,
            projection: ProjectionWeights::AsFile,
            slots: models
                .into_iter()
                .map(|m| ModelSlot {
                    key: "(in memory)",
                    ablation: m.meta.ablation,
                    path: m.path.clone(),
                    loaded: Mutex::new(Some(m)),
                })
                .collect(),
        }
    }

    pub fn spec(&self) -> &WindowSpec {
        &self.spec
    }

    pub fn horizons_ms(&self) -> &[u32] {
        &self.horizons_ms
    }

    /// Which ablations are configured and were checked at start (in memory
    /// or not).
    pub fn available(&self) -> Vec<Ablation> {
        self.slots.iter().map(|s| s.ablation).collect()
    }

    /// Which ablations are in memory now.
    pub fn in_memory(&self) -> Vec<Ablation> {
        self.slots
            .iter()
            .filter(|s| s.loaded().is_some())
            .map(|s| s.ablation)
            .collect()
    }

    /// The network of `ablation`, loading it (and checking it again against
    /// EMP and the robot) when it is not in memory; `Ok(None)` when it is not
    /// configured. A load here is the first switch to a `"when_needed"`
    /// fallback; its time is logged.
    pub fn model(&self, ablation: Ablation) -> Result<Option<LoadedModel>, ForecastError> {
        let Some(slot) = self.slots.iter().find(|s| s.ablation == ablation) else {
            return Ok(None);
        };
        if let Some(m) = slot.loaded().as_ref() {
            return Ok(Some(m.clone()));
        }
        let emp = self.slots.first().and_then(|s| s.loaded().clone());
        let started = std::time::Instant::now();
        let model = load_checked(
            slot.key,
            &slot.path,
            ablation,
            &self.robot_joints,
            emp.as_ref().filter(|e| e.meta.ablation != ablation),
        )?
        .with_projection(self.projection);
        // As at start: hand the load's transient heap back to the system,
        // or the resident memory keeps the load's peak (`docs/performance.md`).
        release_freed_memory();
        tracing::info!(key = slot.key, file = %slot.path.display(),
            load_ms = format!("{:.1}", started.elapsed().as_secs_f64() * 1e3),
            "fallback loaded at its first use");
        *slot.loaded() = Some(model.clone());
        Ok(Some(model))
    }

    /// File of a configured ablation.
    pub fn file(&self, ablation: Ablation) -> Option<&Path> {
        self.slots
            .iter()
            .find(|s| s.ablation == ablation)
            .map(|s| s.path.as_path())
    }
}

/// Loading a network allocates several times its size for a moment (file
/// bytes, the record, the f16 -> f32 cast, the randomly initialised module
/// it replaces); glibc keeps such freed heap mapped. Hand it back to the
/// system once the networks are loaded, so the daemon's resident memory is
/// what it uses.
fn release_freed_memory() {
    #[cfg(all(target_os = "linux", target_env = "gnu"))]
    // SAFETY: malloc_trim only returns free heap pages to the kernel; it
    // touches no memory that is in use.
    unsafe {
        libc::malloc_trim(0);
    }
}

/// Which streams are fresh (not stale) at one tick.
pub type Freshness = crate::streams::PerStream<bool>;

/// The joints of one tick, as the refill rule sees them.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum JointsAt {
    /// Every joint read, none older than `[streams].joints_stale_ms`.
    Fresh,
    /// Every joint read, some older than the bound: the tick holds their
    /// last values (a gap of at most `joints_max_held_ticks` such ticks is
    /// bridged).
    Held,
    /// A joint never read, or no joints sample yet: nothing to bridge with.
    Missing,
}

/// The joints' gaps (runs of ticks that were not fresh) as counted by
/// [`ModelChoice`], for `/diagnostics`.
#[derive(Debug, Clone, Copy, Default, PartialEq, Eq)]
pub struct JointGaps {
    /// Gaps over when the forecast was valid on their first fresh tick (a
    /// brief gap of held values, bridged).
    pub bridged: u64,
    /// Gaps over after which the window had to refill (longer than the
    /// bridge, a joint not read, or too many held ticks in the window).
    pub refilled: u64,
}

/// Chooses the network per tick from stream freshness (see module docs).
#[derive(Debug, Clone)]
pub struct ModelChoice {
    available: Vec<Ablation>,
    active: Ablation,
    /// Consecutive fresh ticks of each stream (0 on a stale tick).
    runs: crate::streams::PerStream<usize>,
    /// Fresh ticks after which a stream counts as back
    /// ([`ModelChoice::refill_ticks`]).
    refill: crate::streams::PerStream<usize>,
    /// `N`, the ticks of the window.
    window_ticks: usize,
    /// `[streams].joints_max_held_ticks`: the longest gap of held joints
    /// bridged, and the most held ticks a valid window may hold.
    max_held: usize,
    /// The joints of the last `N + max_held` ticks, oldest first: the
    /// window and, before it, as many ticks as a bridged gap may last (to
    /// tell whether a gap at the window's start began before it).
    joints: VecDeque<JointsAt>,
    /// Whether the joints were fresh at some tick (a run of stale ticks
    /// before that is the start, not a gap).
    joints_seen_fresh: bool,
    gaps: JointGaps,
    switches: u64,
}

/// Preference order: the most informed network first.
const PREFERENCE: [Ablation; 4] = [Ablation::EMP, Ablation::MP, Ablation::EP, Ablation::P];

/// The most informed of `available` that needs only the streams the
/// config provides (`camera = "none"`: no vision network): what the model
/// choice runs when nothing is lost, so running it is not a degradation.
pub fn best_configured(available: &[Ablation], camera: bool, plan: bool) -> Option<Ablation> {
    PREFERENCE
        .into_iter()
        .find(|a| available.contains(a) && (camera || !a.uses_vision()) && (plan || !a.uses_plan()))
}

impl ModelChoice {
    /// A choice among `available` for windows of `window_ticks` ticks that
    /// bridges no gap of the joints (each needs a whole window of fresh
    /// ticks; [`ModelChoice::bridging`] sets the bridge).
    pub fn new(available: Vec<Ablation>, window_ticks: usize) -> ModelChoice {
        ModelChoice {
            available,
            active: Ablation::EMP,
            runs: Default::default(),
            refill: crate::streams::PerStream {
                joints: window_ticks,
                camera: window_ticks,
                plan: 1,
            },
            window_ticks,
            max_held: 0,
            joints: VecDeque::with_capacity(window_ticks + 1),
            joints_seen_fresh: false,
            gaps: JointGaps::default(),
            switches: 0,
        }
    }

    /// The same choice, bridging a gap of at most `max_held_ticks` ticks of
    /// held joints (`[streams].joints_max_held_ticks`).
    pub fn bridging(mut self, max_held_ticks: usize) -> ModelChoice {
        self.max_held = max_held_ticks;
        self.joints = VecDeque::with_capacity(self.window_ticks + max_held_ticks + 1);
        self
    }

    /// `[streams].joints_max_held_ticks` as given to
    /// [`ModelChoice::bridging`].
    pub fn max_held_ticks(&self) -> usize {
        self.max_held
    }

    /// The ticks of the window (the last N updates) whose joints were not
    /// fresh: held past the bound (in a valid window: the bridged ones), or
    /// missing.
    pub fn stale_ticks(&self) -> usize {
        self.window().filter(|&j| j != JointsAt::Fresh).count()
    }

    /// The joints' gaps so far.
    pub fn joint_gaps(&self) -> JointGaps {
        self.gaps
    }

    /// The joints of the last N updates, oldest first.
    fn window(&self) -> impl Iterator<Item = JointsAt> + '_ {
        let skip = self.joints.len().saturating_sub(self.window_ticks);
        self.joints.iter().skip(skip).copied()
    }

    /// Whether the window's joints can be trusted: every tick fresh, or the
    /// newest fresh and each other one fresh or held (not missing) in a run
    /// of at most `max_held` held ticks (counted from where it began, also
    /// before the window), with at most `max_held` held ticks in the
    /// window.
    fn joints_usable(&self) -> bool {
        if self.runs.joints >= self.window_ticks {
            return true;
        }
        if self.max_held == 0 || self.runs.joints == 0 || self.joints.len() < self.window_ticks {
            return false;
        }
        let skip = self.joints.len().saturating_sub(self.window_ticks);
        let mut held = 0;
        // The run of held ticks being walked, and its length so far.
        let mut run = 0;
        for (i, &j) in self.joints.iter().enumerate() {
            match j {
                JointsAt::Fresh => run = 0,
                JointsAt::Missing if i >= skip => return false,
                // Before the window: only the length of a gap that goes on
                // into it counts.
                JointsAt::Missing => run = self.max_held,
                JointsAt::Held => {
                    run += 1;
                    if i >= skip {
                        held += 1;
                        if run > self.max_held || held > self.max_held {
                            return false;
                        }
                    }
                }
            }
        }
        true
    }

    pub fn active(&self) -> Ablation {
        self.active
    }

    pub fn switches(&self) -> u64 {
        self.switches
    }

    /// Consecutive fresh ticks of `stream` up to the last update.
    pub fn fresh_ticks(&self, stream: StreamKind) -> usize {
        self.runs[stream]
    }

    /// How many consecutive fresh ticks make `stream` usable again after it
    /// was stale: the joints and the camera frames are read over the whole
    /// window, so N (every tick of the window fresh again); the plan is read
    /// from the newest tick's plan message only (which holds the window's
    /// past and future plan), so 1: a fresh plan message is usable at once.
    pub fn refill_ticks(&self, stream: StreamKind) -> usize {
        self.refill[stream]
    }

    /// True when `stream` has been fresh for [`ModelChoice::refill_ticks`]
    /// ticks: a stream that was stale or absent counts as back only then,
    /// so that no window holding a stale value is trusted. The joints also
    /// count as back on the first fresh tick after a bridged gap (see the
    /// module docs): a window holding at most `joints_max_held_ticks` ticks
    /// of held joints, each in a gap no longer than that.
    pub fn refilled(&self, stream: StreamKind) -> bool {
        match stream {
            StreamKind::Joints => self.joints_usable(),
            _ => self.fresh_ticks(stream) >= self.refill_ticks(stream),
        }
    }

    /// Update with one tick's freshness; returns the new ablation if it
    /// changed. Joints that are not fresh count as missing (no gap of them
    /// is bridged: [`ModelChoice::update_ticks`] tells held from missing).
    pub fn update(&mut self, fresh: Freshness) -> Option<Ablation> {
        let joints = if fresh.joints {
            JointsAt::Fresh
        } else {
            JointsAt::Missing
        };
        self.update_ticks(fresh, joints)
    }

    /// Update with one tick's freshness and its joints (`Fresh` exactly
    /// when `fresh.joints`); returns the new ablation if it changed.
    pub fn update_ticks(&mut self, fresh: Freshness, joints: JointsAt) -> Option<Ablation> {
        let joints = match (fresh.joints, joints) {
            (true, _) => JointsAt::Fresh,
            (false, JointsAt::Fresh) => JointsAt::Missing,
            (false, other) => other,
        };
        let gap_over = fresh.joints && self.runs.joints == 0 && self.joints_seen_fresh;
        self.runs = self
            .runs
            .map(|kind, run| if fresh[kind] { run + 1 } else { 0 });
        if self.joints.len() == self.window_ticks + self.max_held {
            self.joints.pop_front();
        }
        self.joints.push_back(joints);
        if gap_over {
            if self.joints_usable() {
                self.gaps.bridged += 1;
            } else {
                self.gaps.refilled += 1;
            }
        }
        self.joints_seen_fresh |= fresh.joints;
        // A stream the active network reads may stay as long as it is fresh;
        // one it does not read must be back for a whole window first.
        let usable = |uses: bool, active_uses: bool, fresh: bool, stream: StreamKind| {
            !uses
                || if active_uses {
                    fresh
                } else {
                    self.refilled(stream)
                }
        };
        let current = self.active;
        let choice = PREFERENCE.into_iter().find(|&a| {
            self.available.contains(&a)
                && usable(
                    a.uses_vision(),
                    current.uses_vision(),
                    fresh.camera,
                    StreamKind::Camera,
                )
                && usable(
                    a.uses_plan(),
                    current.uses_plan(),
                    fresh.plan,
                    StreamKind::Plan,
                )
        });
        match choice {
            Some(next) if next != current => {
                self.active = next;
                self.switches += 1;
                tracing::warn!(
                    from = ablation_name(current),
                    to = ablation_name(next),
                    camera_fresh = fresh.camera,
                    plan_fresh = fresh.plan,
                    "model switch"
                );
                Some(next)
            }
            _ => None,
        }
    }
}

/// p50/p99 of a set of durations in µs (nearest rank), in ms.
pub fn percentiles_ms(samples_us: &mut [u32]) -> Option<(f64, f64)> {
    if samples_us.is_empty() {
        return None;
    }
    samples_us.sort_unstable();
    let rank = |q: f64| {
        let i = ((q * samples_us.len() as f64).ceil() as usize).clamp(1, samples_us.len()) - 1;
        f64::from(samples_us[i]) / 1000.0
    };
    Some((rank(0.50), rank(0.99)))
}

/// One tick handed to the inference thread.
#[derive(Debug)]
pub struct InferenceJob {
    pub tick: i64,
    pub stamp_ns: i64,
    pub ablation: Ablation,
    /// The ring (N consecutive ticks, oldest first); while it fills, the
    /// ticks so far (the forecaster prepares its vision slices from them, so
    /// that the first full window costs one tick). The window is cut from it
    /// on the inference thread, off the runtime.
    pub ticks: Vec<TickInput>,
    pub valid: bool,
    pub invalid_reason: String,
    pub sensed_at: Instant,
}

/// What the inference thread reports to the diagnostics.
#[derive(Debug, Default)]
pub struct InferenceStats {
    /// Inference latencies since the last diagnostics snapshot, µs.
    pub latencies_us: Vec<u32>,
    pub forecasts: u64,
    pub errors: u64,
    pub imminent: bool,
    pub latch_triggers: u64,
}

/// Latencies kept between two diagnostics snapshots, at most.
const MAX_LATENCIES: usize = 4096;

/// The inference thread and its hand-over slot.
#[derive(Debug)]
pub struct Inference {
    jobs: Option<mpsc::SyncSender<InferenceJob>>,
    busy: Arc<AtomicBool>,
    idle: Arc<Notify>,
    dead: Arc<AtomicBool>,
    stats: Arc<Mutex<InferenceStats>>,
    handle: Option<JoinHandle<()>>,
}

impl Inference {
    /// Starts the thread. It owns the networks and the latch, and sends every
    /// result to `bus` (and prints it when `print` is set).
    pub fn spawn(
        models: Arc<ModelSet>,
        latch: SafetyLatch,
        bus: OutputBus,
        print: bool,
    ) -> Result<Inference, ForecastError> {
        let (tx, rx) = mpsc::sync_channel::<InferenceJob>(1);
        let busy = Arc::new(AtomicBool::new(false));
        let idle = Arc::new(Notify::new());
        let stats = Arc::new(Mutex::new(InferenceStats::default()));
        let dead = Arc::new(AtomicBool::new(false));
        let (t_busy, t_idle, t_stats, t_dead) = (
            Arc::clone(&busy),
            Arc::clone(&idle),
            Arc::clone(&stats),
            Arc::clone(&dead),
        );
        let handle = std::thread::Builder::new()
            .name("inference".into())
            .spawn(move || {
                inference_loop(
                    &models, latch, &bus, print, &rx, &t_busy, &t_idle, &t_stats, &t_dead,
                )
            })
            .map_err(ForecastError::Thread)?;
        Ok(Inference {
            jobs: Some(tx),
            busy,
            idle,
            dead,
            stats,
            handle: Some(handle),
        })
    }

    /// Hands `job` over if the thread is idle; gives it back if it is still
    /// busy with the previous tick (an overrun: the caller skips the tick).
    pub fn try_dispatch(&self, job: InferenceJob) -> Result<(), InferenceJob> {
        if self.busy.swap(true, Ordering::AcqRel) {
            return Err(job);
        }
        match &self.jobs {
            Some(tx) => tx.try_send(job).map_err(|e| {
                self.busy.store(false, Ordering::Release);
                match e {
                    mpsc::TrySendError::Full(j) | mpsc::TrySendError::Disconnected(j) => j,
                }
            }),
            None => Err(job),
        }
    }

    /// Wait until the previous job is done (replay at maximum speed).
    pub async fn wait_idle(&self) {
        loop {
            let notified = self.idle.notified();
            if !self.busy.load(Ordering::Acquire) || self.is_dead() {
                return;
            }
            notified.await;
        }
    }

    /// True once the thread has ended (a panic in the network).
    pub fn is_dead(&self) -> bool {
        self.dead.load(Ordering::Acquire)
    }

    pub fn stats(&self) -> &Arc<Mutex<InferenceStats>> {
        &self.stats
    }

    /// Let the last job finish and stop the thread.
    pub fn finish(mut self) {
        self.jobs = None;
        if let Some(handle) = self.handle.take() {
            if handle.join().is_err() {
                tracing::error!("inference thread panicked");
            }
        }
    }
}

#[allow(clippy::too_many_arguments)]
fn inference_loop(
    models: &ModelSet,
    mut latch: SafetyLatch,
    bus: &OutputBus,
    print: bool,
    jobs: &mpsc::Receiver<InferenceJob>,
    busy: &AtomicBool,
    idle: &Notify,
    stats: &Mutex<InferenceStats>,
    dead: &AtomicBool,
) {
    let mut logged_error = false;
    let _alive = AliveGuard { busy, idle, dead };
    let mut forecasters = Forecasters::new(models);
    while let Ok(job) = jobs.recv() {
        let mut valid = job.valid;
        let mut invalid_reason = job.invalid_reason;
        let mut probabilities = Vec::new();
        let mut latency_us = None;
        if job.ticks.len() < models.spec().n_ticks {
            forecasters.prepare(job.ablation, &job.ticks);
        } else {
            let started = Instant::now();
            // A refused or failed network: logged once, counted as an error.
            let mut error = None;
            match forecasters.forecast(models, job.ablation, &job.ticks) {
                Ok(p) => {
                    latency_us =
                        Some(u32::try_from(started.elapsed().as_micros()).unwrap_or(u32::MAX));
                    if valid && p.iter().any(|x| !x.is_finite()) {
                        valid = false;
                        invalid_reason = "the network produced a non-finite probability".into();
                    }
                    probabilities = p;
                }
                Err(ForecastFailure::Input(e)) => {
                    valid = false;
                    invalid_reason = e;
                }
                Err(ForecastFailure::Model(e)) => error = Some(format!("inference failed: {e}")),
                Err(ForecastFailure::Unavailable(e)) => {
                    error = Some(format!("network not loaded: {e}"));
                }
            }
            if let Some(e) = error {
                if !logged_error {
                    tracing::error!(tick = job.tick, error = %e, "no forecast (logged once, counted in /diagnostics)");
                    logged_error = true;
                }
                valid = false;
                invalid_reason = e;
                if let Ok(mut s) = stats.lock() {
                    s.errors += 1;
                }
            }
        }
        latch.select(job.ablation);
        let imminent = latch.update(&probabilities, valid);
        let output = ForecastOutput {
            tick: job.tick,
            stamp_ns: job.stamp_ns,
            probabilities,
            horizons_ms: models.horizons_ms().to_vec(),
            valid,
            imminent,
            ablation: ablation_name(job.ablation),
            invalid_reason,
            sensed_at: job.sensed_at,
        };
        if print {
            print_forecast(&output);
        }
        {
            let mut s = stats.lock().unwrap_or_else(|e| e.into_inner());
            if let Some(us) = latency_us {
                if s.latencies_us.len() < MAX_LATENCIES {
                    s.latencies_us.push(us);
                }
                s.forecasts += 1;
            }
            s.imminent = imminent;
            s.latch_triggers = latch.triggers();
        }
        bus.send_forecast(output);
        busy.store(false, Ordering::Release);
        idle.notify_one();
        // Off the tick's path: the next tick's trajectory features, from
        // this tick's plan (used if no new plan arrives before it).
        if let Some(last) = job.ticks.last() {
            if job.ticks.len() >= models.spec().n_ticks {
                forecasters.precompute_next(job.ablation, last);
            }
        }
    }
}

impl From<ModelError> for ForecastFailure {
    /// Input the network refuses makes the forecast not valid; anything
    /// else is a failure of the network.
    fn from(e: ModelError) -> Self {
        match e {
            ModelError::Input(m) => ForecastFailure::Input(m),
            other => ForecastFailure::Model(other),
        }
    }
}

/// Why a forecast could not be computed.
#[derive(Debug)]
enum ForecastFailure {
    /// The window lacks something (a stream never seen in it): not valid.
    Input(String),
    /// The network refused or failed: an error.
    Model(ModelError),
    /// A `"when_needed"` fallback could not be loaded at its first use.
    Unavailable(String),
}

/// One [`StreamingForecaster`] per loaded network, fed tick by tick: the
/// per-frame work (low-pass, the vision slices that do not touch the
/// window's edges) is done once per frame, not once per tick.
struct Forecasters {
    by_ablation: Vec<(Ablation, StreamingForecaster)>,
    /// The last tick a forecaster refused while the ring filled.
    refused_at: Option<i64>,
}

impl Forecasters {
    fn new(models: &ModelSet) -> Forecasters {
        Forecasters {
            by_ablation: models
                .slots
                .iter()
                .filter_map(|s| {
                    s.loaded()
                        .as_ref()
                        .map(|m| (s.ablation, StreamingForecaster::new(m)))
                })
                .collect(),
            refused_at: None,
        }
    }

    /// The forecaster of `ablation`, made (and its network loaded, for a
    /// `"when_needed"` fallback) at its first use.
    fn forecaster(
        &mut self,
        models: &ModelSet,
        ablation: Ablation,
    ) -> Result<&mut StreamingForecaster, ForecastFailure> {
        if let Some(i) = self.by_ablation.iter().position(|(a, _)| *a == ablation) {
            return Ok(&mut self.by_ablation[i].1);
        }
        let model = models
            .model(ablation)
            .map_err(|e| ForecastFailure::Unavailable(e.to_string()))?
            .ok_or_else(|| {
                ForecastFailure::Input(format!("no {} network loaded", ablation_name(ablation)))
            })?;
        self.by_ablation
            .push((ablation, StreamingForecaster::new(&model)));
        Ok(&mut self.by_ablation.last_mut().expect("just pushed").1)
    }

    /// The forecast of `ablation` for the window `ticks` (N consecutive
    /// ticks, oldest first). Only the ticks the forecaster has not seen are
    /// pushed: one per tick normally, the missed ones after an overrun, the
    /// whole window after a model switch or a gap.
    fn forecast(
        &mut self,
        models: &ModelSet,
        ablation: Ablation,
        ticks: &[TickInput],
    ) -> Result<Vec<f32>, ForecastFailure> {
        let forecaster = self.forecaster(models, ablation)?;
        let first = ticks.first().map(|t| t.tick).unwrap_or_default();
        let from = match forecaster.last_tick() {
            // Continue only a forecaster that holds the window's start (one
            // prepared after a refused tick does not).
            Some(last)
                if last >= first - 1
                    && ticks.iter().any(|t| t.tick > last)
                    && forecaster.first_tick().is_some_and(|f| f <= first) =>
            {
                ticks.partition_point(|t| t.tick <= last)
            }
            _ => {
                forecaster.reset();
                0
            }
        };
        for tick in &ticks[from..] {
            if let Err(e) = forecaster.push(tick) {
                // A window with a hole cannot be continued: start again next time.
                forecaster.reset();
                return Err(e.into());
            }
        }
        Ok(forecaster.forecast()?)
    }
}

impl Forecasters {
    /// After the forecast of `last`'s tick by `ablation`'s forecaster: its
    /// trajectory features for the next tick, computed now
    /// ([`StreamingForecaster::precompute_next`]). A failure is left to
    /// that tick's forecast, which computes and reports it itself.
    fn precompute_next(&mut self, ablation: Ablation, last: &TickInput) {
        if let Some((_, f)) = self.by_ablation.iter_mut().find(|(a, _)| *a == ablation) {
            if f.last_tick() == Some(last.tick) {
                if let Err(e) = f.precompute_next(last) {
                    tracing::debug!(tick = last.tick, error = %e, "trajectory features not computed ahead");
                }
            }
        }
    }

    /// While the ring fills (`ticks` fewer than N): pushes the ticks the
    /// forecaster of `ablation` has not seen and computes their vision
    /// slices, without a forecast. A tick the network refuses (a stream not
    /// seen yet) restarts the forecaster after it, so each tick is pushed
    /// once; the full window's forecast reports any such refusal.
    fn prepare(&mut self, ablation: Ablation, ticks: &[TickInput]) {
        let Some(forecaster) = self
            .by_ablation
            .iter_mut()
            .find(|(a, _)| *a == ablation)
            .map(|(_, f)| f)
        else {
            return;
        };
        let (Some(first), Some(newest)) = (ticks.first(), ticks.last()) else {
            return;
        };
        let from = match forecaster.last_tick() {
            Some(last) if last >= first.tick - 1 && last <= newest.tick => {
                ticks.partition_point(|t| t.tick <= last)
            }
            _ => {
                forecaster.reset();
                // After a refused tick, start after it: no tick is pushed twice.
                match self.refused_at {
                    Some(r) if r >= first.tick && r < newest.tick => {
                        ticks.partition_point(|t| t.tick <= r)
                    }
                    _ => 0,
                }
            }
        };
        for tick in &ticks[from..] {
            if forecaster.push(tick).is_err() {
                forecaster.reset();
                self.refused_at = Some(tick.tick);
                return;
            }
        }
        if let Err(e) = forecaster.prepare() {
            tracing::debug!(error = %e, "vision slices not prepared");
            forecaster.reset();
        }
    }
}

/// Marks the inference thread idle and dead when it ends, even by a panic,
/// so that nothing waits for it forever.
struct AliveGuard<'a> {
    busy: &'a AtomicBool,
    idle: &'a Notify,
    dead: &'a AtomicBool,
}

impl Drop for AliveGuard<'_> {
    fn drop(&mut self) {
        self.dead.store(true, Ordering::Release);
        self.busy.store(false, Ordering::Release);
        self.idle.notify_one();
        if std::thread::panicking() {
            tracing::error!("inference thread panicked: forecasts stop, the daemon exits");
        }
    }
}

/// One line per forecast on stdout, for a person watching a replay:
/// `tick 120 t=4.000s EMP valid p=[0.012 0.034 0.101 0.230] imminent=false`.
pub fn format_forecast(f: &ForecastOutput) -> String {
    let probabilities: Vec<String> = f.probabilities.iter().map(|p| format!("{p:.4}")).collect();
    let validity = if f.valid {
        "valid".to_string()
    } else {
        format!("invalid({})", f.invalid_reason)
    };
    format!(
        "tick {} t={:.3}s {} {} p=[{}] imminent={}",
        f.tick,
        f.stamp_ns as f64 / 1e9,
        f.ablation,
        validity,
        probabilities.join(" "),
        f.imminent
    )
}

fn print_forecast(f: &ForecastOutput) {
    let mut out = std::io::stdout().lock();
    // A closed stdout (a pipe whose reader left) must not stop the daemon.
    let _ = writeln!(out, "{}", format_forecast(f));
}

#[cfg(test)]
mod tests {
    use super::*;

    const FRESH: Freshness = Freshness {
        joints: true,
        camera: true,
        plan: true,
    };

    fn all() -> Vec<Ablation> {
        vec![Ablation::EMP, Ablation::MP, Ablation::EP, Ablation::P]
    }

    #[test]
    fn degrades_per_lost_stream_and_returns_after_a_full_window() {
        let mut choice = ModelChoice::new(all(), 3);
        assert_eq!(choice.update(FRESH), None);
        assert_eq!(choice.active(), Ablation::EMP);
        let no_camera = Freshness {
            camera: false,
            ..FRESH
        };
        assert_eq!(choice.update(no_camera), Some(Ablation::MP));
        let neither = Freshness {
            camera: false,
            plan: false,
            ..FRESH
        };
        assert_eq!(choice.update(neither), Some(Ablation::P));
        let no_plan = Freshness {
            plan: false,
            ..FRESH
        };
        // Camera back: it must stay fresh for 3 ticks before EP takes over.
        assert_eq!(choice.update(no_plan), None);
        assert_eq!(choice.update(no_plan), None);
        assert_eq!(choice.update(no_plan), Some(Ablation::EP));
        // Plan back: its newest message is the whole plan input, so EMP
        // again at once.
        assert_eq!(choice.update(FRESH), Some(Ablation::EMP));
        assert_eq!(choice.switches(), 4);
        // The camera lost again and back: a whole window first.
        assert_eq!(choice.update(no_camera), Some(Ablation::MP));
        assert_eq!(choice.update(FRESH), None);
        assert_eq!(choice.update(FRESH), None);
        assert!(!choice.refilled(StreamKind::Camera));
        assert_eq!(choice.update(FRESH), Some(Ablation::EMP));
        assert!(choice.refilled(StreamKind::Camera) && choice.refilled(StreamKind::Plan));
    }

    #[test]
    fn the_joints_and_camera_refill_a_window_the_plan_one_tick() {
        let mut choice = ModelChoice::new(all(), 4);
        let stale = Freshness {
            joints: false,
            camera: false,
            plan: false,
        };
        choice.update(stale);
        choice.update(FRESH);
        assert!(choice.refilled(StreamKind::Plan));
        assert!(!choice.refilled(StreamKind::Joints));
        assert!(!choice.refilled(StreamKind::Camera));
        assert_eq!(choice.fresh_ticks(StreamKind::Joints), 1);
        assert_eq!(choice.refill_ticks(StreamKind::Joints), 4);
        assert_eq!(choice.refill_ticks(StreamKind::Camera), 4);
        assert_eq!(choice.refill_ticks(StreamKind::Plan), 1);
        for _ in 0..3 {
            choice.update(FRESH);
        }
        assert!(choice.refilled(StreamKind::Joints) && choice.refilled(StreamKind::Camera));
    }

    #[test]
    fn a_gap_of_held_joints_is_bridged_only_when_brief_and_read() {
        let stale = Freshness {
            joints: false,
            ..FRESH
        };
        // A window of 6 ticks bridging gaps of at most 2 held ticks.
        let run = |ticks: &[JointsAt]| {
            let mut choice = ModelChoice::new(all(), 6).bridging(2);
            let usable: Vec<bool> = ticks
                .iter()
                .map(|&j| {
                    let fresh = if j == JointsAt::Fresh { FRESH } else { stale };
                    choice.update_ticks(fresh, j);
                    choice.refilled(StreamKind::Joints)
                })
                .collect();
            (usable, choice)
        };
        use JointsAt::{Fresh as F, Held as H, Missing as M};
        // Two held ticks: not usable while held, usable on the first fresh
        // tick; the joints count as stale ticks of the window until they
        // have left it.
        let (usable, choice) = run(&[F, F, F, F, F, F, H, H, F, F]);
        assert_eq!(
            usable,
            [false, false, false, false, false, true, false, false, true, true]
        );
        assert_eq!(choice.stale_ticks(), 2);
        assert_eq!(
            choice.joint_gaps(),
            JointGaps {
                bridged: 1,
                refilled: 0
            }
        );
        // Three: waited out (usable once the window is fresh again).
        let (usable, choice) = run(&[F, F, F, F, F, F, H, H, H, F, F, F, F, F, F, F]);
        assert_eq!(
            &usable[9..],
            [false, false, false, false, false, true, true]
        );
        assert_eq!(
            choice.joint_gaps(),
            JointGaps {
                bridged: 0,
                refilled: 1
            }
        );
        // One tick with a joint not read: nothing to bridge with.
        let (usable, _) = run(&[F, F, F, F, F, F, M, F, F, F, F, F, F]);
        assert_eq!(&usable[7..], [false, false, false, false, false, true]);
        // A long gap (8 held ticks) whose last two are in the window of the
        // first fresh ticks: it began before the window, so it is not
        // brief, though only two of its ticks are left in the window.
        let (usable, _) = run(&[F, H, H, H, H, H, H, H, H, F, F, F, F, F, F]);
        assert_eq!(&usable[9..], [false, false, false, false, false, true]);
        // Two gaps of one held tick each, then a third: at most 2 in the
        // window.
        let (usable, choice) = run(&[F, F, F, F, F, F, H, F, H, F, H, F, F, F]);
        assert_eq!(
            &usable[6..],
            [false, true, false, true, false, false, true, true]
        );
        assert_eq!(
            choice.joint_gaps(),
            JointGaps {
                bridged: 2,
                refilled: 1
            }
        );
        // Bridging nothing: the old rule, a whole window of fresh ticks.
        let mut choice = ModelChoice::new(all(), 6);
        for j in [F, F, F, F, F, F, H] {
            choice.update_ticks(if j == F { FRESH } else { stale }, j);
        }
        for k in 1..=6 {
            choice.update_ticks(FRESH, F);
            assert_eq!(choice.refilled(StreamKind::Joints), k == 6, "{k}");
        }
    }

    #[test]
    fn a_missing_fallback_keeps_the_next_best() {
        let mut choice = ModelChoice::new(vec![Ablation::EMP, Ablation::P], 2);
        assert_eq!(
            choice.update(Freshness {
                camera: false,
                ..FRESH
            }),
            Some(Ablation::P)
        );
        // With only EMP, losing the camera leaves EMP active (forecasts invalid).
        let mut only = ModelChoice::new(vec![Ablation::EMP], 2);
        assert_eq!(
            only.update(Freshness {
                camera: false,
                ..FRESH
            }),
            None
        );
        assert_eq!(only.active(), Ablation::EMP);
    }

    #[test]
    fn the_best_configured_network_follows_the_configured_streams() {
        assert_eq!(best_configured(&all(), true, true), Some(Ablation::EMP));
        assert_eq!(best_configured(&all(), false, true), Some(Ablation::MP));
        assert_eq!(best_configured(&all(), true, false), Some(Ablation::EP));
        assert_eq!(best_configured(&all(), false, false), Some(Ablation::P));
        assert_eq!(
            best_configured(&[Ablation::EMP, Ablation::P], false, true),
            Some(Ablation::P)
        );
        assert_eq!(best_configured(&[Ablation::EMP], false, true), None);
    }

    #[test]
    fn percentiles_use_nearest_rank() {
        let mut v: Vec<u32> = (1..=100).map(|x| x * 1000).collect();
        assert_eq!(percentiles_ms(&mut v), Some((50.0, 99.0)));
        assert_eq!(percentiles_ms(&mut []), None);
        assert_eq!(percentiles_ms(&mut [7000]), Some((7.0, 7.0)));
    }

    #[test]
    fn forecast_line_shows_tick_time_model_and_validity() {
        let f = ForecastOutput {
            tick: 120,
            stamp_ns: 4_000_000_000,
            probabilities: vec![0.0123, 0.5],
            horizons_ms: vec![500, 1000],
            valid: false,
            imminent: true,
            ablation: "MP",
            invalid_reason: "camera stale".into(),
            sensed_at: Instant::now(),
        };
        assert_eq!(
            format_forecast(&f),
            "tick 120 t=4.000s MP invalid(camera stale) p=[0.0123 0.5000] imminent=true"
        );
    }
}
