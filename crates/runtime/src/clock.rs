//! The one clock: UNIX time in ns as ROS stamps it ([`unix_now_ns`]), the
//! tick grid every stream is resampled onto ([`TickGrid`]), and recorded
//! time laid on the wall clock for a paced replay ([`ReplayClock`]).

use std::time::{Duration, Instant, SystemTime, UNIX_EPOCH};

/// Now, in ns since the UNIX epoch: the daemon's one clock (the live tick,
/// the input boundary, the stamps of servo reads, camera frames and ROS 2
/// receipts), as ROS stamps.
pub fn unix_now_ns() -> i64 {
    SystemTime::now()
        .duration_since(UNIX_EPOCH)
        .map_or(0, |d| i64::try_from(d.as_nanos()).unwrap_or(i64::MAX))
}

/// A tick rate that is not a positive, finite whole number of mHz.
#[derive(Debug, Clone, Copy, PartialEq, thiserror::Error)]
#[error(
    "tick rate must be a positive, finite number of Hz with at most 3 decimals (got {rate_hz})"
)]
pub struct BadRate {
    pub rate_hz: f64,
}

/// The tick grid: tick `k` at `ceil(k * 1e12 / rate_mHz)` ns, so that every
/// stream of a recording and every live stream land on the same ticks.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub struct TickGrid {
    rate_mhz: i64,
}

impl TickGrid {
    /// A grid at `rate_hz` (a whole number of mHz, e.g. 30 or 29.97).
    pub fn new(rate_hz: f64) -> Result<TickGrid, BadRate> {
        let mhz = (rate_hz * 1000.0).round();
        if !rate_hz.is_finite()
            || rate_hz <= 0.0
            || !(1.0..=1e9).contains(&mhz)
            || ((mhz / 1000.0) - rate_hz).abs() > 1e-9 * rate_hz.max(1.0)
        {
            return Err(BadRate { rate_hz });
        }
        Ok(TickGrid {
            rate_mhz: mhz as i64,
        })
    }

    pub fn rate_hz(&self) -> f64 {
        self.rate_mhz as f64 / 1000.0
    }

    /// Stamp of tick `tick`, ns.
    pub fn stamp_ns(&self, tick: i64) -> i64 {
        let num = i128::from(tick) * 1_000_000_000_000;
        let den = i128::from(self.rate_mhz);
        (-((-num).div_euclid(den))) as i64
    }

    /// The first tick whose stamp is at or after `stamp_ns`.
    pub fn first_tick_at_or_after(&self, stamp_ns: i64) -> i64 {
        let num = (i128::from(stamp_ns) - 1) * i128::from(self.rate_mhz);
        (num.div_euclid(1_000_000_000_000) + 1) as i64
    }

    /// The last tick whose stamp is at or before `stamp_ns`.
    pub fn last_tick_at_or_before(&self, stamp_ns: i64) -> i64 {
        self.first_tick_at_or_after(stamp_ns + 1) - 1
    }
}

/// Recorded time on the wall clock of a paced replay: the first stamp
/// placed on it is due at once, every later one `speed` times faster than
/// recorded (a stamp before the first is due at once too). One clock runs
/// on over several `daemon::replay::replay_samples_on` calls whose samples continue each
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
