//! The safety latch behind `/fall_guard/fall_imminent`: a threshold with
//! hysteresis on the fall probability at one configured horizon.
//!
//! Each tick's probabilities enter through [`SafetyLatch::update`]; the latch
//! turns on when the probability at its horizon reaches `trigger`, and off
//! only once it has stayed below `release` (< `trigger`) for the release
//! hold ([`SafetyLatch::with_release_hold`], `[model].release_hold_ms`;
//! one tick without it), so a probability that hovers around one threshold,
//! or a network whose output swings, does not make the signal chatter. The
//! hold only delays a release, never an assertion: a latch that is off turns
//! on at the first tick at or above `trigger`.
//!
//! Each network may have its own pair, chosen for it on validation
//! ([`LatchThresholds`], [`SafetyLatch::with_pairs`]): the latch uses the pair of the network
//! that made the forecast ([`SafetyLatch::select`]), and keeps its state
//! across a model switch.
//!
//! A forecast that is not valid (or has no finite probability at the
//! latch's horizon) **asserts** the latch: `false` is a claim that a
//! trusted forecast said "below release", and a blind predictor cannot make
//! it. After the gap the latch is released by the hysteresis rule alone:
//! only a valid forecast below `release` turns it off. See `docs/ros.md`
//! ("Safety signal") for why this is the fail-safe choice.

use thiserror::Error;

use crate::model::Ablation;

/// A pair that is not a latch's.
#[derive(Debug, Error, PartialEq)]
pub enum LatchError {
    /// `which` (`trigger` or `release`) is not a probability.
    #[error("{which}: expected a probability in [0, 1], got {value}")]
    OutOfRange { which: &'static str, value: f32 },
    /// No hysteresis.
    #[error("release {release} must be below trigger {trigger} (hysteresis)")]
    NotBelow { trigger: f32, release: f32 },
}

/// The pair of a latch: on at or above `trigger`, off below `release`. Made
/// by [`Thresholds::new`] only, the one check of a pair (both in [0, 1],
/// `release` below `trigger`): the config's pairs (`Config::latch_thresholds`)
/// and those of `fall-guard-lab warnings` go through it, and the latch takes
/// the checked value.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct Thresholds {
    trigger: f32,
    release: f32,
}

impl Thresholds {
    /// `trigger` and `release`, checked.
    pub fn new(trigger: f32, release: f32) -> Result<Thresholds, LatchError> {
        for (which, value) in [("trigger", trigger), ("release", release)] {
            if !(0.0..=1.0).contains(&value) {
                return Err(LatchError::OutOfRange { which, value });
            }
        }
        if release >= trigger {
            return Err(LatchError::NotBelow { trigger, release });
        }
        Ok(Thresholds { trigger, release })
    }

    /// On at or above this.
    pub fn trigger(self) -> f32 {
        self.trigger
    }

    /// Off below this.
    pub fn release(self) -> f32 {
        self.release
    }
}

/// A latch's pairs (`[model]`'s, checked by `Config::latch_thresholds`): the
/// default and each network's own.
#[derive(Debug, Clone, PartialEq)]
pub struct LatchThresholds {
    /// `[model].trigger`, `[model].release`: for a network without its own.
    pub default: Thresholds,
    /// `[model.thresholds]`: each network's own.
    pub per_network: Vec<(Ablation, Thresholds)>,
}

impl LatchThresholds {
    /// The pair the latch uses while `network` makes the forecasts: its
    /// own, else the default.
    pub fn of(&self, network: Ablation) -> Thresholds {
        self.per_network
            .iter()
            .find(|(a, _)| *a == network)
            .map_or(self.default, |&(_, pair)| pair)
    }
}

/// Hysteresis on one horizon's fall probability.
#[derive(Debug, Clone, PartialEq)]
pub struct SafetyLatch {
    horizon_index: usize,
    /// The pair in use.
    thresholds: Thresholds,
    imminent: bool,
    /// Number of off -> on transitions on a probability since start (an
    /// assertion for lack of a valid forecast is not counted).
    triggers: u64,
    /// The latest update had no valid forecast.
    blind: bool,
    /// Log each switch (the daemon); off for offline analysis.
    log: bool,
    /// The default pair and each network's own.
    pairs: LatchThresholds,
    /// Valid ticks in a row below `release` that release the latch (>= 1).
    release_hold_ticks: usize,
    /// Valid ticks in a row below `release` so far while on.
    below: usize,
}

/// A release hold of `ms` as ticks at `rate_hz` (rounded up: never shorter).
pub fn release_hold_ticks(ms: u32, rate_hz: f64) -> usize {
    (f64::from(ms) * rate_hz / 1000.0 - 1e-9).ceil().max(0.0) as usize
}

impl SafetyLatch {
    /// A latch watching `probabilities[horizon_index]`, off at start.
    pub fn new(horizon_index: usize, thresholds: Thresholds) -> SafetyLatch {
        SafetyLatch {
            horizon_index,
            thresholds,
            imminent: false,
            triggers: 0,
            blind: false,
            log: true,
            pairs: LatchThresholds {
                default: thresholds,
                per_network: Vec::new(),
            },
            release_hold_ticks: 1,
            below: 0,
        }
    }

    /// A latch watching `probabilities[horizon_index]` with these pairs,
    /// the default in use until [`SafetyLatch::select`]; off at start.
    pub fn with_pairs(horizon_index: usize, pairs: LatchThresholds) -> SafetyLatch {
        let default = pairs.default;
        SafetyLatch {
            pairs,
            ..SafetyLatch::new(horizon_index, default)
        }
    }

    /// The same latch released only after `ticks` valid ticks in a row
    /// below `release` (0 or 1: at the first one).
    pub fn with_release_hold(mut self, ticks: usize) -> SafetyLatch {
        self.release_hold_ticks = ticks.max(1);
        self
    }

    /// Use the pair of `network` (its own, else the default) from the next
    /// update on; the latch's state is kept.
    pub fn select(&mut self, network: Ablation) {
        self.thresholds = self.pairs.of(network);
    }

    /// The pair in use.
    pub fn thresholds(&self) -> Thresholds {
        self.thresholds
    }

    /// The same latch without a log line per switch (offline replays of many episodes).
    pub fn silent(mut self) -> SafetyLatch {
        self.log = false;
        self
    }

    /// Feed one tick's forecast; returns the state after it. Not `valid`,
    /// or no finite probability at the horizon: on (asserted) until a valid
    /// forecast falls below `release`.
    pub fn update(&mut self, probabilities: &[f32], valid: bool) -> bool {
        let p = probabilities
            .get(self.horizon_index)
            .copied()
            .filter(|p| valid && p.is_finite());
        let Some(p) = p else {
            if !self.blind && self.log {
                tracing::warn!(
                    was_imminent = self.imminent,
                    "forecast not valid: fall_imminent asserted until a valid forecast is below release"
                );
            }
            self.blind = true;
            self.imminent = true;
            self.below = 0;
            return true;
        };
        self.blind = false;
        if self.imminent && p < self.thresholds.release {
            self.below += 1;
        } else {
            self.below = 0;
        }
        if !self.imminent && p >= self.thresholds.trigger {
            self.imminent = true;
            self.triggers += 1;
            if self.log {
                tracing::warn!(
                    probability = p,
                    trigger = self.thresholds.trigger,
                    "fall imminent: latch on"
                );
            }
        } else if self.imminent && self.below >= self.release_hold_ticks {
            self.imminent = false;
            self.below = 0;
            if self.log {
                tracing::info!(
                    probability = p,
                    release = self.thresholds.release,
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

    fn pair(trigger: f32, release: f32) -> Thresholds {
        Thresholds::new(trigger, release).expect("valid")
    }

    fn run(latch: &mut SafetyLatch, ps: &[f32]) -> Vec<bool> {
        ps.iter().map(|&p| latch.update(&[0.0, p], true)).collect()
    }

    #[test]
    fn triggers_at_threshold_and_releases_only_below_release() {
        let mut latch = SafetyLatch::new(1, pair(0.7, 0.4));
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

    /// A swinging probability with a hold of 3 ticks: released only after
    /// three valid ticks in a row below release (a blind tick starts the
    /// count again); the assertion is never delayed.
    #[test]
    fn the_release_hold_delays_a_release_never_an_assertion() {
        let mut latch = SafetyLatch::new(1, pair(0.7, 0.4)).with_release_hold(3);
        let states = run(
            &mut latch,
            &[0.1, 0.75, 0.2, 0.3, 0.5, 0.2, 0.1, 0.3, 0.2, 0.8],
        );
        assert_eq!(
            states,
            [false, true, true, true, true, true, true, false, false, true]
        );
        assert_eq!(latch.triggers(), 2);
        assert!(latch.update(&[0.0, 0.1], true));
        assert!(latch.update(&[0.0, 0.1], true));
        assert!(latch.update(&[0.0, 0.1], false), "blind: asserted");
        assert!(latch.update(&[0.0, 0.1], true));
        assert!(latch.update(&[0.0, 0.1], true));
        assert!(
            !latch.update(&[0.0, 0.1], true),
            "three valid below in a row"
        );
        // 0 and 1 both release at the first tick below.
        let mut latch = SafetyLatch::new(1, pair(0.7, 0.4)).with_release_hold(0);
        assert_eq!(run(&mut latch, &[0.8, 0.3]), [true, false]);
    }

    #[test]
    fn hovering_around_the_trigger_does_not_chatter() {
        let mut latch = SafetyLatch::new(1, pair(0.5, 0.3));
        let states = run(&mut latch, &[0.49, 0.51, 0.49, 0.51, 0.49, 0.51]);
        assert_eq!(states, [false, true, true, true, true, true]);
        assert_eq!(latch.triggers(), 1);
    }

    #[test]
    fn invalid_or_nan_forecasts_assert_until_a_valid_one_is_below_release() {
        let mut latch = SafetyLatch::new(0, pair(0.5, 0.3));
        // Blind from the start (the ring filling): asserted.
        assert!(latch.update(&[0.0], false));
        assert!(latch.update(&[], true));
        // Valid again: between release and trigger holds, below release frees.
        assert!(latch.update(&[0.4], true));
        assert!(!latch.update(&[0.1], true));
        // A NaN probability or an invalid forecast asserts it again, even
        // when the untrusted number itself is low.
        assert!(latch.update(&[f32::NAN], true));
        assert!(!latch.update(&[0.2], true));
        assert!(latch.update(&[0.0], false));
        assert!(!latch.update(&[0.0], true));
        // Assertions for lack of data are not counted as triggers.
        assert_eq!(latch.triggers(), 0);
        assert!(latch.update(&[0.9], true));
        assert_eq!(latch.triggers(), 1);
    }

    #[test]
    fn each_network_uses_its_own_pair_and_the_state_survives_a_switch() {
        let mut latch = SafetyLatch::with_pairs(
            0,
            LatchThresholds {
                default: pair(0.5, 0.3),
                per_network: vec![(Ablation::EMP, pair(0.7, 0.4))],
            },
        );
        latch.select(Ablation::EMP);
        assert_eq!(latch.thresholds(), pair(0.7, 0.4));
        // 0.6 is below EMP's trigger.
        assert!(!latch.update(&[0.6], true));
        // MP has no pair of its own: the default; 0.6 triggers it.
        latch.select(Ablation::MP);
        assert_eq!(latch.thresholds(), pair(0.5, 0.3));
        assert!(latch.update(&[0.6], true));
        // Back to EMP while on: released only below EMP's release.
        latch.select(Ablation::EMP);
        assert!(latch.update(&[0.45], true));
        assert!(!latch.update(&[0.35], true));
        assert_eq!(latch.triggers(), 1);
    }

    #[test]
    fn a_pair_is_checked_where_it_is_made() {
        assert_eq!(
            Thresholds::new(0.5, 0.5),
            Err(LatchError::NotBelow {
                trigger: 0.5,
                release: 0.5
            })
        );
        assert_eq!(
            Thresholds::new(0.3, 0.5),
            Err(LatchError::NotBelow {
                trigger: 0.3,
                release: 0.5
            })
        );
        assert_eq!(
            Thresholds::new(1.5, 0.5),
            Err(LatchError::OutOfRange {
                which: "trigger",
                value: 1.5
            })
        );
        assert!(matches!(
            Thresholds::new(0.5, -0.1),
            Err(LatchError::OutOfRange {
                which: "release",
                ..
            })
        ));
        assert!(Thresholds::new(f32::NAN, 0.1).is_err());
        let t = pair(0.7, 0.4);
        assert_eq!((t.trigger(), t.release()), (0.7, 0.4));
    }
}
