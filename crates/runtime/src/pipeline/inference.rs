//! Per-tick inference on its own thread ([`Inference`]), its latency
//! statistics, and the validity of each forecast.
//!
//! Data enters as one [`InferenceJob`] per dispatched tick (built by
//! `tick.rs`: the window of the last N ticks for the chosen ablation, whether
//! it is valid and why not). The inference thread runs the network through
//! one [`StreamingForecaster`] per ablation (per-frame work done once per
//! frame, equal to the whole-window forward to 1e-5), feeds the
//! [`SafetyLatch`], and sends one [`ForecastOutput`] per job to the
//! [`OutputBus`] (and to stdout when asked). A job is only handed over while
//! the thread is idle: an inference that overruns makes the tick loop skip
//! ticks and count them, never queue.

use std::io::Write;
use std::sync::atomic::{AtomicBool, Ordering};
use std::sync::mpsc;
use std::sync::{Arc, Mutex};
use std::thread::JoinHandle;
use std::time::Instant;

use tokio::sync::Notify;

use crate::config::OutOfRange;
use crate::model::ranges::Excursion;
use crate::model::{Ablation, ModelError, StreamingForecaster};
use crate::outputs::latch::SafetyLatch;
use crate::outputs::{ForecastOutput, OutputBus};
use crate::window::TickInput;

use super::guard::InputGuard;
use super::models::{ablation_name, ForecastError, ModelSet};
use crate::outputs::diagnostics::GuardState;

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
    /// The out-of-range guard after the latest forecast.
    pub guard: GuardState,
}

/// The test hook that slows inference down: `ABLATION:MS:UNTIL_TICK`
/// (`EMP:70:150`: EMP's forecasts of the ticks before tick 150 take 70 ms
/// longer), read from this variable at start. For the overload policy's tests (`tests/daemon_overload.rs`);
/// unset on a robot.
pub const SLOW_INFERENCE_ENV: &str = "FALL_GUARD_TEST_SLOW_INFERENCE";

/// The parsed [`SLOW_INFERENCE_ENV`].
#[derive(Debug, Clone, Copy, PartialEq)]
struct SlowInference {
    ablation: Ablation,
    delay: std::time::Duration,
    until_tick: i64,
}

impl SlowInference {
    fn from_env() -> Option<SlowInference> {
        let v = std::env::var(SLOW_INFERENCE_ENV).ok()?;
        let mut parts = v.split(':');
        let parsed = (|| {
            let ablation = parts.next()?.parse::<Ablation>().ok()?;
            let ms: u64 = parts.next()?.parse().ok()?;
            let until_tick: i64 = parts.next()?.parse().ok()?;
            Some(SlowInference {
                ablation,
                delay: std::time::Duration::from_millis(ms),
                until_tick,
            })
        })();
        match parsed {
            Some(_) => {
                tracing::warn!(%v, "{SLOW_INFERENCE_ENV}: inference slowed down on purpose (a test hook)")
            }
            None => {
                tracing::error!(%v, "{SLOW_INFERENCE_ENV}: not ABLATION:MS:UNTIL_TICK, ignored")
            }
        }
        parsed
    }

    /// Sleeps if this forecast is one to slow down.
    fn apply(slow: Option<SlowInference>, ablation: Ablation, tick: i64) {
        if let Some(s) = slow.filter(|s| s.ablation == ablation && tick < s.until_tick) {
            std::thread::sleep(s.delay);
        }
    }
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
    /// Forecasts are printed on stdout (`[output].print_forecasts`).
    print: bool,
}

impl Inference {
    /// Starts the thread. It owns the networks and the latch, and sends every
    /// result to `bus` (and prints it when `print` is set).
    pub fn spawn(
        models: Arc<ModelSet>,
        latch: SafetyLatch,
        bus: OutputBus,
        print: bool,
        out_of_range: OutOfRange,
    ) -> Result<Inference, ForecastError> {
        let (tx, rx) = mpsc::sync_channel::<InferenceJob>(1);
        let busy = Arc::new(AtomicBool::new(false));
        let idle = Arc::new(Notify::new());
        let guard = InputGuard::new(out_of_range, models.spec().joint_names.clone());
        let stats = Arc::new(Mutex::new(InferenceStats {
            guard: guard.state().clone(),
            ..InferenceStats::default()
        }));
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
                    &models, latch, guard, &bus, print, &rx, &t_busy, &t_idle, &t_stats, &t_dead,
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
            print,
        })
    }

    /// Whether forecasts are printed on stdout.
    pub fn prints(&self) -> bool {
        self.print
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
    mut guard: InputGuard,
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
    let slow = SlowInference::from_env();
    while let Ok(job) = jobs.recv() {
        let mut valid = job.valid;
        let mut invalid_reason = job.invalid_reason;
        let mut probabilities = Vec::new();
        let mut latency_us = None;
        let mut out_of_range = String::new();
        if job.ticks.len() < models.spec().n_ticks {
            forecasters.prepare(job.ablation, &job.ticks);
        } else {
            let started = Instant::now();
            // A refused or failed network: logged once, counted as an error.
            let mut error = None;
            let result = forecasters.forecast(models, job.ablation, &job.ticks);
            SlowInference::apply(slow, job.ablation, job.tick);
            match result {
                Ok((p, excursions)) => {
                    latency_us =
                        Some(u32::try_from(started.elapsed().as_micros()).unwrap_or(u32::MAX));
                    if let Some(sentence) = guard.judge(
                        job.tick,
                        job.stamp_ns,
                        &excursions.excursions,
                        &excursions.bounds,
                    ) {
                        if valid && guard.holds() {
                            valid = false;
                            invalid_reason = sentence.clone();
                        }
                        out_of_range = sentence;
                    }
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
            out_of_range,
            skipped: false,
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
            s.guard.clone_from(guard.state());
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

/// The window's inputs outside their ranges, and where the ranges come from.
struct Judged {
    excursions: Vec<Excursion>,
    bounds: String,
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
            by_ablation: models.forecasters(),
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
    /// ticks, oldest first), with the window's inputs outside their bounds
    /// and where the bounds come from. Only the ticks the forecaster has
    /// not seen are pushed: one per tick normally, the missed ones after an
    /// overrun, the whole window after a model switch or a gap.
    fn forecast(
        &mut self,
        models: &ModelSet,
        ablation: Ablation,
        ticks: &[TickInput],
    ) -> Result<(Vec<f32>, Judged), ForecastFailure> {
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
        let p = forecaster.forecast()?;
        let bounds = forecaster.bounds().map_or_else(
            || {
                "none: the file carries no measured input ranges, nothing is checked (fall-guard-lab ranges adds them)"
                    .to_string()
            },
            |b| format!("measured on {}", b.measured_on),
        );
        Ok((
            p,
            Judged {
                excursions: forecaster.excursions(),
                bounds,
            },
        ))
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
    let guard = if f.out_of_range.is_empty() || !f.valid {
        String::new()
    } else {
        format!(" ({})", f.out_of_range)
    };
    format!(
        "tick {} t={:.3}s {} {}{} p=[{}] imminent={}",
        f.tick,
        f.stamp_ns as f64 / 1e9,
        f.ablation,
        validity,
        guard,
        probabilities.join(" "),
        f.imminent
    )
}

pub fn print_forecast(f: &ForecastOutput) {
    let mut out = std::io::stdout().lock();
    // A closed stdout (a pipe whose reader left) must not stop the daemon.
    let _ = writeln!(out, "{}", format_forecast(f));
}

#[cfg(test)]
mod tests {
    use super::*;

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
            out_of_range: String::new(),
            skipped: false,
            sensed_at: Instant::now(),
        };
        assert_eq!(
            format_forecast(&f),
            "tick 120 t=4.000s MP invalid(camera stale) p=[0.0123 0.5000] imminent=true"
        );
    }
}
