//! The safety signal against a labelled fall: how far ahead of the onset
//! `fall_imminent` went on and stayed on, from a replay's ticks. `replay`
//! reports it at the end of a recording that carries a fall onset.

use tokio::sync::broadcast::error::{RecvError, TryRecvError};
use tokio::task::JoinHandle;

use super::OutputBus;
use crate::shutdown::Shutdown;

/// The (stamp, `fall_imminent`) of every forecast `bus` carries that was
/// not skipped, until `shutdown` or the bus closes; `None` when the
/// watcher fell behind and lost some (then no lead is reported).
pub fn watch(bus: &OutputBus, mut shutdown: Shutdown) -> JoinHandle<Option<Vec<(i64, bool)>>> {
    let mut sub = bus.subscribe();
    tokio::spawn(async move {
        let mut ticks = Vec::new();
        let mut lost = false;
        loop {
            tokio::select! {
                f = sub.forecasts.recv() => match f {
                    Ok(f) if !f.skipped => ticks.push((f.stamp_ns, f.imminent)),
                    Ok(_) => {}
                    Err(RecvError::Lagged(_)) => lost = true,
                    Err(RecvError::Closed) => break,
                },
                () = shutdown.recv() => break,
            }
        }
        loop {
            match sub.forecasts.try_recv() {
                Ok(f) if !f.skipped => ticks.push((f.stamp_ns, f.imminent)),
                Ok(_) => {}
                Err(TryRecvError::Lagged(_)) => lost = true,
                Err(_) => break,
            }
        }
        (!lost).then_some(ticks)
    })
}

/// What the latch did before a labelled fall.
#[derive(Debug, Clone, Copy, PartialEq)]
pub enum FallWarning {
    /// Asserted `lead_ns` before the onset, after having been released,
    /// and on until the onset.
    Warned { asserted_ns: i64, lead_ns: i64 },
    /// Off at the last tick before the onset (or no tick before it).
    NotWarned,
    /// On from the first tick to the onset, never released: the window
    /// never filled with a forecast below release, so it says nothing.
    HeldThroughout,
}

/// The warning of `ticks` (stamp, `fall_imminent` after the tick, in tick
/// order; skipped ticks left out) on a fall at `onset_ns`.
pub fn fall_warning(ticks: &[(i64, bool)], onset_ns: i64) -> FallWarning {
    let before = &ticks[..ticks.partition_point(|(t, _)| *t < onset_ns)];
    match before.last() {
        Some((_, true)) => {}
        _ => return FallWarning::NotWarned,
    }
    match before.iter().rposition(|(_, on)| !on) {
        None => FallWarning::HeldThroughout,
        Some(off) => {
            let asserted_ns = before[off + 1].0;
            FallWarning::Warned {
                asserted_ns,
                lead_ns: onset_ns - asserted_ns,
            }
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    fn ticks(states: &[bool]) -> Vec<(i64, bool)> {
        states
            .iter()
            .enumerate()
            .map(|(i, &on)| (i as i64 * 100, on))
            .collect()
    }

    #[test]
    fn the_lead_runs_from_the_last_assertion_to_the_onset() {
        // On while filling, released, a false start, then on from tick 6.
        let t = ticks(&[
            true, true, false, true, false, false, true, true, true, false,
        ]);
        assert_eq!(
            fall_warning(&t, 850),
            FallWarning::Warned {
                asserted_ns: 600,
                lead_ns: 250
            }
        );
        // The onset at the assertion's own tick: no lead.
        assert_eq!(fall_warning(&t, 600), FallWarning::NotWarned);
        // After the release at tick 9 the onset finds it off.
        assert_eq!(fall_warning(&t, 1000), FallWarning::NotWarned);
    }

    #[test]
    fn never_released_or_no_tick_before_says_so() {
        assert_eq!(
            fall_warning(&ticks(&[true, true, true]), 250),
            FallWarning::HeldThroughout
        );
        assert_eq!(fall_warning(&ticks(&[true]), 0), FallWarning::NotWarned);
        assert_eq!(fall_warning(&[], 500), FallWarning::NotWarned);
    }
}
