//! The replay's drive of the tick loop: each recorded sample offered into
//! its stream's feed (the input boundary, with the recorded time as the
//! tick clock) as a live source offers, and taken from the stream's tap
//! into the [`TickLoop`] at recorded time, paced on a [`ReplayClock`] or
//! lock-step as fast as inference allows.

use std::time::Instant;

use crate::clock::ReplayClock;
use crate::daemon::LiveStreams;
use crate::pipeline::tick::TickLoop;
use crate::shutdown::Shutdown;
use crate::sources::replay::{Pacing, Recorded};

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

/// Push `samples` (sorted by stamp) through `tick_loop` with recorded time,
/// then advance to `end_ns`. Each sample is offered into its stream's feed
/// of `streams` (the input boundary, with the recorded time as the tick
/// clock) as a live one is: a rejected one (or a message that was not a
/// sample) is counted there and not pushed; an admitted one is taken from
/// the stream's tap, so that the tick sees what a live source gives it.
/// Paced by `clock`, which may already run (a recording replayed in passes
/// that continue each other in time).
pub async fn replay_samples<I>(
    tick_loop: &mut TickLoop,
    samples: I,
    end_ns: i64,
    pacing: Pacing,
    streams: &LiveStreams,
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
        let offered = streams.feeds[sample.kind].offer_at(stamp_ns, stamp_ns, sample.sample);
        let admitted = offered
            .ok()
            .and_then(|seq| streams.taps[sample.kind].latest().filter(|s| s.seq == seq));
        if let Some(admitted) = admitted {
            summary.samples += 1;
            last_sensed = sensed_at;
            tick_loop.push_sample(admitted.value.clone());
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
