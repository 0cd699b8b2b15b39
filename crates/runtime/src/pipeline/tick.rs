//! The fixed-rate tick at the model's rate: resampling, staleness, the
//! ring, model choice, hand-over to inference, diagnostics and the watchdog.
//!
//! Samples enter a [`TickLoop`] in model form ([`Sample`]): live, from the
//! latest value of each [`StreamTap`] at every tick ([`run_live`]); in replay,
//! every recorded sample at its recorded time ([`TickLoop::push_sample`] from
//! `sources/replay.rs`). Both feed the same [`Resampler`], which turns them
//! into one [`TickInput`] per grid tick; everything after that is the same
//! code for live and replay. Per tick: push into the [`Ring`], check each
//! stream's age against `[streams].*_stale_ms`, update the [`ModelChoice`],
//! and hand the ring to the inference thread if it is idle, else skip the
//! tick and count an overrun. Every `[output].diagnostics_period_ms` of tick
//! time a [`DiagnosticsSnapshot`] leaves on the [`OutputBus`]. Each tick
//! also pets the systemd watchdog.

use std::sync::Arc;
use std::time::{Duration, Instant};

use crate::clock::unix_now_ns;
use crate::model::Ablation;
use crate::outputs::diagnostics::{
    inputs_diagnostics, model_level, stale_joints_text, stream_diagnostics, JointGapFigures,
    ModelFigures, StreamFigures,
};
use crate::outputs::{
    CounterWindow, DiagnosticsSnapshot, ForecastOutput, ModelDiagnostics, OutputBus, ERROR_WINDOW_S,
};
use crate::pipeline::choice::{best_configured, Freshness, JointsAt, ModelChoice};
use crate::pipeline::inference::{percentiles_ms, print_forecast, Inference, InferenceJob};
use crate::pipeline::models::{ablation_name, ModelSet};
use crate::pipeline::overload::{Budget, Overload, OverloadSettings};
use crate::shutdown::Shutdown;
use crate::streams::input::Seq;
use crate::streams::sample::Sample;
use crate::streams::{PerStream, Stamped, StreamKind, StreamStats, StreamTap};
use crate::window::{Resampler, Ring, TickInput, WindowError};

/// One input stream as the tick sees it.
#[derive(Debug, Clone)]
pub struct StreamSlot {
    pub kind: StreamKind,
    /// Where it comes from, for diagnostics ("replay", "ros /joint_states").
    pub source: String,
    /// False when the config has no source for it (`camera = "none"`).
    pub configured: bool,
    pub stale_ns: i64,
    pub stats: Arc<StreamStats>,
}

/// Everything the tick needs besides the networks.
#[derive(Debug, Clone)]
pub struct TickSettings {
    pub streams: PerStream<StreamSlot>,
    /// `[streams].joints_max_held_ticks`: the longest gap of held joints
    /// bridged ([`ModelChoice::bridging`]).
    pub joints_max_held_ticks: usize,
    pub diagnostics_period_ns: i64,
    pub hardware_id: String,
    pub latch_horizon_ms: u32,
}

/// Counters of a tick loop (for diagnostics, tests and benches).
#[derive(Debug, Clone, Copy, Default, PartialEq, Eq)]
pub struct TickCounters {
    pub ticks: u64,
    pub dispatched: u64,
    pub overruns: u64,
}

/// sd-notify: READY after the first tick, WATCHDOG at half the watchdog period.
#[derive(Debug)]
pub struct Watchdog {
    ready_sent: bool,
    interval: Option<Duration>,
    last: Option<Instant>,
}

impl Watchdog {
    /// Reads `WATCHDOG_USEC`; without systemd both messages are no-ops.
    pub fn from_env() -> Watchdog {
        let mut usec = 0u64;
        let interval =
            sd_notify::watchdog_enabled(false, &mut usec).then(|| Duration::from_micros(usec / 2));
        if let Some(i) = interval {
            tracing::info!(
                every_ms = i.as_millis() as u64,
                "systemd watchdog enabled: pinged from the tick loop"
            );
        }
        Watchdog {
            ready_sent: false,
            interval,
            last: None,
        }
    }

    /// Call once per tick.
    pub fn tick(&mut self) {
        if !self.ready_sent {
            self.ready_sent = true;
            if let Err(e) = sd_notify::notify(false, &[sd_notify::NotifyState::Ready]) {
                tracing::warn!(error = %e, "sd-notify READY failed");
            }
        }
        if let Some(interval) = self.interval {
            if self.last.is_none_or(|t| t.elapsed() >= interval) {
                self.last = Some(Instant::now());
                let _ = sd_notify::notify(false, &[sd_notify::NotifyState::Watchdog]);
            }
        }
    }
}

/// The shared part of live and replay, from samples to inference jobs.
pub struct TickLoop {
    resampler: Resampler,
    ring: Ring,
    models: Arc<ModelSet>,
    choice: ModelChoice,
    inference: Inference,
    settings: TickSettings,
    bus: OutputBus,
    watchdog: Watchdog,
    pending: Vec<TickInput>,
    counters: TickCounters,
    /// Sample counts and stamp at the last diagnostics snapshot.
    diag_samples: PerStream<u64>,
    diag_stamp_ns: Option<i64>,
    /// Per stream, (error total, rejection total) at each snapshot of the
    /// last [`ERROR_WINDOW_S`] seconds of tick time: levels look at errors
    /// and rejections in that window.
    error_history: PerStream<CounterWindow<i64, (u64, u64)>>,
    /// Model-order joint names, to name the joints a reading lacks.
    joint_names: Vec<String>,
    last_valid: bool,
    last_reason: String,
    /// The latest tick whose joints were stale, and why (`/diagnostics`
    /// names it even when the gap was bridged between two snapshots).
    last_joints_stale: Option<(i64, String)>,
    /// When inference runs late: which networks are set aside.
    overload: Overload,
    /// The network of the last job dispatched, and whether it was that
    /// network's first after a switch: a tick skipped meanwhile is charged
    /// to it only when it is the active network's steady work
    /// ([`Budget::Excused`]).
    last_job: Option<(Ablation, bool)>,
}

/// Names of the joints a tick has no angle for: never read (a motor that
/// has not answered since the start).
fn unread_joints(tick: &TickInput, names: &[String]) -> Vec<String> {
    tick.joints_rad.as_ref().map_or_else(Vec::new, |j| {
        j.iter()
            .zip(names)
            .filter(|(v, _)| !v.is_finite())
            .map(|(_, n)| n.clone())
            .collect()
    })
}

/// The joints whose value is older than `stale_ns` at this tick, with
/// their ages in ns, oldest first (joints never read are
/// [`unread_joints`]).
fn stale_joints(tick: &TickInput, names: &[String], stale_ns: i64) -> Vec<(String, i64)> {
    let mut stale: Vec<(String, i64)> = names
        .iter()
        .enumerate()
        .filter_map(|(i, n)| {
            tick.joint_age_ns(i)
                .filter(|&age| age > stale_ns)
                .map(|age| (n.clone(), age))
        })
        .collect();
    stale.sort_by_key(|(_, age)| std::cmp::Reverse(*age));
    stale
}

/// Whether a tick's joints are all usable: every joint read, none older
/// than `stale_ns` (the tick's joints age is its oldest joint's).
fn joints_fresh(tick: &TickInput, stale_ns: i64) -> bool {
    tick.age_ns.joints.is_some_and(|age| age <= stale_ns)
        && tick
            .joints_rad
            .as_ref()
            .is_some_and(|j| j.iter().all(|v| v.is_finite()))
}

/// Whether a tick has a finite angle for every joint (what the network
/// can be fed, however old).
fn joints_complete(tick: &TickInput) -> bool {
    tick.joints_rad
        .as_ref()
        .is_some_and(|j| j.iter().all(|v| v.is_finite()))
}

/// A tick's joints for the refill rule: fresh, held (every joint read,
/// some older than `stale_ns`) or missing.
fn joints_at(tick: &TickInput, stale_ns: i64) -> JointsAt {
    if joints_fresh(tick, stale_ns) {
        JointsAt::Fresh
    } else if joints_complete(tick) {
        JointsAt::Held
    } else {
        JointsAt::Missing
    }
}

/// Why a tick's forecast is not valid (`None`: valid). Valid means: the
/// ring holds N ticks, and every input the active network reads is within
/// its bound (`[streams].*_stale_ms`) over what the network reads of it:
/// the joints and the camera frames of every tick of the window, the plan
/// of the newest tick only (the window's plan, past and future, is cut from
/// the newest tick's plan message). So after a joints or camera value older
/// than its bound the window must refill (N fresh ticks), while a fresh
/// plan message is usable at once ([`ModelChoice::refilled`]). A brief gap
/// of the joints (at most `[streams].joints_max_held_ticks` ticks, every
/// joint read, some held past the bound) is bridged: its own ticks are not
/// valid, the first fresh one after it is.
///
/// The joints are judged per joint: a joint whose motor did not answer in a
/// cycle keeps its last value while that is younger than
/// `joints_stale_ms`; older than that it makes the forecast not valid,
/// naming it. No angle is substituted (the planned one, say): the networks
/// were never trained on a window with a substituted joint, so a forecast
/// from one would be a number nobody measured the worth of.
fn invalid_reason(
    ring: &Ring,
    tick: &TickInput,
    choice: &ModelChoice,
    slots: &PerStream<StreamSlot>,
    joint_names: &[String],
) -> Option<String> {
    if !ring.is_full() {
        return Some(format!(
            "ring filling ({}/{} ticks)",
            ring.len(),
            ring.capacity()
        ));
    }
    let active = choice.active();
    let used = PerStream {
        joints: true,
        camera: active.uses_vision(),
        plan: active.uses_plan(),
    };
    let not_ready: Vec<String> = StreamKind::ALL
        .into_iter()
        .filter(|&kind| used[kind] && !choice.refilled(kind))
        .map(|kind| {
            let stale_ns = slots[kind].stale_ns;
            let unread = if kind == StreamKind::Joints {
                unread_joints(tick, joint_names)
            } else {
                Vec::new()
            };
            match tick.age_ns[kind] {
                None => format!("no {kind} sample yet"),
                Some(_) if !unread.is_empty() => {
                    format!("joints not read: {}", unread.join(", "))
                }
                Some(age) if age > stale_ns && kind == StreamKind::Joints => format!(
                    "joints stale ({} ms old): {}",
                    age / 1_000_000,
                    stale_joints_text(
                        &stale_joints(tick, joint_names, stale_ns),
                        joint_names.len()
                    )
                ),
                Some(age) if age > stale_ns => {
                    format!("{kind} stale ({} ms old)", age / 1_000_000)
                }
                Some(_) if kind == StreamKind::Joints && choice.max_held_ticks() > 0 => format!(
                    "{kind} back, window refilling ({}/{} fresh ticks; {} stale in it, a gap of at most {} held bridged)",
                    choice.fresh_ticks(kind),
                    choice.refill_ticks(kind),
                    choice.stale_ticks(),
                    choice.max_held_ticks()
                ),
                Some(_) => format!(
                    "{kind} back, window refilling ({}/{} fresh ticks)",
                    choice.fresh_ticks(kind),
                    choice.refill_ticks(kind)
                ),
            }
        })
        .collect();
    (!not_ready.is_empty()).then(|| not_ready.join(", "))
}

impl TickLoop {
    pub fn new(
        models: Arc<ModelSet>,
        inference: Inference,
        settings: TickSettings,
        bus: OutputBus,
    ) -> Result<TickLoop, WindowError> {
        let spec = models.spec().clone();
        let overload = Overload::new(OverloadSettings::at_rate(spec.rate_hz));
        Ok(TickLoop {
            resampler: Resampler::new(&spec)?,
            ring: Ring::new(spec.n_ticks),
            choice: ModelChoice::new(models.available(), spec.n_ticks)
                .bridging(settings.joints_max_held_ticks),
            models,
            inference,
            settings,
            bus,
            watchdog: Watchdog::from_env(),
            pending: Vec::new(),
            counters: TickCounters::default(),
            diag_samples: PerStream::default(),
            diag_stamp_ns: None,
            error_history: Default::default(),
            joint_names: spec.joint_names.clone(),
            last_valid: false,
            last_reason: String::new(),
            last_joints_stale: None,
            overload,
            last_job: None,
        })
    }

    /// Feed one sample in model form (stamps in non-decreasing order per stream).
    pub fn push_sample(&mut self, sample: Sample) {
        self.resampler.push(sample, &mut self.pending);
    }

    /// Declare that no sample at or before `now_ns` will come: every tick up
    /// to it becomes final.
    pub fn advance_to(&mut self, now_ns: i64) {
        self.resampler.advance_to(now_ns, &mut self.pending);
    }

    /// Stamp of the next tick to become final (`None` before the first sample).
    pub fn next_tick_stamp(&self) -> Option<i64> {
        self.resampler
            .next_tick()
            .map(|t| self.resampler.grid().stamp_ns(t))
    }

    /// Ticks made final since the last call, waiting to be run.
    pub fn pending_ticks(&self) -> usize {
        self.pending.len()
    }

    pub fn counters(&self) -> TickCounters {
        self.counters
    }

    pub fn active(&self) -> Ablation {
        self.choice.active()
    }

    pub fn inference(&self) -> &Inference {
        &self.inference
    }

    /// Run the ticks made final. With `lockstep` (replay at maximum speed)
    /// every tick waits for the previous inference and none is skipped;
    /// otherwise only the newest tick may be dispatched, and only if the
    /// inference thread is idle: every other one is an overrun.
    pub async fn run_pending(&mut self, sensed_at: Instant, lockstep: bool) {
        let ticks = std::mem::take(&mut self.pending);
        let last = ticks.len().saturating_sub(1);
        for (i, tick) in ticks.into_iter().enumerate() {
            self.run_tick(tick, sensed_at, lockstep || i == last, lockstep)
                .await;
        }
    }

    async fn run_tick(
        &mut self,
        tick: TickInput,
        sensed_at: Instant,
        dispatch: bool,
        lockstep: bool,
    ) {
        self.counters.ticks += 1;
        self.watchdog.tick();
        let slots = &self.settings.streams;
        let joints = joints_at(&tick, slots.joints.stale_ns);
        let fresh: Freshness = PerStream::from_fn(|kind| match kind {
            StreamKind::Joints => joints == JointsAt::Fresh,
            _ => tick.age_ns[kind].is_some_and(|age| age <= slots[kind].stale_ns),
        });
        self.choice.update_ticks(fresh, joints);
        let (tick_index, stamp_ns) = (tick.tick, tick.stamp_ns);
        self.ring.push(tick);
        let active = self.choice.active();
        let latest = self.ring.latest().cloned();
        let reason = latest
            .as_ref()
            .and_then(|t| invalid_reason(&self.ring, t, &self.choice, slots, &self.joint_names));
        self.last_valid = reason.is_none();
        self.last_reason = reason.clone().unwrap_or_default();
        if let Some(r) = reason.as_ref().filter(|r| r.contains("joints stale")) {
            self.last_joints_stale = Some((tick_index, r.clone()));
        }
        if dispatch {
            if lockstep {
                self.inference.wait_idle().await;
            }
            // A window with a joint never read is not run (the network
            // would refuse it): the forecast is not valid and says why.
            // Every other window goes to the network, valid or not, so that
            // its forecaster follows the ring tick by tick and a window
            // refilling after a stale input costs one tick's work when it
            // becomes valid again. While the ring fills, the ticks so far go
            // to the network (vision slices prepared ahead of the first
            // forecast).
            let ticks = if self.ring.iter().all(joints_complete) {
                self.ring.iter().cloned().collect()
            } else {
                Vec::new()
            };
            let job = InferenceJob {
                tick: tick_index,
                stamp_ns,
                ablation: active,
                ticks,
                valid: reason.is_none(),
                invalid_reason: reason.unwrap_or_default(),
                sensed_at,
            };
            match self.inference.try_dispatch(job) {
                Ok(()) => {
                    self.counters.dispatched += 1;
                    let switched = self.last_job.is_none_or(|(a, _)| a != active);
                    self.last_job = Some((active, switched));
                    self.budget(Budget::Kept, active);
                }
                Err(_) => self.overrun(tick_index, stamp_ns, active, sensed_at),
            }
        } else {
            self.overrun(tick_index, stamp_ns, active, sensed_at);
        }
        self.maybe_diagnostics(stamp_ns, latest.as_ref());
    }

    /// A tick skipped because the inference of an earlier one is still
    /// running: counted, published as NaN with its reason (the latch's
    /// state unchanged), and judged by the overload policy.
    fn overrun(&mut self, tick: i64, stamp_ns: i64, active: Ablation, sensed_at: Instant) {
        self.counters.overruns += 1;
        if self.counters.overruns == 1 || self.counters.overruns.is_power_of_two() {
            tracing::warn!(
                tick,
                overruns = self.counters.overruns,
                "inference overrun: tick skipped"
            );
        }
        let imminent = self
            .inference
            .stats()
            .lock()
            .map(|s| s.imminent)
            .unwrap_or(true);
        let skipped = ForecastOutput {
            tick,
            stamp_ns,
            probabilities: Vec::new(),
            horizons_ms: self.models.horizons_ms().to_vec(),
            valid: false,
            imminent,
            ablation: ablation_name(active),
            invalid_reason: format!(
                "skipped: the inference of an earlier tick was still running ({} ticks skipped since start)",
                self.counters.overruns
            ),
            out_of_range: String::new(),
            skipped: true,
            sensed_at,
        };
        if self.inference.prints() {
            print_forecast(&skipped);
        }
        self.bus.send_forecast(skipped);
        let budget = match self.last_job {
            Some((network, first)) if network != active || first => Budget::Excused,
            _ => Budget::Missed,
        };
        self.budget(budget, active);
    }

    /// One tick's budget to the overload policy; a network it sets aside
    /// (or tries again) reaches the model choice.
    fn budget(&mut self, budget: Budget, active: Ablation) {
        let lighter = self.choice.has_lighter();
        if self.overload.tick(budget, active, lighter).is_some() {
            self.choice.set_aside(self.overload.set_aside());
        }
    }

    fn maybe_diagnostics(&mut self, stamp_ns: i64, latest: Option<&TickInput>) {
        let since = *self.diag_stamp_ns.get_or_insert(stamp_ns);
        let period_ns = stamp_ns - since;
        if period_ns < self.settings.diagnostics_period_ns {
            return;
        }
        self.diag_stamp_ns = Some(stamp_ns);
        let snapshot = self.diagnostics(stamp_ns, period_ns, latest);
        self.bus.send_diagnostics(snapshot);
    }

    /// Build a diagnostics snapshot now (also used at the end of a replay):
    /// the figures gathered here, their meaning decided in
    /// `outputs::diagnostics`.
    pub fn diagnostics(
        &mut self,
        stamp_ns: i64,
        period_ns: i64,
        latest: Option<&TickInput>,
    ) -> DiagnosticsSnapshot {
        let active = self.choice.active();
        let age = |kind: StreamKind| latest.and_then(|t| t.age_ns[kind]);
        let period_s = (period_ns as f64 / 1e9).max(1e-9);
        let mut streams = Vec::with_capacity(3);
        let mut devices = Vec::new();
        for (kind, slot) in self.settings.streams.iter() {
            let stats = slot.stats.snapshot();
            let rate_hz =
                (stats.samples - self.diag_samples[kind].min(stats.samples)) as f64 / period_s;
            self.diag_samples[kind] = stats.samples;
            let window_ns = ERROR_WINDOW_S as i64 * 1_000_000_000;
            // Errors (rejections) since the newest snapshot at or before the
            // window's start (all of them while the run is younger than the
            // window).
            let history = &mut self.error_history[kind];
            history.push(stamp_ns, window_ns, (stats.errors, stats.rejected));
            let (recent_errors, recent_rejected) = match history.window_start(stamp_ns, window_ns) {
                Some(&(_, (e, r))) => (
                    stats.errors.saturating_sub(e),
                    stats.rejected.saturating_sub(r),
                ),
                None => (stats.errors, stats.rejected),
            };
            let (unread, stale) = match (kind, latest) {
                (StreamKind::Joints, Some(t)) => (
                    unread_joints(t, &self.joint_names),
                    stale_joints(t, &self.joint_names, slot.stale_ns),
                ),
                _ => (Vec::new(), Vec::new()),
            };
            // The joints' gaps: how many were bridged on held values, how
            // many waited out, the ticks of the window that were not fresh
            // (bridged ones while the forecast is valid), the last stale
            // tick and its joints.
            let gaps = (kind == StreamKind::Joints).then(|| {
                let gaps = self.choice.joint_gaps();
                JointGapFigures {
                    stale_ticks_in_window: self.choice.stale_ticks(),
                    max_held_ticks: self.choice.max_held_ticks(),
                    bridged: gaps.bridged,
                    refilled: gaps.refilled,
                    last_stale: self
                        .last_joints_stale
                        .as_ref()
                        .map(|(tick, r)| format!("tick {tick}: {r}"))
                        .unwrap_or_default(),
                }
            });
            devices.extend(stats.devices.iter().cloned());
            streams.push(stream_diagnostics(StreamFigures {
                stream: slot.kind.as_str(),
                source: slot.source.clone(),
                configured: slot.configured,
                stale_ns: slot.stale_ns,
                stats: &stats,
                rate_hz,
                age_ns: age(kind),
                recent_errors,
                recent_rejected,
                unread,
                stale,
                n_joints: self.joint_names.len(),
                gaps,
            }));
        }
        let (mut latencies, forecasts, errors, imminent, guard) = {
            let mut s = self
                .inference
                .stats()
                .lock()
                .unwrap_or_else(|e| e.into_inner());
            (
                std::mem::take(&mut s.latencies_us),
                s.forecasts,
                s.errors,
                s.imminent,
                s.guard.clone(),
            )
        };
        let percentiles = percentiles_ms(&mut latencies);
        let s = &self.settings.streams;
        let expected = best_configured(
            &self.models.available(),
            s.camera.configured,
            s.plan.configured,
        );
        let names = |v: &[Ablation]| v.iter().map(|&a| ablation_name(a)).collect::<Vec<_>>();
        let (level, message, valid, invalid_reason) = model_level(&ModelFigures {
            errors,
            valid: self.last_valid,
            reason: self.last_reason.clone(),
            guard: &guard,
            active: ablation_name(active),
            expected: expected.map(ablation_name),
            set_aside: names(self.overload.set_aside()),
            overload_last: self.overload.last.as_ref().map(ToString::to_string),
            retry_in_ticks: self.overload.retry_in_ticks(),
            configured_streams: configured_streams(&self.settings.streams),
        });
        DiagnosticsSnapshot {
            stamp_ns,
            hardware_id: self.settings.hardware_id.clone(),
            streams,
            devices,
            model: ModelDiagnostics {
                level,
                message,
                active_ablation: ablation_name(active),
                model_file: self
                    .models
                    .file(active)
                    .map(|p| p.display().to_string())
                    .unwrap_or_default(),
                inference_p50_ms: percentiles.map(|p| p.0),
                inference_p99_ms: percentiles.map(|p| p.1),
                overruns: self.counters.overruns,
                ticks: self.counters.ticks,
                forecasts,
                valid,
                invalid_reason,
                switches: self.choice.switches(),
                ring_ticks: self.ring.len(),
                ring_capacity: self.ring.capacity(),
                imminent,
                latch_horizon_ms: self.settings.latch_horizon_ms,
                networks_in_memory: names(&self.models.in_memory()).join(","),
                set_aside: names(self.overload.set_aside()).join(","),
                skipped_in_window: self.overload.skipped_in_window(),
                overload_window: self.overload.window_ticks(),
                overload_switches: self.overload.switches,
            },
            inputs: inputs_diagnostics(&guard),
        }
    }

    /// Wait for the last inference and stop the thread.
    pub async fn finish(self) -> TickCounters {
        self.inference.wait_idle().await;
        let counters = self.counters;
        self.inference.finish();
        counters
    }
}

/// The configured streams, for a message (`joints, plan`).
fn configured_streams(slots: &PerStream<StreamSlot>) -> String {
    slots
        .iter()
        .filter(|(_, s)| s.configured)
        .map(|(k, _)| k.as_str())
        .collect::<Vec<_>>()
        .join(", ")
}

/// The live streams, in model form: the tick's end of each.
pub type LiveTaps = PerStream<StreamTap<Sample>>;

/// Drive `tick_loop` from the system clock until shutdown or until the
/// inference thread dies: at each grid tick, take the latest sample of each
/// stream (new ones only, in stamp order) and run the ticks that became
/// final. The caller finishes the loop (`daemon::lifecycle`).
pub async fn run_live(tick_loop: &mut TickLoop, taps: LiveTaps, mut shutdown: Shutdown) {
    let grid = tick_loop.resampler.grid();
    // The last sequence number taken per stream: a sample is new when its
    // `seq` is above it (never by comparing pointers, which an allocator
    // may reuse).
    let mut seen: PerStream<Seq> = PerStream::default();
    loop {
        let now = unix_now_ns();
        let next = grid.stamp_ns(grid.last_tick_at_or_before(now) + 1);
        let wait = Duration::from_nanos(u64::try_from(next - now).unwrap_or(0));
        tokio::select! {
            () = tokio::time::sleep(wait) => {}
            () = shutdown.recv() => break,
        }
        let mut fresh: Vec<Sample> = Vec::with_capacity(StreamKind::ALL.len());
        // When the newest sensor sample entered (a plan does not count).
        let mut sensed_at: Option<Instant> = None;
        for (kind, tap) in taps.iter() {
            let Some(s) = take_new(tap, &mut seen[kind]) else {
                continue;
            };
            if kind.is_sensor() {
                sensed_at = Some(sensed_at.map_or(s.received, |t| t.max(s.received)));
            }
            fresh.push(s.value.clone());
        }
        fresh.sort_by_key(Sample::stamp_ns);
        let now_ns = unix_now_ns();
        for sample in fresh {
            tick_loop.push_sample(sample);
        }
        tick_loop.advance_to(now_ns);
        // Latency is counted from the newest sensor sample, or from the tick
        // itself when no new sample arrived (a stale tick).
        tick_loop
            .run_pending(sensed_at.unwrap_or_else(Instant::now), false)
            .await;
        if tick_loop.inference().is_dead() {
            // Exit (non-zero from `run`) so that systemd restarts the daemon.
            break;
        }
    }
}

/// The tap's latest sample if its sequence number is above `seen` (which
/// then becomes it).
fn take_new<T>(tap: &StreamTap<T>, seen: &mut Seq) -> Option<Arc<Stamped<T>>> {
    let s = tap.latest()?;
    (s.seq > *seen).then(|| {
        *seen = s.seq;
        s
    })
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::streams::input::InputLimits;

    #[test]
    fn a_sample_is_taken_once_by_its_sequence_number() {
        let now = unix_now_ns();
        let (feed, tap) =
            crate::streams::stream::<Vec<f32>>(StreamKind::Joints, InputLimits::shapes(1, 4));
        let mut seen = 0;
        assert!(take_new(&tap, &mut seen).is_none());
        feed.offer_at(now, now, Ok(vec![1.0])).expect("admitted");
        assert_eq!(take_new(&tap, &mut seen).map(|s| s.seq), Some(1));
        assert!(take_new(&tap, &mut seen).is_none(), "taken twice");
        // A rejected sample is not new.
        assert!(feed
            .offer_at(now, now + 60_000_000_000, Ok(vec![2.0]))
            .is_err());
        assert!(take_new(&tap, &mut seen).is_none());
        // Two equal values in a row are two samples.
        feed.offer_at(now, now + 1, Ok(vec![1.0]))
            .expect("admitted");
        assert_eq!(take_new(&tap, &mut seen).map(|s| s.seq), Some(2));
    }

    fn spec(n_ticks: usize) -> crate::window::WindowSpec {
        crate::window::WindowSpec {
            n_ticks,
            max_horizon_ticks: 1,
            rate_hz: 30.0,
            joint_names: vec!["a".into(), "b".into(), "c".into()],
            frame_size: 4,
        }
    }

    /// Ticks at 30 Hz of a 3-joint servo reading every 20 ms, `missed(k, j)`
    /// saying whether joint `j` missed reading `k`.
    fn servo_ticks(readings: i64, missed: impl Fn(i64, usize) -> bool) -> Vec<TickInput> {
        let mut resampler = Resampler::new(&spec(4)).expect("spec");
        let mut out = Vec::new();
        for k in 0..readings {
            let positions_rad = (0..3)
                .map(|j| {
                    if missed(k, j) {
                        f32::NAN
                    } else {
                        0.1 * j as f32
                    }
                })
                .collect();
            resampler.push(
                Sample::Joints {
                    stamp_ns: k * 20_000_000,
                    positions_rad,
                    read_ns: None,
                },
                &mut out,
            );
        }
        out
    }

    /// The reason of each tick's forecast with the P network (joints only)
    /// and `joints_stale_ms` = 100, bridging no gap, as the tick loop
    /// judges them.
    fn reasons(ticks: Vec<TickInput>) -> Vec<Option<String>> {
        judged(ticks, 4, 100, 0).0
    }

    /// The reason of each tick's forecast with the P network (joints only),
    /// a window of `n` ticks, `joints_stale_ms` = `stale_ms` and
    /// `joints_max_held_ticks` = `max_held`, as the tick loop judges them;
    /// and the model choice after the last tick.
    fn judged(
        ticks: Vec<TickInput>,
        n: usize,
        stale_ms: i64,
        max_held: usize,
    ) -> (Vec<Option<String>>, ModelChoice) {
        let stale_ns = stale_ms * 1_000_000;
        let names: Vec<String> = vec!["a".into(), "b".into(), "c".into()];
        let slots = PerStream::from_fn(|kind| StreamSlot {
            kind,
            source: "test".into(),
            configured: kind == StreamKind::Joints,
            stale_ns,
            stats: Arc::default(),
        });
        let mut ring = Ring::new(n);
        let mut choice = ModelChoice::new(vec![Ablation::P], n).bridging(max_held);
        let reasons = ticks
            .into_iter()
            .map(|tick| {
                let joints = joints_at(&tick, stale_ns);
                choice.update_ticks(
                    PerStream::from_fn(|kind| {
                        kind == StreamKind::Joints && joints == JointsAt::Fresh
                    }),
                    joints,
                );
                ring.push(tick);
                let latest = ring.latest().expect("a tick").clone();
                invalid_reason(&ring, &latest, &choice, &slots, &names)
            })
            .collect();
        (reasons, choice)
    }

    /// One read cycle of a 3-joint robot on two buses as the servo source
    /// makes it: joints a and b on the first bus, c on the second, each bus
    /// stamped just before its sync read; `None` for a bus whose read
    /// failed (its motors not read this cycle).
    struct Cycle {
        /// The cycle's start (its first request), ns.
        start_ns: i64,
        /// When the reading reaches the tick (the cycle's end plus the
        /// hand-over), ns.
        delivered_ns: i64,
        /// Per bus, the stamp of its sync read (`None`: lost).
        buses: [Option<i64>; 2],
    }

    /// The ticks the live tick loop makes of `cycles`: at each tick, the
    /// readings delivered by then are pushed (each stamped per bus, or with
    /// the cycle's start for every joint when `per_bus` is false, as before
    /// the per-bus stamps), then the tick is made final.
    fn live_ticks(cycles: &[Cycle], per_bus: bool, n_ticks: i64) -> Vec<TickInput> {
        let mut resampler = Resampler::new(&spec(4)).expect("spec");
        let grid = resampler.grid();
        let mut out = Vec::new();
        let mut next = 0;
        for tick in 1..=n_ticks {
            let now = grid.stamp_ns(tick);
            while next < cycles.len() && cycles[next].delivered_ns <= now {
                let c = &cycles[next];
                next += 1;
                let bus_of = |j: usize| usize::from(j == 2);
                let read: Vec<Option<i64>> = (0..3)
                    .map(|j| c.buses[bus_of(j)].map(|t| if per_bus { t } else { c.start_ns }))
                    .collect();
                let Some(stamp_ns) = read.iter().flatten().copied().max() else {
                    continue;
                };
                resampler.push(
                    Sample::Joints {
                        stamp_ns,
                        positions_rad: read
                            .iter()
                            .map(|r| if r.is_some() { 0.5 } else { f32::NAN })
                            .collect(),
                        read_ns: Some(read.iter().map(|r| r.unwrap_or(stamp_ns)).collect()),
                    },
                    &mut out,
                );
            }
            resampler.advance_to(now, &mut out);
        }
        out
    }

    /// Read cycles from `t0`: the first bus's sync read takes 12 ms (a
    /// retry included), the second's 11 ms, a lost one 20 ms (its timeout),
    /// and a reading reaches the tick 5 ms after its cycle ends; `lost(k)`
    /// says which buses cycle `k` lost.
    fn cycles(n: usize, lost: impl Fn(usize) -> [bool; 2]) -> Vec<Cycle> {
        let mut t = 0;
        (0..n)
            .map(|k| {
                let lost = lost(k);
                let first = t;
                t += if lost[0] { 20_000_000 } else { 12_000_000 };
                let second = t;
                t += if lost[1] { 20_000_000 } else { 11_000_000 };
                Cycle {
                    start_ns: first,
                    delivered_ns: t + 5_000_000,
                    buses: [(!lost[0]).then_some(first), (!lost[1]).then_some(second)],
                }
            })
            .collect()
    }

    #[test]
    fn each_joint_is_as_old_as_its_own_bus_read() {
        // Cycles of 23 ms, nothing lost: at every tick, a and b are as old
        // as the first bus's read, c as the second's (11 ms later).
        let ticks = live_ticks(&cycles(80, |_| [false; 2]), true, 40);
        for t in &ticks[5..] {
            let (a, c) = (t.joint_age_ns(0).expect("a"), t.joint_age_ns(2).expect("c"));
            assert_eq!(a - c, 12_000_000, "tick {}: a {a} ns, c {c} ns", t.tick);
            assert_eq!(t.age_ns.joints, Some(a));
        }
        // Stamped with the cycle's start, c was 12 ms older than its value.
        let before = live_ticks(&cycles(80, |_| [false; 2]), false, 40);
        let age_at_20 = |ticks: &[TickInput]| {
            let t = ticks.iter().find(|t| t.tick == 20).expect("tick 20");
            t.joint_age_ns(2).expect("c")
        };
        assert_eq!(age_at_20(&before) - age_at_20(&ticks), 12_000_000);
    }

    #[test]
    fn a_joint_read_late_in_its_cycle_and_within_the_bound_keeps_the_forecast_valid() {
        // The second bus (c) loses cycles 20, 21 and 22, each a 20 ms
        // timeout: c's value, read at 449 ms (12 ms into cycle 19), is
        // 117.7 ms old at tick 17 (566.7 ms), the last before the next one
        // arrives (584 ms). Under a 120 ms bound its own stamp keeps every
        // forecast valid; stamped with its cycle's start (437 ms) it was
        // 129.7 ms old, and stale.
        let lost = |k: usize| [false, (20..23).contains(&k)];
        let own_ticks = live_ticks(&cycles(100, lost), true, 60);
        let at_17 = own_ticks.iter().find(|t| t.tick == 17).expect("tick 17");
        assert_eq!(at_17.joint_age_ns(2), Some(117_666_667));
        let (own, _) = judged(own_ticks, 4, 120, 0);
        assert!(own[4..].iter().all(Option::is_none), "{own:?}");
        let start_ticks = live_ticks(&cycles(100, lost), false, 60);
        let at = start_ticks
            .iter()
            .position(|t| t.tick == 17)
            .expect("tick 17");
        let (start, _) = judged(start_ticks, 4, 120, 0);
        assert_eq!(
            start[at].as_deref(),
            Some("joints stale (129 ms old): c 129 ms"),
            "{start:?}"
        );
    }

    #[test]
    fn two_lost_cycles_in_a_row_on_a_bus_make_no_gap() {
        // Each bus loses two cycles in a row, each a 20 ms timeout, at
        // every phase against the ticks: at the shipped bound (150 ms) no
        // tick is stale. The worst case is 113 ms (the first bus: 12 + 3
        // cycles + 5 ms); under the former 100 ms bound it was a gap.
        let mut gaps_under_100_ms = 0;
        for phase in 0..23 {
            let lost = |k: usize| {
                [
                    (20 + phase..22 + phase).contains(&k),
                    (50 + phase..52 + phase).contains(&k),
                ]
            };
            let ticks = live_ticks(&cycles(160, lost), true, 100);
            let worst = ticks[5..]
                .iter()
                .filter_map(|t| t.age_ns.joints)
                .max()
                .expect("ages");
            assert!(worst <= 113_000_000, "phase {phase}: {worst} ns");
            let (r, _) = judged(ticks.clone(), 4, 150, 0);
            assert!(r[3..].iter().all(Option::is_none), "phase {phase}: {r:?}");
            let (r, _) = judged(ticks, 4, 100, 0);
            gaps_under_100_ms +=
                usize::from(r.iter().flatten().any(|r| r.starts_with("joints stale")));
        }
        assert!(gaps_under_100_ms > 0, "no phase made a gap under 100 ms");
    }

    #[test]
    fn a_joint_missed_now_and_then_keeps_the_forecast_valid() {
        // Joint b misses every other reading, c three in a row: never
        // older than 100 ms.
        let r = reasons(servo_ticks(60, |k, j| {
            (j == 1 && k % 2 == 1) || (j == 2 && (10..13).contains(&k))
        }));
        assert_eq!(r[2].as_deref(), Some("ring filling (3/4 ticks)"));
        assert!(r[3..].iter().all(Option::is_none), "{r:?}");
    }

    #[test]
    fn a_joint_older_than_its_bound_is_named_and_the_window_refills() {
        // Joint c not read in readings 10..=17 (200 ms to 340 ms): its value
        // of 180 ms is older than 100 ms from tick 9 (300 ms) to tick 10
        // (333 ms); reading 18 (360 ms) brings it back at tick 11.
        let r = reasons(servo_ticks(45, |k, j| j == 2 && (10..18).contains(&k)));
        let at = |tick: usize| r[tick].as_deref().unwrap_or("valid");
        assert_eq!(at(8), "valid");
        assert_eq!(at(9), "joints stale (120 ms old): c 120 ms");
        assert_eq!(at(10), "joints stale (153 ms old): c 153 ms");
        assert_eq!(at(11), "joints back, window refilling (1/4 fresh ticks)");
        assert_eq!(at(13), "joints back, window refilling (3/4 fresh ticks)");
        // Valid once the window's four ticks are all fresh.
        assert_eq!(at(14), "valid");
    }

    #[test]
    fn a_brief_gap_is_bridged_and_a_longer_one_waited_out() {
        // A window of 10 ticks, joints_stale_ms = 100, gaps of at most 3
        // held ticks bridged. Joint c not read in readings 20..=27 (its
        // value of 380 ms stale at ticks 15 and 16), 60..=72 (ticks 39 to
        // 43), 100..=109 (ticks 63 to 65) and 111..=119 (ticks 70, 71).
        let missing = |k: i64| {
            (20..=27).contains(&k)
                || (60..=72).contains(&k)
                || (100..=109).contains(&k)
                || (111..=119).contains(&k)
        };
        let (r, choice) = judged(servo_ticks(140, |k, j| j == 2 && missing(k)), 10, 100, 3);
        let at = |tick: usize| r[tick].as_deref().unwrap_or("valid");
        let stale: Vec<usize> = (0..r.len())
            .filter(|&t| at(t).starts_with("joints stale"))
            .collect();
        assert_eq!(stale, [15, 16, 39, 40, 41, 42, 43, 63, 64, 65, 70, 71]);
        assert_eq!(at(15), "joints stale (120 ms old): c 120 ms");
        // Two ticks held: bridged, valid on the first fresh tick, the
        // stale ticks still in the window.
        assert_eq!(at(14), "valid");
        assert!((17..39).all(|t| at(t) == "valid"), "{r:?}");
        // Five: waited out until they have left the window (tick 43 + 10).
        assert_eq!(
            at(44),
            "joints back, window refilling (1/10 fresh ticks; 5 stale in it, a gap of at most 3 held bridged)"
        );
        assert!((44..53).all(|t| at(t).starts_with("joints back")), "{r:?}");
        assert!((53..63).all(|t| at(t) == "valid"), "{r:?}");
        // Three, bridged; then two more while the three are in the window:
        // five held ticks in it, more than 3, so the forecast waits until
        // no more than 3 are (tick 74: the window 65..=74).
        assert!((66..70).all(|t| at(t) == "valid"), "{r:?}");
        assert!(at(72).starts_with("joints back, window refilling (1/10 fresh ticks; 5 stale"));
        assert!(at(73).starts_with("joints back, window refilling (2/10 fresh ticks; 4 stale"));
        assert!((74..r.len()).all(|t| at(t) == "valid"), "{r:?}");
        let gaps = choice.joint_gaps();
        assert_eq!((gaps.bridged, gaps.refilled), (2, 2));
        assert_eq!(choice.stale_ticks(), 0);
        // Bridging nothing, every gap waits for a whole window.
        let (r, choice) = judged(servo_ticks(140, |k, j| j == 2 && missing(k)), 10, 100, 0);
        assert_eq!(
            r[17].as_deref(),
            Some("joints back, window refilling (1/10 fresh ticks)")
        );
        assert_eq!(r[26], None);
        assert_eq!(choice.joint_gaps().bridged, 0);
    }

    #[test]
    fn a_joint_never_read_and_a_stopped_stream_say_so() {
        let r = reasons(servo_ticks(20, |_, j| j == 0));
        assert!(
            r[3..]
                .iter()
                .all(|x| x.as_deref() == Some("joints not read: a")),
            "{r:?}"
        );
        // Every joint's value older than the bound: the whole stream stopped.
        let mut ticks = servo_ticks(10, |_, _| false);
        let last = ticks.last().cloned().expect("ticks");
        for k in 1..=4 {
            let mut t = last.clone();
            t.tick += k;
            t.stamp_ns += k * 33_333_333;
            t.age_ns.joints = t.age_ns.joints.map(|a| a + k * 33_333_333);
            ticks.push(t);
        }
        let r = reasons(ticks);
        assert_eq!(
            r.last().cloned().flatten().as_deref(),
            Some("joints stale (139 ms old): all 3 joints")
        );
    }

    #[test]
    fn unix_clock_is_after_2020() {
        assert!(unix_now_ns() > 1_577_836_800_000_000_000);
    }
}
