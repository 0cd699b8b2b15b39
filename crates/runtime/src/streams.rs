//! Input streams, each behind one small interface: a source (servo bus,
//! ROS 2 subscription, camera, replay) turns an outside stream into
//! timestamped model-form values and offers each to its stream's
//! [`input::Gate`] (the input boundary, `streams/input.rs`: the one place
//! where stamps and values are checked and sequence numbers given). An
//! admitted sample becomes the stream's latest [`Stamped`] value in a
//! [`StreamFeed`] (a `tokio::sync::watch` channel, never a queue); samples,
//! rejections and source errors are counted in shared [`StreamStats`]. The
//! tick reads the other end, a [`StreamTap`], once per tick, and takes a
//! sample as new by its `seq`.
//!
//! Time: `stamp_ns` is on the clock that drives the ticks: UNIX time in ns
//! when live (ROS `header.stamp` where the message has one), the recording's
//! log time in replay.
//!
//! Value type: every live stream of the model carries a
//! [`crate::streams::sample::Sample`], the one model-form sample of the tick (its
//! variant is the stream's kind: joints in radians in the model's joint
//! order, `robot.rs`; a camera `Frame` already S x S; a `Plan`), so that
//! the tick takes new samples of every stream in one loop
//! ([`PerStream`] of [`StreamTap`]s). `record` keeps one more stream, the
//! camera as compressed (`Arc<msgs::CompressedImage>`).

use std::collections::VecDeque;
use std::fmt;
use std::sync::atomic::{AtomicU64, Ordering};
use std::sync::{Arc, Mutex};
use std::time::Instant;

use tokio::sync::watch;

pub mod input;
pub mod sample;

use input::{Gate, InputLimits, Rejection, Seq, StreamValue};

/// Topic names of a recording (see `docs/contracts.md`).
pub mod topics {
    pub const JOINT_STATES: &str = "/joint_states";
    pub const PLANNED_TRAJECTORY: &str = "/planned_trajectory";
    pub const HEAD_CAMERA: &str = "/head_camera/image_raw/compressed";
    pub const GROUND_TRUTH_FALLEN: &str = "/ground_truth/fallen";

    /// The topic of an input stream.
    pub fn of_stream(kind: super::StreamKind) -> &'static str {
        use super::StreamKind;
        match kind {
            StreamKind::Joints => JOINT_STATES,
            StreamKind::Camera => HEAD_CAMERA,
            StreamKind::Plan => PLANNED_TRAJECTORY,
        }
    }
}

/// Level of one diagnostic status (values as in `diagnostic_msgs/DiagnosticStatus`).
#[derive(Debug, Clone, Copy, PartialEq, Eq, PartialOrd, Ord)]
pub enum DiagnosticLevel {
    Ok,
    Warn,
    Error,
    Stale,
}

impl DiagnosticLevel {
    /// The `level` byte of `diagnostic_msgs/msg/DiagnosticStatus`.
    pub fn as_byte(self) -> u8 {
        match self {
            DiagnosticLevel::Ok => 0,
            DiagnosticLevel::Warn => 1,
            DiagnosticLevel::Error => 2,
            DiagnosticLevel::Stale => 3,
        }
    }

    pub fn as_str(self) -> &'static str {
        match self {
            DiagnosticLevel::Ok => "OK",
            DiagnosticLevel::Warn => "WARN",
            DiagnosticLevel::Error => "ERROR",
            DiagnosticLevel::Stale => "STALE",
        }
    }
}

/// Health of one device behind a stream (a servo bus), reported by its
/// source: published as a status of its own, `<node>: <name>`.
#[derive(Debug, Clone, PartialEq)]
pub struct DeviceDiagnostics {
    /// Status name after the node prefix, e.g. `servo bus lower`.
    pub name: String,
    /// The device, e.g. the serial port path.
    pub hardware_id: String,
    pub level: DiagnosticLevel,
    /// One line for a human that names the fault.
    pub message: String,
    pub values: Vec<(String, String)>,
}

/// Seconds over which error counts are judged (levels, `errors_in_window`).
pub const ERROR_WINDOW_S: u64 = 10;

/// Counters sampled at each diagnostics report, for figures over the last
/// window (`ERROR_WINDOW_S` in the caller's time unit `S`): the reports
/// kept are the newest one at or before the window's start and those
/// after it.
#[derive(Debug, Clone)]
pub struct CounterWindow<S, T> {
    history: VecDeque<(S, T)>,
}

impl<S, T> Default for CounterWindow<S, T> {
    fn default() -> Self {
        CounterWindow {
            history: VecDeque::new(),
        }
    }
}

impl<S, T> CounterWindow<S, T>
where
    S: Copy + PartialOrd + std::ops::Sub<Output = S>,
{
    /// Adds the counters `now` at time `t` (non-decreasing), forgetting the
    /// reports older than the newest one at or before `t - window`.
    pub fn push(&mut self, t: S, window: S, now: T) {
        self.history.push_back((t, now));
        while self.history.len() > 1 && self.history[1].0 <= t - window {
            self.history.pop_front();
        }
    }

    /// The report at the start of the window that ends at `t`, `(its time,
    /// its counters)`: the figures to subtract. `None` while the run is
    /// younger than `window` (count from the start, all zeros).
    pub fn window_start(&self, t: S, window: S) -> Option<&(S, T)> {
        self.history
            .front()
            .filter(|(start, _)| *start <= t - window)
    }

    /// The counters of the latest report.
    pub fn latest(&self) -> Option<&T> {
        self.history.back().map(|(_, c)| c)
    }
}

/// The three input streams of the model.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Hash)]
pub enum StreamKind {
    /// Measured joint angles (servo bus or `/joint_states`).
    Joints,
    /// Head camera frames (V4L2 or `/head_camera/image_raw/compressed`).
    Camera,
    /// The planner's trajectory (`/planned_trajectory`).
    Plan,
}

impl StreamKind {
    /// Every stream, in diagnostics order.
    pub const ALL: [StreamKind; 3] = [StreamKind::Joints, StreamKind::Camera, StreamKind::Plan];

    /// Whether a new sample of this stream is a sensor reading, from which
    /// the sensor-to-publish latency of a forecast is counted. A plan is
    /// not: it says what the robot will do, not what it sensed.
    pub fn is_sensor(self) -> bool {
        match self {
            StreamKind::Joints | StreamKind::Camera => true,
            StreamKind::Plan => false,
        }
    }

    /// Short name used in logs, diagnostics and config keys.
    pub fn as_str(self) -> &'static str {
        match self {
            StreamKind::Joints => "joints",
            StreamKind::Camera => "camera",
            StreamKind::Plan => "plan",
        }
    }
}

/// One value per stream, indexed by [`StreamKind`] (instead of arrays
/// indexed 0/1/2).
#[derive(Debug, Clone, Copy, PartialEq, Eq, Default)]
pub struct PerStream<T> {
    pub joints: T,
    pub camera: T,
    pub plan: T,
}

impl<T> PerStream<T> {
    /// `f(kind)` for every stream.
    pub fn from_fn(mut f: impl FnMut(StreamKind) -> T) -> PerStream<T> {
        PerStream {
            joints: f(StreamKind::Joints),
            camera: f(StreamKind::Camera),
            plan: f(StreamKind::Plan),
        }
    }

    pub fn map<U>(self, mut f: impl FnMut(StreamKind, T) -> U) -> PerStream<U> {
        PerStream {
            joints: f(StreamKind::Joints, self.joints),
            camera: f(StreamKind::Camera, self.camera),
            plan: f(StreamKind::Plan, self.plan),
        }
    }

    /// Every stream with its value, in diagnostics order.
    pub fn iter(&self) -> impl Iterator<Item = (StreamKind, &T)> {
        StreamKind::ALL.into_iter().map(move |k| (k, &self[k]))
    }
}

impl<T> std::ops::Index<StreamKind> for PerStream<T> {
    type Output = T;
    fn index(&self, kind: StreamKind) -> &T {
        match kind {
            StreamKind::Joints => &self.joints,
            StreamKind::Camera => &self.camera,
            StreamKind::Plan => &self.plan,
        }
    }
}

impl<T> std::ops::IndexMut<StreamKind> for PerStream<T> {
    fn index_mut(&mut self, kind: StreamKind) -> &mut T {
        match kind {
            StreamKind::Joints => &mut self.joints,
            StreamKind::Camera => &mut self.camera,
            StreamKind::Plan => &mut self.plan,
        }
    }
}

impl fmt::Display for StreamKind {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        f.write_str(self.as_str())
    }
}

/// One admitted value of a stream with its time.
#[derive(Debug, Clone)]
pub struct Stamped<T> {
    /// Its number on its stream (1, 2, ...), given at the boundary: the
    /// tick takes a sample as new when this is above the last one it took.
    pub seq: Seq,
    /// Time the value applies to, on the tick clock (see module docs).
    pub stamp_ns: i64,
    /// When the daemon received it (for sensor-to-publish latency).
    pub received: Instant,
    pub value: T,
}

/// Counters of one stream, shared between its source and the diagnostics.
#[derive(Debug, Default)]
pub struct StreamStats {
    samples: AtomicU64,
    errors: AtomicU64,
    /// Samples the boundary rejected, per reason (first-seen order), and
    /// the latest rejection.
    rejected: AtomicU64,
    rejections: Mutex<Vec<(&'static str, u64)>>,
    last_rejection: Mutex<String>,
    /// Errors per kind ("timeout", "bad checksum", "decode"...), in first-seen order.
    error_kinds: Mutex<Vec<(String, u64)>>,
    /// Free-form state of the source ("connected", "reopening /dev/ttyACM0").
    state: Mutex<String>,
    /// Errors and key-values kept by the source itself (servo bus counters).
    external_errors: AtomicU64,
    external_details: Mutex<Vec<(String, String)>>,
    /// Statuses of the devices behind the stream (one per servo bus).
    devices: Mutex<Vec<DeviceDiagnostics>>,
}

/// A copy of [`StreamStats`] at one instant.
#[derive(Debug, Clone, Default, PartialEq)]
pub struct StreamStatsSnapshot {
    /// Admitted samples.
    pub samples: u64,
    pub errors: u64,
    /// Rejected samples, per [`Rejection::key`], and the latest one.
    pub rejected: u64,
    pub rejections: Vec<(&'static str, u64)>,
    pub last_rejection: String,
    pub error_kinds: Vec<(String, u64)>,
    pub state: String,
    /// Source-kept counters, as diagnostic key-values.
    pub details: Vec<(String, String)>,
    /// The devices' own statuses (servo buses), published beside the stream's.
    pub devices: Vec<DeviceDiagnostics>,
}

impl StreamStats {
    pub fn record_sample(&self) {
        self.samples.fetch_add(1, Ordering::Relaxed);
    }

    /// Count one error of `kind`. Returns true the first time this kind is
    /// seen, so that the caller logs each kind once instead of every time.
    pub fn record_error(&self, kind: &str) -> bool {
        self.errors.fetch_add(1, Ordering::Relaxed);
        let mut kinds = self.error_kinds.lock().unwrap_or_else(|e| e.into_inner());
        match kinds.iter_mut().find(|(k, _)| k == kind) {
            Some((_, n)) => {
                *n += 1;
                false
            }
            None => {
                kinds.push((kind.to_string(), 1));
                true
            }
        }
    }

    /// Count one rejected sample. Returns true the first time its reason
    /// is seen (the caller logs each reason once).
    pub fn record_rejection(&self, r: &Rejection) -> bool {
        self.rejected.fetch_add(1, Ordering::Relaxed);
        *self
            .last_rejection
            .lock()
            .unwrap_or_else(|e| e.into_inner()) = r.to_string();
        let mut kinds = self.rejections.lock().unwrap_or_else(|e| e.into_inner());
        match kinds.iter_mut().find(|(k, _)| *k == r.key()) {
            Some((_, n)) => {
                *n += 1;
                false
            }
            None => {
                kinds.push((r.key(), 1));
                true
            }
        }
    }

    pub fn set_state(&self, state: impl Into<String>) {
        *self.state.lock().unwrap_or_else(|e| e.into_inner()) = state.into();
    }

    /// Replace the counters a source keeps itself (its error total is added
    /// to this stream's errors).
    pub fn set_external(&self, errors: u64, details: Vec<(String, String)>) {
        self.external_errors.store(errors, Ordering::Relaxed);
        *self
            .external_details
            .lock()
            .unwrap_or_else(|e| e.into_inner()) = details;
    }

    /// Replace the statuses of the devices behind this stream.
    pub fn set_devices(&self, devices: Vec<DeviceDiagnostics>) {
        *self.devices.lock().unwrap_or_else(|e| e.into_inner()) = devices;
    }

    pub fn snapshot(&self) -> StreamStatsSnapshot {
        StreamStatsSnapshot {
            devices: self
                .devices
                .lock()
                .unwrap_or_else(|e| e.into_inner())
                .clone(),
            samples: self.samples.load(Ordering::Relaxed),
            rejected: self.rejected.load(Ordering::Relaxed),
            rejections: self
                .rejections
                .lock()
                .unwrap_or_else(|e| e.into_inner())
                .clone(),
            last_rejection: self
                .last_rejection
                .lock()
                .unwrap_or_else(|e| e.into_inner())
                .clone(),
            errors: self.errors.load(Ordering::Relaxed)
                + self.external_errors.load(Ordering::Relaxed),
            details: self
                .external_details
                .lock()
                .unwrap_or_else(|e| e.into_inner())
                .clone(),
            error_kinds: self
                .error_kinds
                .lock()
                .unwrap_or_else(|e| e.into_inner())
                .clone(),
            state: self.state.lock().unwrap_or_else(|e| e.into_inner()).clone(),
        }
    }
}

/// The source's end of a stream: offer samples through the stream's
/// [`Gate`], count errors.
#[derive(Debug)]
pub struct StreamFeed<T> {
    kind: StreamKind,
    sender: Arc<watch::Sender<Option<Arc<Stamped<T>>>>>,
    gate: Arc<Gate>,
    stats: Arc<StreamStats>,
}

/// The tick's end of a stream: the latest sample, and the stream's counters.
#[derive(Debug)]
pub struct StreamTap<T> {
    kind: StreamKind,
    receiver: watch::Receiver<Option<Arc<Stamped<T>>>>,
    stats: Arc<StreamStats>,
}

impl<T> Clone for StreamFeed<T> {
    fn clone(&self) -> Self {
        StreamFeed {
            kind: self.kind,
            sender: Arc::clone(&self.sender),
            gate: Arc::clone(&self.gate),
            stats: Arc::clone(&self.stats),
        }
    }
}

impl<T> Clone for StreamTap<T> {
    fn clone(&self) -> Self {
        StreamTap {
            kind: self.kind,
            receiver: self.receiver.clone(),
            stats: Arc::clone(&self.stats),
        }
    }
}

/// A new, empty stream of `kind`, whose samples are checked against `limits`.
pub fn stream<T>(kind: StreamKind, limits: InputLimits) -> (StreamFeed<T>, StreamTap<T>) {
    let (sender, receiver) = watch::channel(None);
    let stats = Arc::new(StreamStats::default());
    (
        StreamFeed {
            kind,
            sender: Arc::new(sender),
            gate: Arc::new(Gate::new(kind, limits, Arc::clone(&stats))),
            stats: Arc::clone(&stats),
        },
        StreamTap {
            kind,
            receiver,
            stats,
        },
    )
}

impl<T: StreamValue> StreamFeed<T> {
    pub fn kind(&self) -> StreamKind {
        self.kind
    }

    /// Offer a value stamped `stamp_ns` (or the source's conversion error)
    /// at the boundary, now on the live tick clock: admitted, it becomes the
    /// stream's latest sample (replacing the previous one) and its sequence
    /// number is returned; rejected, it is counted and goes no further.
    pub fn offer(&self, stamp_ns: i64, value: Result<T, Rejection>) -> Result<Seq, Rejection> {
        self.offer_at(crate::clock::unix_now_ns(), stamp_ns, value)
    }

    /// [`offer`](Self::offer) with the tick clock at `now_ns`.
    pub fn offer_at(
        &self,
        now_ns: i64,
        stamp_ns: i64,
        value: Result<T, Rejection>,
    ) -> Result<Seq, Rejection> {
        let received = Instant::now();
        self.gate.pass(now_ns, stamp_ns, value, |seq, value| {
            // `send_replace` never fails, even with no receiver left.
            self.sender.send_replace(Some(Arc::new(Stamped {
                seq,
                stamp_ns,
                received,
                value,
            })));
        })
    }
}

impl<T> StreamFeed<T> {
    /// Count an error of `kind`; logs a warning the first time each kind is seen.
    pub fn error(&self, kind: &str, detail: &dyn fmt::Display) {
        if self.stats.record_error(kind) {
            tracing::warn!(stream = %self.kind, kind, %detail, "stream error (logged once per kind, counted in /diagnostics)");
        } else {
            tracing::debug!(stream = %self.kind, kind, %detail, "stream error");
        }
    }

    pub fn stats(&self) -> &Arc<StreamStats> {
        &self.stats
    }

    /// What this stream's boundary checks samples against.
    pub fn limits(&self) -> &InputLimits {
        self.gate.limits()
    }
}

impl<T> StreamTap<T> {
    pub fn kind(&self) -> StreamKind {
        self.kind
    }

    /// The latest sample, if any arrived yet.
    pub fn latest(&self) -> Option<Arc<Stamped<T>>> {
        self.receiver.borrow().clone()
    }

    pub fn stats(&self) -> &Arc<StreamStats> {
        &self.stats
    }

    /// Wait for a sample newer than the last one seen through this tap
    /// (`None` once the source is gone).
    pub async fn changed(&mut self) -> Option<Arc<Stamped<T>>> {
        self.receiver.changed().await.ok()?;
        self.receiver.borrow_and_update().clone()
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    /// The window starts at the newest report at or before `t - window`;
    /// before one exists (a run younger than the window), there is none.
    #[test]
    fn counter_window_subtracts_the_report_at_its_start() {
        let mut w: CounterWindow<i64, u64> = CounterWindow::default();
        for (t, total) in [(0, 1), (4, 3), (9, 3)] {
            w.push(t, 10, total);
            assert_eq!(w.window_start(t, 10), None, "t {t}");
        }
        w.push(10, 10, 6);
        assert_eq!(w.window_start(10, 10), Some(&(0, 1)));
        w.push(15, 10, 8);
        assert_eq!(w.window_start(15, 10), Some(&(4, 3)));
        w.push(30, 10, 9);
        assert_eq!(w.window_start(30, 10), Some(&(15, 8)));
        assert_eq!(w.latest(), Some(&9));
    }

    #[test]
    fn tap_sees_only_the_latest_admitted_sample_and_counts_all() {
        let now = 1_000_000_000_000;
        let (feed, tap) = stream::<Vec<f32>>(StreamKind::Joints, InputLimits::shapes(1, 4));
        assert!(tap.latest().is_none());
        assert_eq!(feed.offer_at(now, now + 10, Ok(vec![1.0])), Ok(1));
        assert_eq!(feed.offer_at(now, now + 20, Ok(vec![2.0])), Ok(2));
        // Rejected: neither the latest nor numbered.
        assert!(feed
            .offer_at(now, now + 30, Ok(vec![f32::INFINITY]))
            .is_err());
        assert!(feed.offer_at(now, now + 30, Ok(vec![1.0, 2.0])).is_err());
        let latest = tap.latest().expect("a sample");
        assert_eq!(
            (latest.seq, latest.stamp_ns, latest.value.clone()),
            (2, now + 20, vec![2.0])
        );
        let snap = tap.stats().snapshot();
        assert_eq!((snap.samples, snap.rejected), (2, 2));
        assert_eq!(
            snap.rejections,
            vec![("non_finite", 1), ("wrong_joints", 1)]
        );
    }

    #[test]
    fn per_stream_is_indexed_by_kind() {
        let mut p = PerStream::from_fn(|k| k.as_str().len());
        p[StreamKind::Plan] += 10;
        assert_eq!((p.joints, p.camera, p.plan), (6, 6, 14));
        let kinds: Vec<StreamKind> = p.iter().map(|(k, _)| k).collect();
        assert_eq!(kinds, StreamKind::ALL);
    }

    #[test]
    fn errors_are_counted_per_kind_and_reported_new_once() {
        let stats = StreamStats::default();
        assert!(stats.record_error("timeout"));
        assert!(!stats.record_error("timeout"));
        assert!(stats.record_error("bad checksum"));
        let snap = stats.snapshot();
        assert_eq!(snap.errors, 3);
        assert_eq!(
            snap.error_kinds,
            vec![("timeout".to_string(), 2), ("bad checksum".to_string(), 1)]
        );
    }
}
