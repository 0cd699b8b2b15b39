//! Replay of an MCAP recording through the daemon, with recorded time.
//!
//! The recording is read once ([`Recording::open_for_replay`]; errors name
//! the file and byte offset), its messages become model-form samples with
//! the same conversion training uses ([`recorded_samples`]), and each
//! sample is offered to its stream's input boundary and pushed into the
//! [`TickLoop`] at its log time: paced at `speed` times real time, or as
//! fast as inference allows ([`Pacing::MaxSpeed`], lock-step: no tick
//! skipped). After the samples the tick loop is identical to live.
//!
//! A bad message inside a sound file (bytes that do not decode as its
//! type, a value that does not convert, such as a NaN joint angle) fails
//! only itself: it reaches its stream's boundary as a [`Recorded`] whose
//! sample is the [`Rejection`], is counted there as a live one is
//! (`rejected_<reason>`, `last_rejection` on `/diagnostics`), and the replay
//! goes on, the stream holding its previous sample. A file whose structure
//! is broken (not MCAP, truncated, a corrupt chunk, a topic of the wrong
//! type) is an error at load. Counters of each replayed stream go to the
//! same [`StreamStats`](crate::streams::StreamStats) the diagnostics read
//! for live sources.

pub use crate::config::Pacing;
use std::path::{Path, PathBuf};
use std::sync::Arc;

use thiserror::Error;

use crate::recording::{topics, Recording, RecordingError};
use crate::streams::input::Rejection;
use crate::streams::sample::{Plan, Sample};
use crate::streams::StreamKind;
use crate::window::{recorded_samples, WindowError, WindowSpec};

#[derive(Debug, Error)]
pub enum ReplayError {
    #[error(transparent)]
    Recording(#[from] RecordingError),
    #[error(transparent)]
    Window(#[from] WindowError),
    #[error("{}: the recording has no messages", .0.display())]
    Empty(PathBuf),
}

/// One recorded message on its way to its stream's input boundary: a
/// model-form sample, or why its message is not one (it did not decode or
/// did not convert), which the boundary rejects as it would a live one.
#[derive(Debug, Clone)]
pub struct Recorded {
    pub kind: StreamKind,
    /// Log time, ns.
    pub stamp_ns: i64,
    pub sample: Result<Sample, Rejection>,
}

impl From<Sample> for Recorded {
    fn from(sample: Sample) -> Recorded {
        Recorded {
            kind: sample.kind(),
            stamp_ns: sample.stamp_ns(),
            sample: Ok(sample),
        }
    }
}

/// A recording, read and converted, ready to replay (possibly many times).
#[derive(Debug, Clone)]
pub struct ReplayRecording {
    pub path: PathBuf,
    /// Every message of the input streams, in log-time order.
    pub samples: Vec<Recorded>,
    /// Log time of the last message, ns.
    pub end_ns: i64,
    pub start_ns: i64,
    /// Fall onset from the episode metadata (`None`: no fall, or unlabelled).
    pub fall_onset_ns: Option<i64>,
}

impl ReplayRecording {
    pub fn open(path: &Path, spec: &WindowSpec) -> Result<ReplayRecording, ReplayError> {
        let (rec, undecodable) = Recording::open_for_replay(path)?;
        if rec.joint_states.is_empty() {
            return Err(WindowError::NoSamples {
                path: path.to_path_buf(),
                topic: topics::JOINT_STATES,
            }
            .into());
        }
        // (log time, file order, message)
        let mut keyed: Vec<(i64, u64, Recorded)> = recorded_samples(&rec, spec)
            .into_iter()
            .map(|r| {
                let recorded = Recorded {
                    kind: r.kind,
                    stamp_ns: r.stamp_ns,
                    sample: r.sample.map_err(|e| Rejection::from_sample(&e)),
                };
                (r.stamp_ns, r.file_order, recorded)
            })
            .collect();
        for m in &undecodable {
            let Some(kind) = StreamKind::ALL
                .into_iter()
                .find(|&k| topics::of_stream(k) == m.topic)
            else {
                tracing::warn!(error = %m.error, "undecodable message skipped (not an input stream)");
                continue;
            };
            let rejection = Rejection::Undecodable {
                what: m.error.to_string(),
            };
            let recorded = Recorded {
                kind,
                stamp_ns: m.log_time_ns,
                sample: Err(rejection),
            };
            keyed.push((m.log_time_ns, m.file_order, recorded));
        }
        keyed.sort_by_key(|(stamp, order, _)| (*stamp, *order));
        let samples: Vec<Recorded> = keyed.into_iter().map(|(_, _, r)| r).collect();
        let (Some(start_ns), Some(end_ns)) = (rec.start_ns(), rec.end_ns()) else {
            return Err(ReplayError::Empty(path.to_path_buf()));
        };
        let bad = samples.iter().filter(|r| r.sample.is_err()).count();
        tracing::info!(recording = %path.display(), samples = samples.len(), bad,
            duration_s = (end_ns - start_ns) as f64 / 1e9, "recording loaded for replay");
        Ok(ReplayRecording {
            path: path.to_path_buf(),
            samples,
            end_ns,
            start_ns,
            fall_onset_ns: rec.episode.as_ref().and_then(|e| e.fall_onset_ns),
        })
    }
}

/// A recorded message moved `offset_ns` later in time (plans move every
/// point).
pub fn shifted(recorded: &Recorded, offset_ns: i64) -> Recorded {
    Recorded {
        kind: recorded.kind,
        stamp_ns: recorded.stamp_ns + offset_ns,
        sample: recorded
            .sample
            .as_ref()
            .map(|s| shifted_sample(s, offset_ns))
            .map_err(Clone::clone),
    }
}

fn shifted_sample(sample: &Sample, offset_ns: i64) -> Sample {
    match sample {
        Sample::Joints {
            stamp_ns,
            positions_rad,
            read_ns,
        } => Sample::Joints {
            stamp_ns: stamp_ns + offset_ns,
            positions_rad: positions_rad.clone(),
            read_ns: read_ns
                .as_ref()
                .map(|r| r.iter().map(|t| t + offset_ns).collect()),
        },
        Sample::Frame { stamp_ns, frame } => Sample::Frame {
            stamp_ns: stamp_ns + offset_ns,
            frame: Arc::clone(frame),
        },
        Sample::Plan { stamp_ns, plan } => Sample::Plan {
            stamp_ns: stamp_ns + offset_ns,
            plan: Arc::new(Plan {
                stamp_ns: plan.stamp_ns + offset_ns,
                times_ns: plan.times_ns.iter().map(|t| t + offset_ns).collect(),
                positions_rad: plan.positions_rad.clone(),
                n_joints: plan.n_joints,
            }),
        },
    }
}
