//! `fall-guard replay --out FILE.mcap`: the recording replayed, with the
//! daemon's outputs merged in, for people to look at (Foxglove, with the
//! layout in `docs/foxglove/fall-guard.json`).
//!
//! The output holds every record of the input unchanged, plus what the
//! daemon would have published on ROS 2 at each tick, stamped with the tick's
//! recorded time: `/fall_guard/forecast` (NaN while not valid, exactly as
//! published), `/fall_guard/fall_imminent` (on change, as published) and
//! `/diagnostics` (every diagnostics period). The messages are built by the
//! same functions as the ROS 2 publisher's, so the file shows what a
//! subscriber would have seen.

use std::path::{Path, PathBuf};

use tokio::sync::broadcast::error::RecvError;
use tokio::task::JoinHandle;

use super::ros::{diagnostic_array, forecast_message, OutputTopics};
use super::{DiagnosticsSnapshot, ForecastOutput, OutputBus};
use crate::msgs::{Bool, DiagnosticArray, Float32MultiArray};
use crate::outputs::{publish_imminent_change, published_probabilities};
use crate::recording::{copy_with, RecordingError, RecordingWriter};
use crate::shutdown::Shutdown;

/// One output message, in publish order.
enum Output {
    Forecast(Float32MultiArray),
    FallImminent(bool),
    Diagnostics(DiagnosticArray),
}

/// What the collector took off the bus.
pub struct Collected {
    /// (log time ns, message), in the order published.
    messages: Vec<(i64, Output)>,
    /// Forecasts or snapshots the collector fell behind on and lost.
    pub lost: u64,
}

impl Collected {
    /// Forecasts collected (one per tick).
    pub fn forecasts(&self) -> usize {
        self.messages
            .iter()
            .filter(|(_, m)| matches!(m, Output::Forecast(_)))
            .count()
    }
}

/// Topics in the output file (the daemon's default names, no namespace).
pub struct AnnotateTopics {
    forecast: String,
    fall_imminent: String,
    diagnostics: String,
}

impl Default for AnnotateTopics {
    fn default() -> Self {
        let t = OutputTopics::default();
        let absolute = |s: &str| {
            if s.starts_with('/') {
                s.to_owned()
            } else {
                format!("/{s}")
            }
        };
        AnnotateTopics {
            forecast: absolute(&t.forecast),
            fall_imminent: absolute(&t.fall_imminent),
            diagnostics: absolute(&t.diagnostics),
        }
    }
}

/// Subscribes to `bus` now and collects every forecast and diagnostics
/// snapshot until `shutdown` fires (then drains what is queued).
/// `status_prefix` names the diagnostic statuses as the ROS 2 publisher does.
pub fn collect(
    bus: &OutputBus,
    mut shutdown: Shutdown,
    status_prefix: String,
) -> JoinHandle<Collected> {
    let mut sub = bus.subscribe();
    tokio::spawn(async move {
        let mut out = Collected {
            messages: Vec::new(),
            lost: 0,
        };
        let mut imminent: Option<bool> = None;
        let mut take_forecast = |out: &mut Collected, f: &ForecastOutput| {
            let msg = forecast_message(&published_probabilities(f));
            out.messages.push((f.stamp_ns, Output::Forecast(msg)));
            if f.skipped {
                return;
            }
            let _ = publish_imminent_change(&mut imminent, f.imminent, |v| {
                out.messages.push((f.stamp_ns, Output::FallImminent(v)));
                Ok::<(), std::convert::Infallible>(())
            });
        };
        let take_diagnostics = |out: &mut Collected, d: &DiagnosticsSnapshot| {
            let msg = diagnostic_array(&status_prefix, d);
            out.messages.push((d.stamp_ns, Output::Diagnostics(msg)));
        };
        loop {
            tokio::select! {
                f = sub.forecasts.recv() => match f {
                    Ok(f) => take_forecast(&mut out, &f),
                    Err(RecvError::Lagged(n)) => out.lost += n,
                    Err(RecvError::Closed) => break,
                },
                d = sub.diagnostics.recv() => match d {
                    Ok(d) => take_diagnostics(&mut out, &d),
                    Err(RecvError::Lagged(n)) => out.lost += n,
                    Err(RecvError::Closed) => break,
                },
                () = shutdown.recv() => break,
            }
        }
        loop {
            match sub.forecasts.try_recv() {
                Ok(f) => take_forecast(&mut out, &f),
                Err(tokio::sync::broadcast::error::TryRecvError::Lagged(n)) => out.lost += n,
                Err(_) => break,
            }
        }
        while let Ok(d) = sub.diagnostics.try_recv() {
            take_diagnostics(&mut out, &d);
        }
        out
    })
}

/// Errors writing the annotated recording.
#[derive(Debug, thiserror::Error)]
pub enum AnnotateError {
    #[error("{path}: the replay lost {lost} outputs before they could be written (the writer fell behind); nothing was written")]
    Lost { path: PathBuf, lost: u64 },
    #[error(transparent)]
    Recording(#[from] RecordingError),
}

/// Writes `input` with the collected outputs merged in to `out`
/// (`out.partial` first, renamed when complete). Refuses to write a file
/// that would silently miss outputs.
pub fn write(input: &Path, out: &Path, collected: Collected) -> Result<(), AnnotateError> {
    if collected.lost > 0 {
        return Err(AnnotateError::Lost {
            path: out.to_path_buf(),
            lost: collected.lost,
        });
    }
    let topics = AnnotateTopics::default();
    let mut messages = collected.messages;
    // Stable: messages of one tick keep their publish order.
    messages.sort_by_key(|(t, _)| *t);
    let mut pending = messages.into_iter().peekable();
    copy_with(input, out, |w: &mut RecordingWriter, until| {
        while let Some((t, _)) = pending.peek() {
            if until.is_some_and(|u| u64::try_from(*t).is_ok_and(|t| t > u)) {
                break;
            }
            let Some((t, msg)) = pending.next() else {
                break;
            };
            match msg {
                Output::Forecast(m) => w.write(&topics.forecast, t, &m)?,
                Output::FallImminent(b) => w.write(&topics.fall_imminent, t, &Bool { data: b })?,
                Output::Diagnostics(m) => w.write(&topics.diagnostics, t, &m)?,
            }
        }
        Ok(())
    })?;
    Ok(())
}

/// The forecasts of an annotated recording as read back (for tests and
/// tools): log time and the published probabilities.
pub fn read_forecasts(path: &Path) -> Result<Vec<(i64, Vec<f32>)>, RecordingError> {
    let topic = AnnotateTopics::default().forecast;
    crate::recording::read_topic::<Float32MultiArray>(path, &topic)
        .map(|v| v.into_iter().map(|(t, m)| (t, m.data)).collect())
}
