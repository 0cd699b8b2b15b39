//! The safety latch behind `/fall_guard/fall_imminent`: a threshold with
//! hysteresis on the fall probability at one configured horizon.
//!
//! Each tick's probabilities enter through [`SafetyLatch::update`]; the latch
//! turns on when the probability at its horizon reaches `trigger`, and off
//! only once it drops below `release` (< `trigger`), so a probability that
//! hovers around one threshold does not make the signal chatter. A forecast
//! that is not valid leaves the state as it is: the latch never releases on
//! data it cannot trust (a safety node reads validity on `/diagnostics`).

use thiserror::Error;

#[derive(Debug, Error, PartialEq)]
pub enum LatchError {
    #[error(
        "release threshold {release} must be below the trigger threshold {trigger}, both in [0, 1]"
    )]
    Thresholds { trigger: f32, release: f32 },
}

/// Hysteresis on one horizon's fall probability.
#[derive(Debug, Clone, PartialEq)]
pub struct SafetyLatch {
    horizon_index: usize,
    trigger: f32,
    release: f32,
    imminent: bool,
    /// Number of off -> on transitions since start.
    triggers: u64,
    /// Log each switch (the daemon); off for offline analysis.
    log: bool,
}

impl SafetyLatch {
    /// A latch watching `probabilities[horizon_index]`, off at start.
    pub fn new(
        horizon_index: usize,
        trigger: f32,
        release: f32,
    ) -> Result<SafetyLatch, LatchError> {
        let in_unit = |p: f32| (0.0..=1.0).contains(&p);
        if !(in_unit(trigger) && in_unit(release) && release < trigger) {
            return Err(LatchError::Thresholds { trigger, release });
        }
        Ok(SafetyLatch {
            horizon_index,
            trigger,
            release,
            imminent: false,
            triggers: 0,
            log: true,
        })
    }

    /// The same latch without a log line per switch (offline replays of many episodes).
    pub fn silent(mut self) -> SafetyLatch {
        self.log = false;
        self
    }

    /// Feed one tick's forecast; returns the state after it.
    pub fn update(&mut self, probabilities: &[f32], valid: bool) -> bool {
        let Some(&p) = probabilities.get(self.horizon_index) else {
            return self.imminent;
        };
        if !valid || p.is_nan() {
            return self.imminent;
        }
        if !self.imminent && p >= self.trigger {
            self.imminent = true;
            self.triggers += 1;
            if self.log {
                tracing::warn!(
                    probability = p,
                    trigger = self.trigger,
                    "fall imminent: latch on"
                );
            }
        } else if self.imminent && p < self.release {
            self.imminent = false;
            if self.log {
                tracing::info!(
                    probability = p,
                    release = self.release,
                    "fall no longer imminent: latch off"
                );
            }
        }
        self.imminent
    }

    pub fn imminent(&self) -> bool {
        self.imminent
    }

    pub fn horizon_index(&self) -> usize {
        self.horizon_index
    }

    pub fn triggers(&self) -> u64 {
        self.triggers
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    fn run(latch: &mut SafetyLatch, ps: &[f32]) -> Vec<bool> {
        ps.iter().map(|&p| latch.update(&[0.0, p], true)).collect()
    }

    #[test]
    fn triggers_at_threshold_and_releases_only_below_release() {
        let mut latch = SafetyLatch::new(1, 0.7, 0.4).expect("valid");
        let states = run(
            &mut latch,
            &[0.1, 0.69, 0.7, 0.5, 0.41, 0.4, 0.39, 0.6, 0.69, 0.71],
        );
        assert_eq!(
            states,
            [false, false, true, true, true, true, false, false, false, true]
        );
        assert_eq!(latch.triggers(), 2);
    }

    #[test]
    fn hovering_around_the_trigger_does_not_chatter() {
        let mut latch = SafetyLatch::new(1, 0.5, 0.3).expect("valid");
        let states = run(&mut latch, &[0.49, 0.51, 0.49, 0.51, 0.49, 0.51]);
        assert_eq!(states, [false, true, true, true, true, true]);
        assert_eq!(latch.triggers(), 1);
    }

    #[test]
    fn invalid_or_nan_forecasts_hold_the_state() {
        let mut latch = SafetyLatch::new(0, 0.5, 0.3).expect("valid");
        assert!(!latch.update(&[0.9], false));
        assert!(latch.update(&[0.9], true));
        assert!(latch.update(&[0.0], false));
        assert!(latch.update(&[f32::NAN], true));
        assert!(latch.update(&[], true));
        assert!(!latch.update(&[0.0], true));
    }

    #[test]
    fn rejects_release_not_below_trigger() {
        assert!(SafetyLatch::new(0, 0.5, 0.5).is_err());
        assert!(SafetyLatch::new(0, 1.5, 0.5).is_err());
        assert!(SafetyLatch::new(0, 0.5, -0.1).is_err());
    }
}
