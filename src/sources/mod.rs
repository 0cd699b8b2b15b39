//! Input streams, each behind one small interface: a source (servo bus,
//! ROS 2 subscription, camera, replay) turns an outside stream into
//! timestamped [`Stamped`] values and hands over only its **latest** one through a
//! [`StreamFeed`] (a `tokio::sync::watch` channel, never a queue), counting
//! samples and errors in shared [`StreamStats`]. The tick reads the other end,
//! a [`StreamTap`], once per tick.
//!
//! Time: `stamp_ns` is on the clock that drives the ticks: UNIX time in ns
//! when live (ROS `header.stamp` where the message has one), the recording's
//! log time in replay.
//!
//! Value types per stream (one per [`StreamKind`]):
//! - joints: `Vec<f32>`, radians in the model's joint order (`robot.rs`);
//! - camera: `crate::frame::Frame`, already S x S;
//! - plan: `crate::window::Plan`.

pub mod ros;

use std::fmt;
use std::sync::atomic::{AtomicU64, Ordering};
use std::sync::{Arc, Mutex};
use std::time::Instant;

use tokio::sync::watch;

use crate::outputs::DeviceDiagnostics;

pub mod camera;
pub mod dynamixel;
pub mod replay;

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

    /// Short name used in logs, diagnostics and config keys.
    pub fn as_str(self) -> &'static str {
        match self {
            StreamKind::Joints => "joints",
            StreamKind::Camera => "camera",
            StreamKind::Plan => "plan",
        }
    }
}

impl fmt::Display for StreamKind {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        f.write_str(self.as_str())
    }
}

/// One value of a stream with its time.
#[derive(Debug, Clone)]
pub struct Stamped<T> {
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
    pub samples: u64,
    pub errors: u64,
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

/// The source's end of a stream: publish the latest sample, count errors.
#[derive(Debug)]
pub struct StreamFeed<T> {
    kind: StreamKind,
    sender: Arc<watch::Sender<Option<Arc<Stamped<T>>>>>,
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

/// A new, empty stream of `kind`.
pub fn stream<T>(kind: StreamKind) -> (StreamFeed<T>, StreamTap<T>) {
    let (sender, receiver) = watch::channel(None);
    let stats = Arc::new(StreamStats::default());
    (
        StreamFeed {
            kind,
            sender: Arc::new(sender),
            stats: Arc::clone(&stats),
        },
        StreamTap {
            kind,
            receiver,
            stats,
        },
    )
}

impl<T> StreamFeed<T> {
    pub fn kind(&self) -> StreamKind {
        self.kind
    }

    /// Hand over a new latest value (replaces the previous one).
    pub fn send(&self, stamp_ns: i64, value: T) {
        self.send_sample(Stamped {
            stamp_ns,
            received: Instant::now(),
            value,
        });
    }

    /// Hand over a sample built by the caller (replay sets `received` itself).
    pub fn send_sample(&self, sample: Stamped<T>) {
        self.stats.record_sample();
        // `send_replace` never fails, even with no receiver left.
        self.sender.send_replace(Some(Arc::new(sample)));
    }

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

    #[test]
    fn tap_sees_only_the_latest_sample_and_counts_all() {
        let (feed, tap) = stream::<Vec<f32>>(StreamKind::Joints);
        assert!(tap.latest().is_none());
        feed.send(10, vec![1.0]);
        feed.send(20, vec![2.0]);
        let latest = tap.latest().expect("a sample");
        assert_eq!((latest.stamp_ns, latest.value.clone()), (20, vec![2.0]));
        assert_eq!(tap.stats().snapshot().samples, 2);
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
