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

use std::collections::VecDeque;
use std::sync::Arc;
use std::time::{Duration, Instant, SystemTime, UNIX_EPOCH};

use crate::forecast::{
    ablation_name, best_configured, percentiles_ms, Freshness, Inference, InferenceJob,
    ModelChoice, ModelSet,
};
use crate::frame::Frame;
use crate::model::Ablation;
use crate::outputs::{
    DiagnosticLevel, DiagnosticsSnapshot, ModelDiagnostics, OutputBus, StreamDiagnostics,
    ERROR_WINDOW_S,
};
use crate::shutdown::Shutdown;
use crate::sources::{StreamKind, StreamStats, StreamTap};
use crate::window::{Plan, Resampler, Ring, Sample, TickInput, WindowError};

/// Now, in ns since the UNIX epoch (the live tick clock, as ROS stamps).
pub fn unix_now_ns() -> i64 {
    SystemTime::now()
        .duration_since(UNIX_EPOCH)
        .map_or(0, |d| i64::try_from(d.as_nanos()).unwrap_or(i64::MAX))
}

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
    /// Joints, camera, plan (in that order).
    pub streams: [StreamSlot; 3],
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
    diag_samples: [u64; 3],
    diag_stamp_ns: Option<i64>,
    /// Per stream, (tick stamp, error total) at each snapshot of the last
    /// [`ERROR_WINDOW_S`] seconds: levels look at errors in that window.
    error_history: [VecDeque<(i64, u64)>; 3],
    /// Model-order joint names, to name the joints a reading lacks.
    joint_names: Vec<String>,
    last_valid: bool,
    last_reason: String,
}

/// Names of the joints a tick has no (finite) angle for.
fn unread_joints(tick: &TickInput, names: &[String]) -> Vec<String> {
    tick.joints_rad.as_ref().map_or_else(Vec::new, |j| {
        j.iter()
            .zip(names)
            .filter(|(v, _)| !v.is_finite())
            .map(|(_, n)| n.clone())
            .collect()
    })
}

/// Whether a tick has every joint angle, finite.
fn joints_complete(tick: &TickInput) -> bool {
    tick.joints_rad
        .as_ref()
        .is_some_and(|j| j.iter().all(|v| v.is_finite()))
}

/// Why a tick's forecast is not valid (`None`: valid). Valid means: the
/// ring holds N ticks, and every stream the active network reads was fresh
/// in each of them. A stream back after a gap therefore keeps the forecast
/// invalid until N fresh ticks have refilled the window, as a lost camera or
/// plan must before the model choice takes it back.
///
/// A joints tick counts as fresh only when it has every joint: a motor
/// that does not answer (NaN from the servo source) makes the forecast not
/// valid, naming the joints, and once it answers again N complete ticks
/// must refill the window. No angle is substituted (the planned one, say):
/// the networks were never trained on a window with a substituted joint,
/// so a forecast from one would be a number nobody measured the worth of.
fn invalid_reason(
    ring: &Ring,
    tick: &TickInput,
    choice: &ModelChoice,
    slots: &[StreamSlot; 3],
    joint_names: &[String],
) -> Option<String> {
    if !ring.is_full() {
        return Some(format!(
            "ring filling ({}/{} ticks)",
            ring.len(),
            ring.capacity()
        ));
    }
    let ages = [
        tick.age_ns.joints_ns,
        tick.age_ns.frame_ns,
        tick.age_ns.plan_ns,
    ];
    let active = choice.active();
    let used = [true, active.uses_vision(), active.uses_plan()];
    let window = ring.capacity();
    let not_ready: Vec<String> = (0..3)
        .filter(|&i| used[i] && !choice.refilled(slots[i].kind))
        .map(|i| {
            let kind = slots[i].kind;
            match ages[i] {
                None => format!("no {kind} sample yet"),
                Some(age) if age > slots[i].stale_ns => {
                    format!("{kind} stale ({} ms old)", age / 1_000_000)
                }
                Some(_) if i == 0 && !joints_complete(tick) => format!(
                    "joints not read: {}",
                    unread_joints(tick, joint_names).join(", ")
                ),
                Some(_) => format!(
                    "{kind} back, window refilling ({}/{window} fresh ticks)",
                    choice.fresh_ticks(kind)
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
        Ok(TickLoop {
            resampler: Resampler::new(&spec)?,
            ring: Ring::new(spec.n_ticks),
            choice: ModelChoice::new(models.available(), spec.n_ticks),
            models,
            inference,
            settings,
            bus,
            watchdog: Watchdog::from_env(),
            pending: Vec::new(),
            counters: TickCounters::default(),
            diag_samples: [0; 3],
            diag_stamp_ns: None,
            error_history: Default::default(),
            joint_names: spec.joint_names.clone(),
            last_valid: false,
            last_reason: String::new(),
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
        let ages = [
            tick.age_ns.joints_ns,
            tick.age_ns.frame_ns,
            tick.age_ns.plan_ns,
        ];
        let slots = &self.settings.streams;
        let complete = joints_complete(&tick);
        let fresh: [bool; 3] = std::array::from_fn(|i| {
            ages[i].is_some_and(|age| age <= slots[i].stale_ns) && (i != 0 || complete)
        });
        self.choice.update(Freshness {
            joints: fresh[0],
            camera: fresh[1],
            plan: fresh[2],
        });
        let (tick_index, stamp_ns) = (tick.tick, tick.stamp_ns);
        self.ring.push(tick);
        let active = self.choice.active();
        let latest = self.ring.latest().cloned();
        let reason = latest
            .as_ref()
            .and_then(|t| invalid_reason(&self.ring, t, &self.choice, slots, &self.joint_names));
        self.last_valid = reason.is_none();
        self.last_reason = reason.clone().unwrap_or_default();
        if dispatch {
            if lockstep {
                self.inference.wait_idle().await;
            }
            // A window with a joint not read is not run (the network would
            // refuse it anyway): the forecast is not valid and says why.
            // While the ring fills, the ticks so far go to the network
            // (vision slices prepared ahead of the first forecast).
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
                Ok(()) => self.counters.dispatched += 1,
                Err(_) => self.overrun(tick_index),
            }
        } else {
            self.overrun(tick_index);
        }
        self.maybe_diagnostics(stamp_ns, latest.as_ref());
    }

    fn overrun(&mut self, tick: i64) {
        self.counters.overruns += 1;
        if self.counters.overruns == 1 || self.counters.overruns.is_power_of_two() {
            tracing::warn!(
                tick,
                overruns = self.counters.overruns,
                "inference overrun: tick skipped"
            );
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

    /// Build a diagnostics snapshot now (also used at the end of a replay).
    pub fn diagnostics(
        &mut self,
        stamp_ns: i64,
        period_ns: i64,
        latest: Option<&TickInput>,
    ) -> DiagnosticsSnapshot {
        let active = self.choice.active();
        let ages = latest.map_or([None; 3], |t| {
            [t.age_ns.joints_ns, t.age_ns.frame_ns, t.age_ns.plan_ns]
        });
        let period_s = (period_ns as f64 / 1e9).max(1e-9);
        let mut streams = Vec::with_capacity(3);
        let mut devices = Vec::new();
        for (i, slot) in self.settings.streams.iter().enumerate() {
            let stats = slot.stats.snapshot();
            let rate_hz =
                (stats.samples - self.diag_samples[i].min(stats.samples)) as f64 / period_s;
            self.diag_samples[i] = stats.samples;
            let history = &mut self.error_history[i];
            history.push_back((stamp_ns, stats.errors));
            let window_ns = ERROR_WINDOW_S as i64 * 1_000_000_000;
            while history.len() > 1 && history[1].0 <= stamp_ns - window_ns {
                history.pop_front();
            }
            // Errors since the newest snapshot at or before the window's
            // start (all of them while the run is younger than the window).
            let recent_errors = match history.front() {
                Some(&(t, n)) if t <= stamp_ns - window_ns => stats.errors.saturating_sub(n),
                _ => stats.errors,
            };
            let unread = if i == 0 {
                latest.map_or_else(Vec::new, |t| unread_joints(t, &self.joint_names))
            } else {
                Vec::new()
            };
            let (level, message) = if !slot.configured {
                (DiagnosticLevel::Ok, "not configured".to_string())
            } else {
                match ages[i] {
                    None => (DiagnosticLevel::Stale, "no sample yet".to_string()),
                    Some(age) if age > slot.stale_ns => (
                        DiagnosticLevel::Stale,
                        format!(
                            "stale: last sample {} ms old (limit {} ms)",
                            age / 1_000_000,
                            slot.stale_ns / 1_000_000
                        ),
                    ),
                    Some(_) if !unread.is_empty() => (
                        DiagnosticLevel::Warn,
                        format!(
                            "{} of {} joints not read: {}",
                            unread.len(),
                            self.joint_names.len(),
                            unread.join(", ")
                        ),
                    ),
                    Some(_) if recent_errors > 0 => (
                        DiagnosticLevel::Warn,
                        format!("{recent_errors} errors in the last {ERROR_WINDOW_S} s"),
                    ),
                    Some(_) => (DiagnosticLevel::Ok, "ok".to_string()),
                }
            };
            let mut details: Vec<(String, String)> = stats
                .error_kinds
                .iter()
                .map(|(k, n)| (format!("errors.{k}"), n.to_string()))
                .collect();
            details.extend(stats.details.iter().cloned());
            if !stats.state.is_empty() {
                details.push(("state".to_string(), stats.state.clone()));
            }
            if i == 0 {
                details.push(("joints_not_read".to_string(), unread.join(",")));
            }
            devices.extend(stats.devices.iter().cloned());
            streams.push(StreamDiagnostics {
                stream: slot.kind.as_str(),
                source: slot.source.clone(),
                level,
                message,
                rate_hz,
                last_sample_age_ms: ages[i].map(|a| a as f64 / 1e6),
                errors: stats.errors,
                recent_errors,
                details,
            });
        }
        let (mut latencies, forecasts, errors, imminent) = {
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
            )
        };
        let percentiles = percentiles_ms(&mut latencies);
        let [_, camera, plan] = &self.settings.streams;
        let expected =
            best_configured(&self.models.available(), camera.configured, plan.configured);
        let (level, message) = if errors > 0 && !self.last_valid {
            (
                DiagnosticLevel::Error,
                format!("{errors} inference errors; {}", self.last_reason),
            )
        } else if !self.last_valid {
            (
                DiagnosticLevel::Warn,
                format!("forecast not valid: {}", self.last_reason),
            )
        } else if Some(active) != expected {
            (
                DiagnosticLevel::Warn,
                format!(
                    "degraded: running {} ({} needs a stream that is lost)",
                    ablation_name(active),
                    expected.map_or("?", ablation_name)
                ),
            )
        } else if active != Ablation::EMP {
            // What the config asked for (camera = "none", plan = "none").
            (
                DiagnosticLevel::Ok,
                format!(
                    "ok: running {} (the configured streams: {})",
                    ablation_name(active),
                    configured_streams(&self.settings.streams)
                ),
            )
        } else {
            (DiagnosticLevel::Ok, "ok".to_string())
        };
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
                valid: self.last_valid,
                invalid_reason: self.last_reason.clone(),
                switches: self.choice.switches(),
                ring_ticks: self.ring.len(),
                ring_capacity: self.ring.capacity(),
                imminent,
                latch_horizon_ms: self.settings.latch_horizon_ms,
                networks_in_memory: self
                    .models
                    .in_memory()
                    .into_iter()
                    .map(ablation_name)
                    .collect::<Vec<_>>()
                    .join(","),
            },
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
fn configured_streams(slots: &[StreamSlot; 3]) -> String {
    slots
        .iter()
        .filter(|s| s.configured)
        .map(|s| s.kind.as_str())
        .collect::<Vec<_>>()
        .join(", ")
}

/// The live streams, in model form.
#[derive(Debug, Clone)]
pub struct LiveTaps {
    pub joints: StreamTap<Vec<f32>>,
    pub camera: StreamTap<Arc<Frame>>,
    pub plan: StreamTap<Arc<Plan>>,
}

/// Drive `tick_loop` from the system clock until shutdown: at each grid
/// tick, take the latest sample of each stream (new ones only, in stamp
/// order) and run the ticks that became final.
/// Returns the counters and whether the inference thread died.
pub async fn run_live(
    mut tick_loop: TickLoop,
    taps: LiveTaps,
    mut shutdown: Shutdown,
) -> (TickCounters, bool) {
    let grid = tick_loop.resampler.grid();
    let mut seen: [Option<i64>; 3] = [None; 3];
    let mut seen_ptr: [usize; 3] = [0; 3];
    loop {
        let now = unix_now_ns();
        let next = grid.stamp_ns(grid.last_tick_at_or_before(now) + 1);
        let wait = Duration::from_nanos(u64::try_from(next - now).unwrap_or(0));
        tokio::select! {
            () = tokio::time::sleep(wait) => {}
            () = shutdown.recv() => break,
        }
        let mut fresh: Vec<(i64, Sample)> = Vec::with_capacity(3);
        let mut sensed_at: Option<Instant> = None;
        if let Some(s) = taps.joints.latest() {
            let ptr = Arc::as_ptr(&s) as usize;
            if seen_ptr[0] != ptr {
                seen_ptr[0] = ptr;
                seen[0] = Some(s.stamp_ns);
                sensed_at = Some(s.received);
                fresh.push((
                    s.stamp_ns,
                    Sample::Joints {
                        stamp_ns: s.stamp_ns,
                        positions_rad: s.value.clone(),
                    },
                ));
            }
        }
        if let Some(s) = taps.camera.latest() {
            let ptr = Arc::as_ptr(&s) as usize;
            if seen_ptr[1] != ptr {
                seen_ptr[1] = ptr;
                seen[1] = Some(s.stamp_ns);
                sensed_at = Some(sensed_at.map_or(s.received, |t| t.max(s.received)));
                fresh.push((
                    s.stamp_ns,
                    Sample::Frame {
                        stamp_ns: s.stamp_ns,
                        frame: Arc::clone(&s.value),
                    },
                ));
            }
        }
        if let Some(s) = taps.plan.latest() {
            let ptr = Arc::as_ptr(&s) as usize;
            if seen_ptr[2] != ptr {
                seen_ptr[2] = ptr;
                seen[2] = Some(s.stamp_ns);
                fresh.push((
                    s.stamp_ns,
                    Sample::Plan {
                        stamp_ns: s.stamp_ns,
                        plan: Arc::clone(&s.value),
                    },
                ));
            }
        }
        fresh.sort_by_key(|(stamp, _)| *stamp);
        let now_ns = unix_now_ns();
        for (_, sample) in fresh {
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
    let dead = tick_loop.inference().is_dead();
    (tick_loop.finish().await, dead)
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn unix_clock_is_after_2020() {
        assert!(unix_now_ns() > 1_577_836_800_000_000_000);
    }
}
