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
//! same [`StreamStats`](crate::sources::StreamStats) the diagnostics read
//! for live sources.

use std::path::{Path, PathBuf};
use std::sync::Arc;
use std::time::{Duration, Instant};

use thiserror::Error;

use crate::recording::{topics, Recording, RecordingError};
use crate::shutdown::Shutdown;
use crate::sources::input::{Gate, Rejection};
use crate::sources::{PerStream, StreamKind};
use crate::tick::TickLoop;
use crate::window::{recorded_samples, Plan, Sample, WindowError, WindowSpec};

#[derive(Debug, Error)]
pub enum ReplayError {
    #[error(transparent)]
    Recording(#[from] RecordingError),
    #[error(transparent)]
    Window(#[from] WindowError),
    #[error("{}: the recording has no messages", .0.display())]
    Empty(PathBuf),
}

/// How fast recorded time runs.
#[derive(Debug, Clone, Copy, PartialEq)]
pub enum Pacing {
    /// `x` times real time (1.0: as recorded).
    Speed(f64),
    /// As fast as inference allows; every tick gets a forecast.
    MaxSpeed,
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
                    sample: r.sample.map_err(|e| Rejection::from_window(&e)),
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
        } => Sample::Joints {
            stamp_ns: stamp_ns + offset_ns,
            positions_rad: positions_rad.clone(),
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

/// What one replay did.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Default)]
pub struct ReplaySummary {
    pub samples: u64,
    pub interrupted: bool,
    /// The inference thread ended (a panic in the network): replay stopped.
    pub inference_failed: bool,
}

/// Sleeps until `due`; false when a shutdown came first.
async fn sleep_until_unless_shutdown(due: Instant, shutdown: &mut Shutdown) -> bool {
    tokio::select! {
        () = tokio::time::sleep_until(due.into()) => true,
        () = shutdown.recv() => false,
    }
}

/// Recorded time on the wall clock of a paced replay: the first stamp
/// placed on it is due at once, every later one `speed` times faster than
/// recorded (a stamp before the first is due at once too). One clock runs
/// on over several [`replay_samples_on`] calls whose samples continue each
/// other in time (the bench's passes, each shifted by the recording's
/// span): the tick after one pass's last is then due one tick period after
/// it, as live, not at once when the next pass starts.
#[derive(Debug, Clone, Copy, Default)]
pub struct ReplayClock {
    /// (wall time, stamp) of the first stamp placed.
    origin: Option<(Instant, i64)>,
}

impl ReplayClock {
    /// A clock that starts at the first stamp placed on it.
    pub fn new() -> ReplayClock {
        ReplayClock::default()
    }

    /// Starts the clock at `stamp_ns` now, unless it runs already.
    pub fn start_at(&mut self, stamp_ns: i64) {
        self.origin.get_or_insert((Instant::now(), stamp_ns));
    }

    /// When `stamp_ns` is due at `speed` times real time (starting the
    /// clock at it if it has not started).
    pub fn due(&mut self, stamp_ns: i64, speed: f64) -> Instant {
        let (wall, t0) = *self.origin.get_or_insert((Instant::now(), stamp_ns));
        wall + Duration::from_secs_f64(((stamp_ns - t0) as f64 / 1e9 / speed).max(0.0))
    }
}

/// Push `samples` (sorted by stamp) through `tick_loop` with recorded time,
/// then advance to `end_ns`. Each sample passes its stream's `gates` (the
/// input boundary, with the recorded time as the tick clock) as a live one
/// does: a rejected one (or a message that was not a sample) is counted
/// there and not pushed.
pub async fn replay_samples<I>(
    tick_loop: &mut TickLoop,
    samples: I,
    end_ns: i64,
    pacing: Pacing,
    gates: &PerStream<Gate>,
    shutdown: &mut Shutdown,
) -> ReplaySummary
where
    I: IntoIterator<Item = Recorded>,
{
    let mut clock = ReplayClock::new();
    replay_samples_on(
        tick_loop, samples, end_ns, pacing, gates, shutdown, &mut clock,
    )
    .await
}

/// [`replay_samples`] paced by `clock`, which may already run (a
/// recording replayed in passes that continue each other in time).
pub async fn replay_samples_on<I>(
    tick_loop: &mut TickLoop,
    samples: I,
    end_ns: i64,
    pacing: Pacing,
    gates: &PerStream<Gate>,
    shutdown: &mut Shutdown,
    clock: &mut ReplayClock,
) -> ReplaySummary
where
    I: IntoIterator<Item = Recorded>,
{
    let lockstep = pacing == Pacing::MaxSpeed;
    let mut summary = ReplaySummary::default();
    // When the newest sample entered (sensor-to-publish latency of a tick).
    let mut last_sensed = Instant::now();
    let mut samples = samples.into_iter().peekable();
    while let Some(sample) = samples.next() {
        if shutdown.is_shutdown() {
            summary.interrupted = true;
            return summary;
        }
        let stamp_ns = sample.stamp_ns;
        if let Pacing::Speed(speed) = pacing {
            clock.start_at(stamp_ns);
            // The tick clock runs on between samples, as it does live: a tick
            // becomes final at its own time, not when the next sample comes
            // (that would hand two ticks over at once and skip one).
            while let Some(tick_ns) = tick_loop.next_tick_stamp().filter(|&t| t < stamp_ns) {
                if !sleep_until_unless_shutdown(clock.due(tick_ns, speed), shutdown).await {
                    summary.interrupted = true;
                    return summary;
                }
                tick_loop.advance_to(tick_ns);
                if tick_loop.pending_ticks() == 0 {
                    break;
                }
                tick_loop.run_pending(last_sensed, false).await;
            }
            if !sleep_until_unless_shutdown(clock.due(stamp_ns, speed), shutdown).await {
                summary.interrupted = true;
                return summary;
            }
        }
        let sensed_at = Instant::now();
        let mut admitted = None;
        let _ = gates[sample.kind].pass(stamp_ns, stamp_ns, sample.sample, |_, s| {
            admitted = Some(s);
        });
        if let Some(sample) = admitted {
            summary.samples += 1;
            last_sensed = sensed_at;
            tick_loop.push_sample(sample);
        }
        // Every sample at this stamp is in: the tick at this stamp is final.
        if samples.peek().is_none_or(|next| next.stamp_ns > stamp_ns) {
            tick_loop.advance_to(stamp_ns);
        }
        if tick_loop.pending_ticks() > 0 {
            tick_loop.run_pending(sensed_at, lockstep).await;
        }
        if tick_loop.inference().is_dead() {
            summary.inference_failed = true;
            return summary;
        }
    }
    tick_loop.advance_to(end_ns);
    tick_loop.run_pending(Instant::now(), lockstep).await;
    summary
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn a_clock_that_runs_on_puts_the_next_pass_one_tick_after_the_last() {
        let tick = 33_333_333;
        let mut clock = ReplayClock::new();
        clock.start_at(1_000);
        let first = clock.due(1_000, 1.0);
        // A stamp before the start is due at once.
        assert_eq!(clock.due(0, 1.0), first);
        // The last tick of a 10 s pass, then the first of the next pass
        // (its samples shifted by the span): one tick apart on the wall
        // clock, as recorded.
        let last = clock.due(1_000 + 10_000_000_000, 1.0);
        clock.start_at(1_000 + 10_000_000_000 + tick);
        let next = clock.due(1_000 + 10_000_000_000 + tick, 1.0);
        assert_eq!(next - last, Duration::from_nanos(tick as u64));
        assert_eq!(last - first, Duration::from_secs(10));
        // Twice real time: half the wall time.
        assert_eq!(
            clock.due(1_000 + 2 * tick, 2.0) - first,
            Duration::from_nanos(tick as u64)
        );
    }
}
