//! What the daemon produces, and the seam between the service and whoever
//! publishes it (ROS 2 in `outputs/ros.rs`, stdout, the recorder, benches).
//!
//! Per tick the service makes one [`ForecastOutput`]; at 1 Hz one
//! [`DiagnosticsSnapshot`]. Both go out on an [`OutputBus`] (bounded
//! `tokio::sync::broadcast` channels: a publisher that falls behind loses the
//! oldest values and is told how many, nothing queues without bound). A
//! publisher calls [`OutputBus::subscribe`], turns each value into its
//! messages, and after publishing a forecast calls
//! [`OutputSubscription::published`] so that sensor-to-publish latency is
//! measured at the real publish point.
//!
//! Mapping to ROS 2 (see `docs/ros.md`):
//! - `/fall_guard/forecast` (`Float32MultiArray`): `probabilities` when
//!   `valid`, NaN for every horizon otherwise; one dim labelled
//!   `horizon_ms` with `horizons_ms.len()` entries; every tick.
//! - `/fall_guard/fall_imminent` (`Bool`): `imminent` (already latched with
//!   hysteresis by [`latch::SafetyLatch`]).
//! - `/diagnostics` (`DiagnosticArray`): [`DiagnosticsSnapshot::statuses`],
//!   one [`StatusEntry`] per input stream, one per device a source reports
//!   (each servo bus), and one for the model. This is the one diagnostics
//!   model: `outputs/ros.rs` copies these entries into the message as they are.

pub mod annotate;
pub mod diagnostics;
pub mod latch;
pub mod lead;
pub mod recorder;
pub mod ros;

use std::sync::{Arc, Mutex};

pub use crate::streams::{CounterWindow, DeviceDiagnostics, DiagnosticLevel, ERROR_WINDOW_S};
use std::time::{Duration, Instant};

use tokio::sync::broadcast;

/// One tick's forecast, published every tick (valid or not), so that a
/// subscriber can tell silence from "safe".
#[derive(Debug, Clone, PartialEq)]
pub struct ForecastOutput {
    /// Tick index on the model's grid (tick 0 = first tick of the run).
    pub tick: i64,
    /// Time of the tick on the tick clock (UNIX ns live, log time in replay).
    pub stamp_ns: i64,
    /// Fall probability per horizon, non-decreasing, same order as `horizons_ms`.
    /// Empty when no forecast could be computed this tick (ring not full).
    pub probabilities: Vec<f32>,
    /// The horizons, in ms ahead of `stamp_ns`.
    pub horizons_ms: Vec<u32>,
    /// False until the ring is full, whenever a stream the network reads is
    /// stale, and until such a stream has been fresh for a whole window again.
    /// Published as NaN when false (the probabilities stay here for the
    /// stdout line of a replay).
    pub valid: bool,
    /// The safety latch state after this tick.
    pub imminent: bool,
    /// Which network produced it: "EMP", "MP", "EP" or "P".
    pub ablation: &'static str,
    /// Why the forecast is not valid (empty when valid).
    pub invalid_reason: String,
    /// The window's inputs outside the range the network was trained on
    /// (empty: none), whether the forecast is valid or not
    /// (`[model].out_of_range`).
    pub out_of_range: String,
    /// Not forecast: the inference of an earlier tick was still running
    /// (the overload policy, `pipeline/overload.rs`). Published as NaN;
    /// `imminent` is the latch's state as it was, and does not change the
    /// published `fall_imminent`.
    pub skipped: bool,
    /// When the newest sensor sample used by this tick reached the daemon.
    pub sensed_at: Instant,
}

/// Health of one input stream.
#[derive(Debug, Clone, PartialEq)]
pub struct StreamDiagnostics {
    /// "joints", "camera" or "plan".
    pub stream: &'static str,
    /// Where it comes from: "dynamixel /dev/ttyACM0", "ros /joint_states", "replay", ...
    pub source: String,
    pub level: DiagnosticLevel,
    /// One line for a human ("ok", "stale: no sample for 412 ms", "not configured").
    pub message: String,
    /// Samples per second over the last diagnostics period.
    pub rate_hz: f64,
    /// Age of the latest sample at the snapshot's tick, ms (None: never received).
    pub last_sample_age_ms: Option<f64>,
    /// Total errors since start.
    pub errors: u64,
    /// Errors in the last [`ERROR_WINDOW_S`] seconds of tick time: the
    /// level looks at these, so it returns to OK once a fault is gone.
    pub recent_errors: u64,
    /// Source-specific counters and state, e.g. ("timeout", "3").
    pub details: Vec<(String, String)>,
}

/// Health of the inference.
#[derive(Debug, Clone, PartialEq)]
pub struct ModelDiagnostics {
    pub level: DiagnosticLevel,
    pub message: String,
    /// Active network: "EMP", "MP", "EP" or "P".
    pub active_ablation: &'static str,
    /// File the active network was loaded from.
    pub model_file: String,
    /// Inference latency over the last diagnostics period (None: no inference yet).
    pub inference_p50_ms: Option<f64>,
    pub inference_p99_ms: Option<f64>,
    /// Ticks skipped because the previous inference was still running (total).
    pub overruns: u64,
    /// Ticks run and forecasts computed since start.
    pub ticks: u64,
    pub forecasts: u64,
    /// Whether the latest forecast was valid, and why not.
    pub valid: bool,
    pub invalid_reason: String,
    /// Model switches (degradation and recovery) since start.
    pub switches: u64,
    /// Ticks in the ring / ticks needed for a window.
    pub ring_ticks: usize,
    pub ring_capacity: usize,
    /// Safety latch state and the horizon it watches.
    pub imminent: bool,
    pub latch_horizon_ms: u32,
    /// The networks in memory now ("EMP,MP"): with `[model].fallbacks =
    /// "when_needed"` a fallback appears after its first use.
    pub networks_in_memory: String,
    /// The overload policy: networks set aside ("EMP"), ticks skipped in
    /// its window and the window, set-asides and retries since start.
    pub set_aside: String,
    pub skipped_in_window: usize,
    pub overload_window: usize,
    pub overload_switches: u64,
}

/// Everything `/diagnostics` says, once per second.
#[derive(Debug, Clone, PartialEq)]
pub struct DiagnosticsSnapshot {
    /// Tick clock time of the snapshot.
    pub stamp_ns: i64,
    /// `hardware_id` of every status (the robot's name from the config).
    pub hardware_id: String,
    pub streams: Vec<StreamDiagnostics>,
    /// Devices the sources report (servo buses), after the streams.
    pub devices: Vec<DeviceDiagnostics>,
    pub model: ModelDiagnostics,
    /// The out-of-range guard: `fall_guard: inputs`.
    pub inputs: InputsDiagnostics,
}

/// Whether the forecast window lies inside what the network was trained on.
#[derive(Debug, Clone, PartialEq)]
pub struct InputsDiagnostics {
    pub level: DiagnosticLevel,
    pub message: String,
    /// `out_of_range` (the inputs, comma-separated), `since_s`,
    /// `windows_out_of_range`, `windows`, `policy`, `bounds`.
    pub values: Vec<(String, String)>,
}

/// One `diagnostic_msgs/DiagnosticStatus`, ready to be copied into a message.
#[derive(Debug, Clone, PartialEq)]
pub struct StatusEntry {
    pub level: DiagnosticLevel,
    pub name: String,
    pub message: String,
    pub hardware_id: String,
    pub values: Vec<(String, String)>,
}

fn ms(value: Option<f64>) -> String {
    value.map_or_else(|| "none".to_string(), |v| format!("{v:.3}"))
}

impl DiagnosticsSnapshot {
    /// The statuses of one `/diagnostics` message, names prefixed with the
    /// node name (`fall_guard: joints`): one per stream (keys `source`,
    /// `rate_hz`, `age_ms`, `errors`, `errors_in_window`, `error_window_s`,
    /// then the source's own), one per device (`fall_guard: servo bus
    /// lower`, `hardware_id` the port), then `fall_guard: model` and
    /// `fall_guard: inputs`.
    pub fn statuses(&self, prefix: &str) -> Vec<StatusEntry> {
        let mut out = Vec::with_capacity(self.streams.len() + self.devices.len() + 2);
        for s in &self.streams {
            let mut values = vec![
                ("source".to_string(), s.source.clone()),
                ("rate_hz".to_string(), format!("{:.1}", s.rate_hz)),
                (
                    "age_ms".to_string(),
                    s.last_sample_age_ms
                        .map_or_else(|| "never".to_string(), |a| format!("{a:.1}")),
                ),
                ("errors".to_string(), s.errors.to_string()),
                ("errors_in_window".to_string(), s.recent_errors.to_string()),
                ("error_window_s".to_string(), ERROR_WINDOW_S.to_string()),
            ];
            values.extend(s.details.iter().cloned());
            out.push(StatusEntry {
                level: s.level,
                name: format!("{prefix}: {}", s.stream),
                message: format!("{} ({})", s.message, s.source),
                hardware_id: self.hardware_id.clone(),
                values,
            });
        }
        for d in &self.devices {
            out.push(StatusEntry {
                level: d.level,
                name: format!("{prefix}: {}", d.name),
                message: d.message.clone(),
                hardware_id: d.hardware_id.clone(),
                values: d.values.clone(),
            });
        }
        let m = &self.model;
        out.push(StatusEntry {
            level: m.level,
            name: format!("{prefix}: model"),
            message: m.message.clone(),
            hardware_id: self.hardware_id.clone(),
            values: vec![
                ("inference_p50_ms".to_string(), ms(m.inference_p50_ms)),
                ("inference_p99_ms".to_string(), ms(m.inference_p99_ms)),
                ("overruns".to_string(), m.overruns.to_string()),
                ("active_model".to_string(), m.active_ablation.to_string()),
                ("valid".to_string(), m.valid.to_string()),
                ("invalid_reason".to_string(), m.invalid_reason.clone()),
                ("model_file".to_string(), m.model_file.clone()),
                ("ticks".to_string(), m.ticks.to_string()),
                ("forecasts".to_string(), m.forecasts.to_string()),
                ("model_switches".to_string(), m.switches.to_string()),
                (
                    "ring".to_string(),
                    format!("{}/{}", m.ring_ticks, m.ring_capacity),
                ),
                ("fall_imminent".to_string(), m.imminent.to_string()),
                (
                    "latch_horizon_ms".to_string(),
                    m.latch_horizon_ms.to_string(),
                ),
                (
                    "networks_in_memory".to_string(),
                    m.networks_in_memory.clone(),
                ),
                ("set_aside".to_string(), m.set_aside.clone()),
                (
                    "skipped_in_window".to_string(),
                    format!("{}/{}", m.skipped_in_window, m.overload_window),
                ),
                (
                    "overload_switches".to_string(),
                    m.overload_switches.to_string(),
                ),
            ],
        });
        out.push(StatusEntry {
            level: self.inputs.level,
            name: format!("{prefix}: inputs"),
            message: self.inputs.message.clone(),
            hardware_id: self.hardware_id.clone(),
            values: self.inputs.values.clone(),
        });
        out
    }
}

/// Sensor-to-publish latencies, recorded by publishers (shared, bounded).
#[derive(Debug, Default)]
pub struct PublishLatency {
    samples_us: Mutex<Vec<u32>>,
}

/// Keep at most this many latencies between two reads (about 9 min at 30 Hz).
const MAX_LATENCY_SAMPLES: usize = 16_384;

impl PublishLatency {
    pub fn record(&self, latency: Duration) {
        let mut samples = self.samples_us.lock().unwrap_or_else(|e| e.into_inner());
        if samples.len() < MAX_LATENCY_SAMPLES {
            samples.push(u32::try_from(latency.as_micros()).unwrap_or(u32::MAX));
        }
    }

    /// All latencies recorded since the last call, in µs, and forget them.
    pub fn take_us(&self) -> Vec<u32> {
        std::mem::take(&mut *self.samples_us.lock().unwrap_or_else(|e| e.into_inner()))
    }
}

/// Fan-out of forecasts and diagnostics to every publisher.
#[derive(Debug, Clone)]
pub struct OutputBus {
    forecasts: broadcast::Sender<Arc<ForecastOutput>>,
    diagnostics: broadcast::Sender<Arc<DiagnosticsSnapshot>>,
    latency: Arc<PublishLatency>,
}

/// One publisher's end of the [`OutputBus`].
#[derive(Debug)]
pub struct OutputSubscription {
    pub forecasts: broadcast::Receiver<Arc<ForecastOutput>>,
    pub diagnostics: broadcast::Receiver<Arc<DiagnosticsSnapshot>>,
    latency: Arc<PublishLatency>,
}

/// Forecasts a publisher may fall behind before it loses the oldest (~2 s at 30 Hz).
const FORECAST_CAPACITY: usize = 64;
const DIAGNOSTICS_CAPACITY: usize = 4;

impl Default for OutputBus {
    fn default() -> Self {
        Self::new()
    }
}

impl OutputBus {
    pub fn new() -> OutputBus {
        OutputBus {
            forecasts: broadcast::channel(FORECAST_CAPACITY).0,
            diagnostics: broadcast::channel(DIAGNOSTICS_CAPACITY).0,
            latency: Arc::new(PublishLatency::default()),
        }
    }

    /// A new publisher; it sees values sent from now on.
    pub fn subscribe(&self) -> OutputSubscription {
        OutputSubscription {
            forecasts: self.forecasts.subscribe(),
            diagnostics: self.diagnostics.subscribe(),
            latency: Arc::clone(&self.latency),
        }
    }

    pub fn send_forecast(&self, forecast: ForecastOutput) {
        // Err only means "no publisher subscribed": nothing to do.
        let _ = self.forecasts.send(Arc::new(forecast));
    }

    pub fn send_diagnostics(&self, snapshot: DiagnosticsSnapshot) {
        let _ = self.diagnostics.send(Arc::new(snapshot));
    }

    /// The latencies publishers recorded.
    pub fn latency(&self) -> &Arc<PublishLatency> {
        &self.latency
    }
}

impl OutputSubscription {
    /// Call right after a forecast went out: records its sensor-to-publish latency.
    pub fn published(&self, forecast: &ForecastOutput) {
        self.latency.record(forecast.sensed_at.elapsed());
    }
}

/// Publishes `fall_imminent` on its first value and on every change
/// (`last`: the value subscribers were last sent). `last` moves only when
/// the publish succeeded, so a change that failed (a full send window) is
/// sent again on the next tick instead of being lost: a safety node must
/// not be left holding the old state.
pub fn publish_imminent_change<E>(
    last: &mut Option<bool>,
    now: bool,
    publish: impl FnOnce(bool) -> Result<(), E>,
) -> Result<(), E> {
    if *last == Some(now) {
        return Ok(());
    }
    publish(now)?;
    *last = Some(now);
    Ok(())
}

/// What goes on `/fall_guard/forecast` for one tick: the probabilities of a
/// valid forecast, or NaN for every horizon when it is not valid (the ring
/// is filling, a stream the network needs is stale, absent, or back but not
/// yet fresh for a whole window). A subscriber reading only this topic can
/// thus never mistake a forecast on held data for one it may trust
/// (`p >= threshold` is false for NaN, `isnan` says "unknown"). The forecast
/// is published every tick either way, so that a subscriber can tell
/// silence from "safe"; `/diagnostics` (model status, `invalid_reason`)
/// says why it is not valid.
pub fn published_probabilities(f: &ForecastOutput) -> Vec<f32> {
    if f.valid && f.probabilities.len() == f.horizons_ms.len() {
        f.probabilities.clone()
    } else {
        vec![f32::NAN; f.horizons_ms.len()]
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    fn forecast(tick: i64) -> ForecastOutput {
        ForecastOutput {
            tick,
            stamp_ns: tick * 33_333_333,
            probabilities: vec![0.1, 0.2, 0.3, 0.4],
            horizons_ms: vec![500, 1000, 1500, 2000],
            valid: true,
            imminent: false,
            ablation: "EMP",
            invalid_reason: String::new(),
            out_of_range: String::new(),
            skipped: false,
            sensed_at: Instant::now(),
        }
    }

    #[tokio::test]
    async fn every_subscriber_gets_every_forecast_in_order() {
        let bus = OutputBus::new();
        let mut a = bus.subscribe();
        let mut b = bus.subscribe();
        for t in 0..3 {
            bus.send_forecast(forecast(t));
        }
        for t in 0..3 {
            assert_eq!(a.forecasts.recv().await.expect("a").tick, t);
            assert_eq!(b.forecasts.recv().await.expect("b").tick, t);
        }
        a.published(&forecast(3));
        assert_eq!(bus.latency().take_us().len(), 1);
        assert!(bus.latency().take_us().is_empty());
    }

    #[tokio::test]
    async fn a_slow_subscriber_loses_the_oldest_not_the_newest() {
        let bus = OutputBus::new();
        let mut slow = bus.subscribe();
        let n = FORECAST_CAPACITY as i64 + 10;
        for t in 0..n {
            bus.send_forecast(forecast(t));
        }
        assert!(matches!(
            slow.forecasts.recv().await,
            Err(broadcast::error::RecvError::Lagged(10))
        ));
        assert_eq!(slow.forecasts.recv().await.expect("next").tick, 10);
    }

    #[test]
    fn statuses_name_every_stream_and_the_model() {
        let snap = DiagnosticsSnapshot {
            stamp_ns: 0,
            hardware_id: "poppy".into(),
            streams: vec![StreamDiagnostics {
                stream: "joints",
                source: "replay".into(),
                level: DiagnosticLevel::Stale,
                message: "stale".into(),
                rate_hz: 0.0,
                last_sample_age_ms: None,
                errors: 2,
                recent_errors: 1,
                details: vec![("timeout".into(), "2".into())],
            }],
            devices: vec![DeviceDiagnostics {
                name: "servo bus lower".into(),
                hardware_id: "/dev/ttyACM0".into(),
                level: DiagnosticLevel::Warn,
                message: "motor 36 (head_z) not answering".into(),
                values: vec![("missing_ids".into(), "[36]".into())],
            }],
            model: ModelDiagnostics {
                level: DiagnosticLevel::Warn,
                message: "not valid".into(),
                active_ablation: "P",
                model_file: "models/p.bpk".into(),
                inference_p50_ms: Some(1.5),
                inference_p99_ms: None,
                overruns: 1,
                ticks: 10,
                forecasts: 9,
                valid: false,
                invalid_reason: "joints stale".into(),
                switches: 1,
                ring_ticks: 10,
                ring_capacity: 60,
                imminent: false,
                latch_horizon_ms: 1000,
                networks_in_memory: "EMP,MP,EP,P".to_string(),
                set_aside: String::new(),
                skipped_in_window: 0,
                overload_window: 30,
                overload_switches: 0,
            },
            inputs: InputsDiagnostics {
                level: DiagnosticLevel::Warn,
                message: "inputs outside the training range: bust_x".into(),
                values: vec![("out_of_range".into(), "bust_x".into())],
            },
        };
        let statuses = snap.statuses("fall_guard");
        assert_eq!(statuses.len(), 4);
        assert_eq!(statuses[0].name, "fall_guard: joints");
        assert_eq!(statuses[0].message, "stale (replay)");
        assert_eq!(statuses[0].level.as_byte(), 3);
        let has = |i: usize, k: &str, v: &str| {
            statuses[i].values.contains(&(k.to_string(), v.to_string()))
        };
        assert!(has(0, "age_ms", "never"));
        assert!(has(0, "errors", "2"));
        assert!(has(0, "errors_in_window", "1"));
        assert!(has(0, "timeout", "2"));
        assert_eq!(statuses[1].name, "fall_guard: servo bus lower");
        assert_eq!(statuses[1].hardware_id, "/dev/ttyACM0");
        assert_eq!(statuses[1].level, DiagnosticLevel::Warn);
        assert!(has(1, "missing_ids", "[36]"));
        assert_eq!(statuses[2].name, "fall_guard: model");
        assert_eq!(statuses[2].hardware_id, "poppy");
        assert!(has(2, "active_model", "P"));
        assert!(has(2, "ring", "10/60"));
        assert!(has(2, "invalid_reason", "joints stale"));
        assert_eq!(statuses[3].name, "fall_guard: inputs");
        assert_eq!(statuses[3].level, DiagnosticLevel::Warn);
        assert!(has(3, "out_of_range", "bust_x"));
    }
}
