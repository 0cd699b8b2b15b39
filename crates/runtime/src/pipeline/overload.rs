//! The overload policy: what the daemon does when inference runs late.
//!
//! A tick's budget is its period: the inference of one tick must be done
//! before the next is final. When it is not, the tick loop neither queues
//! the tick nor drops it silently: the newest window is forecast as soon as
//! the inference thread is free, and each tick skipped meanwhile is
//! published as NaN with its reason and counted (`tick.rs`). This module
//! decides when a budget missed on a share of ticks is *persistent*, and
//! then sets the running network aside so that the model choice falls back
//! to a lighter one (EMP -> MP or EP -> P, as for a lost stream), says so,
//! and tries the heavier network again once the budget has held for a
//! while, waiting twice as long after each failed try.
//!
//! Judged on ticks, not on clock time: the same decisions in a replay at
//! any speed as live, for the same sequence of skipped ticks.
//!
//! A skipped tick is charged to the network whose steady work made it late.
//! One skipped while another network's forecast is still running (the one
//! just set aside finishing its last tick), or while a network makes its
//! first forecast after a switch (its whole window pushed at once, a cost
//! of the switch, not of the network), is excused: published and counted
//! like any other, but neither a miss nor a tick within budget here.
//! Without that, on a core where EMP runs late, EMP's last forecast and
//! MP's first one are charged to MP, which is then set aside in turn and
//! the daemon falls through to P although MP keeps its budget.

use std::collections::VecDeque;

use crate::model::Ablation;

use super::models::ablation_name;

/// The policy's parameters, in ticks.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct OverloadSettings {
    /// Ticks judged together: the last second at 30 Hz.
    pub window_ticks: usize,
    /// Skipped ticks in that window that make a miss persistent.
    pub max_skipped: usize,
    /// Ticks within budget before a set-aside network is tried again.
    pub retry_ticks: usize,
    /// The longest wait before a retry, after failed ones.
    pub max_retry_ticks: usize,
}

impl OverloadSettings {
    /// At `rate_hz`: a window of 1 s, persistent at 20% of it skipped, a
    /// retry after 10 s within budget, at most 5 min.
    pub fn at_rate(rate_hz: f64) -> OverloadSettings {
        let ticks = |s: f64| ((s * rate_hz).round() as usize).max(1);
        let window_ticks = ticks(1.0).max(5);
        OverloadSettings {
            window_ticks,
            max_skipped: (window_ticks / 5).max(2),
            retry_ticks: ticks(10.0),
            max_retry_ticks: ticks(300.0),
        }
    }
}

/// A tick as the policy counts it.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum Budget {
    /// Forecast in time.
    Kept,
    /// Skipped: the running network's own forecast was still running.
    Missed,
    /// Skipped, but charged to no network: another network's forecast, or
    /// this one's first after a switch, was running (module docs).
    Excused,
}

/// A decision of the policy.
#[derive(Debug, Clone, PartialEq)]
pub enum OverloadChange {
    /// `network` set aside: it missed its budget on `skipped` of the last
    /// `window` ticks.
    SetAside {
        network: Ablation,
        skipped: usize,
        window: usize,
    },
    /// `network` tried again after `calm` ticks within budget.
    Retry { network: Ablation, calm: usize },
}

impl std::fmt::Display for OverloadChange {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        match self {
            OverloadChange::SetAside {
                network,
                skipped,
                window,
            } => write!(
                f,
                "{} set aside: inference missed its budget (one tick) on {skipped} of the last {window} ticks",
                ablation_name(*network)
            ),
            OverloadChange::Retry { network, calm } => write!(
                f,
                "{} tried again after {calm} ticks within budget",
                ablation_name(*network)
            ),
        }
    }
}

/// Follows the ticks' budgets and sets networks aside.
#[derive(Debug, Clone)]
pub struct Overload {
    settings: OverloadSettings,
    /// The last `window_ticks` ticks: skipped or not.
    recent: VecDeque<bool>,
    /// Networks set aside, in the order they were.
    set_aside: Vec<Ablation>,
    /// Ticks within budget in a row.
    calm: usize,
    /// Current wait before a retry.
    retry_ticks: usize,
    /// The network retried and the tick count of the retry, while the
    /// retry is on probation (one window).
    probation: Option<(Ablation, usize)>,
    ticks: usize,
    /// Set-asides and retries since start.
    pub switches: u64,
    /// The last decision, for `/diagnostics`.
    pub last: Option<OverloadChange>,
}

impl Overload {
    pub fn new(settings: OverloadSettings) -> Overload {
        Overload {
            settings,
            recent: VecDeque::with_capacity(settings.window_ticks + 1),
            set_aside: Vec::new(),
            calm: 0,
            retry_ticks: settings.retry_ticks,
            probation: None,
            ticks: 0,
            switches: 0,
            last: None,
        }
    }

    /// The networks set aside now (the model choice skips them).
    pub fn set_aside(&self) -> &[Ablation] {
        &self.set_aside
    }

    /// Skipped ticks in the current window.
    pub fn skipped_in_window(&self) -> usize {
        self.recent.iter().filter(|&&s| s).count()
    }

    pub fn window_ticks(&self) -> usize {
        self.settings.window_ticks
    }

    /// Ticks within budget still needed before the next retry (none: none
    /// set aside).
    pub fn retry_in_ticks(&self) -> Option<usize> {
        (!self.set_aside.is_empty()).then(|| self.retry_ticks.saturating_sub(self.calm))
    }

    /// One tick: its [`Budget`]; `active` the network running and
    /// `lighter` whether the model choice has one to fall back to. An
    /// excused tick moves neither the window nor the calm count.
    pub fn tick(
        &mut self,
        budget: Budget,
        active: Ablation,
        lighter: bool,
    ) -> Option<OverloadChange> {
        self.ticks += 1;
        let skipped = match budget {
            Budget::Kept => false,
            Budget::Missed => true,
            Budget::Excused => return None,
        };
        if self.recent.len() == self.settings.window_ticks {
            self.recent.pop_front();
        }
        self.recent.push_back(skipped);
        self.calm = if skipped { 0 } else { self.calm + 1 };
        if let Some((_, at)) = self.probation {
            if self.ticks - at > self.settings.window_ticks {
                // The retried network held its budget for a window: the
                // wait starts again from its shortest.
                self.probation = None;
                self.retry_ticks = self.settings.retry_ticks;
            }
        }
        let skipped_now = self.skipped_in_window();
        if skipped_now >= self.settings.max_skipped && lighter {
            if let Some((network, _)) = self.probation.take() {
                if network == active {
                    self.retry_ticks = (self.retry_ticks * 2).min(self.settings.max_retry_ticks);
                }
            }
            self.set_aside.push(active);
            self.recent.clear();
            self.calm = 0;
            return self.decided(OverloadChange::SetAside {
                network: active,
                skipped: skipped_now,
                window: self.settings.window_ticks,
            });
        }
        if self.calm >= self.retry_ticks {
            if let Some(network) = self.set_aside.pop() {
                let calm = self.calm;
                self.calm = 0;
                self.recent.clear();
                self.probation = Some((network, self.ticks));
                return self.decided(OverloadChange::Retry { network, calm });
            }
        }
        None
    }

    fn decided(&mut self, change: OverloadChange) -> Option<OverloadChange> {
        self.switches += 1;
        tracing::warn!("overload: {change}");
        self.last = Some(change.clone());
        Some(change)
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    fn missed(skipped: bool) -> Budget {
        if skipped {
            Budget::Missed
        } else {
            Budget::Kept
        }
    }

    fn settings() -> OverloadSettings {
        OverloadSettings {
            window_ticks: 10,
            max_skipped: 3,
            retry_ticks: 20,
            max_retry_ticks: 80,
        }
    }

    #[test]
    fn a_budget_missed_now_and_then_sets_nothing_aside() {
        let mut o = Overload::new(settings());
        for i in 0..100 {
            assert_eq!(
                o.tick(missed(i % 5 == 0), Ablation::EMP, true),
                None,
                "tick {i}"
            );
        }
        assert!(o.set_aside().is_empty());
    }

    #[test]
    fn a_persistent_miss_sets_the_network_aside_and_it_is_retried_with_backoff() {
        let mut o = Overload::new(settings());
        // Every other tick skipped: the third skip in the window decides.
        let mut decided = None;
        for i in 0..10 {
            if let Some(c) = o.tick(missed(i % 2 == 1), Ablation::EMP, true) {
                decided = Some((i, c));
                break;
            }
        }
        let (at, change) = decided.expect("set aside");
        assert_eq!(at, 5);
        assert_eq!(
            change,
            OverloadChange::SetAside {
                network: Ablation::EMP,
                skipped: 3,
                window: 10
            }
        );
        assert_eq!(o.set_aside(), &[Ablation::EMP]);
        // MP keeps its budget: EMP is tried after 20 calm ticks.
        for _ in 0..19 {
            assert_eq!(o.tick(Budget::Kept, Ablation::MP, true), None);
        }
        assert_eq!(o.retry_in_ticks(), Some(1));
        assert_eq!(
            o.tick(Budget::Kept, Ablation::MP, true),
            Some(OverloadChange::Retry {
                network: Ablation::EMP,
                calm: 20
            })
        );
        assert!(o.set_aside().is_empty());
        // EMP misses again at once: set aside, and the next wait doubles.
        let mut again = None;
        for i in 0..10 {
            again = again.or(o.tick(missed(i % 2 == 1), Ablation::EMP, true));
        }
        assert!(matches!(again, Some(OverloadChange::SetAside { .. })));
        assert_eq!(o.retry_in_ticks(), Some(40));
        assert_eq!(o.switches, 3);
    }

    #[test]
    fn without_a_lighter_network_the_miss_is_only_counted() {
        let mut o = Overload::new(settings());
        for _ in 0..30 {
            assert_eq!(o.tick(Budget::Missed, Ablation::P, false), None);
        }
        assert_eq!(o.skipped_in_window(), 10);
    }

    #[test]
    fn excused_ticks_are_charged_to_no_network() {
        let mut o = Overload::new(settings());
        // Two misses, then as many excused ticks as a window: the third
        // miss still decides, the excused ones neither fill nor empty it.
        for _ in 0..2 {
            assert_eq!(o.tick(Budget::Missed, Ablation::MP, true), None);
        }
        for _ in 0..30 {
            assert_eq!(o.tick(Budget::Excused, Ablation::MP, true), None);
        }
        assert_eq!(o.skipped_in_window(), 2);
        assert!(matches!(
            o.tick(Budget::Missed, Ablation::MP, true),
            Some(OverloadChange::SetAside {
                network: Ablation::MP,
                ..
            })
        ));
        // Nor do they count as calm: the retry still needs 20 kept ticks.
        for _ in 0..19 {
            assert_eq!(o.tick(Budget::Kept, Ablation::P, true), None);
            assert_eq!(o.tick(Budget::Excused, Ablation::P, true), None);
        }
        assert_eq!(o.retry_in_ticks(), Some(1));
    }

    #[test]
    fn the_settings_follow_the_rate() {
        let s = OverloadSettings::at_rate(30.0);
        assert_eq!((s.window_ticks, s.max_skipped), (30, 6));
        assert_eq!((s.retry_ticks, s.max_retry_ticks), (300, 9000));
    }
}
