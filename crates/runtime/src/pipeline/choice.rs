//! Which network runs ([`ModelChoice`]): camera lost -> MP, plan lost ->
//! EP, both -> P; a lost camera counts as back once it has been fresh for a
//! whole window (N ticks), so that the bigger network never sees a window
//! holding stale frames; a lost plan as soon as a fresh plan message is
//! there (the window's plan is cut from the newest tick's message alone).
//! The same rule makes a forecast valid again after a stale input the
//! active network reads ([`ModelChoice::refilled`]): the joints, too, need N
//! fresh ticks, except after a brief gap: a run of at most
//! `[streams].joints_max_held_ticks` ticks whose joints were all held (every
//! joint read, some older than the bound) is bridged, and the forecast is
//! valid again on the first fresh tick, while the window holds no more than
//! that many such ticks ([`ModelChoice::stale_ticks`]). Each switch is
//! logged and counted.

use std::collections::VecDeque;

use crate::model::Ablation;
use crate::streams::StreamKind;

use super::models::ablation_name;

/// Which streams are fresh (not stale) at one tick.
pub type Freshness = crate::streams::PerStream<bool>;

/// The joints of one tick, as the refill rule sees them.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum JointsAt {
    /// Every joint read, none older than `[streams].joints_stale_ms`.
    Fresh,
    /// Every joint read, some older than the bound: the tick holds their
    /// last values (a gap of at most `joints_max_held_ticks` such ticks is
    /// bridged).
    Held,
    /// A joint never read, or no joints sample yet: nothing to bridge with.
    Missing,
}

/// The joints' gaps (runs of ticks that were not fresh) as counted by
/// [`ModelChoice`], for `/diagnostics`.
#[derive(Debug, Clone, Copy, Default, PartialEq, Eq)]
pub struct JointGaps {
    /// Gaps over when the forecast was valid on their first fresh tick (a
    /// brief gap of held values, bridged).
    pub bridged: u64,
    /// Gaps over after which the window had to refill (longer than the
    /// bridge, a joint not read, or too many held ticks in the window).
    pub refilled: u64,
}

/// Chooses the network per tick from stream freshness (see module docs).
#[derive(Debug, Clone)]
pub struct ModelChoice {
    available: Vec<Ablation>,
    active: Ablation,
    /// Consecutive fresh ticks of each stream (0 on a stale tick).
    runs: crate::streams::PerStream<usize>,
    /// Fresh ticks after which a stream counts as back
    /// ([`ModelChoice::refill_ticks`]).
    refill: crate::streams::PerStream<usize>,
    /// `N`, the ticks of the window.
    window_ticks: usize,
    /// `[streams].joints_max_held_ticks`: the longest gap of held joints
    /// bridged, and the most held ticks a valid window may hold.
    max_held: usize,
    /// The joints of the last `N + max_held` ticks, oldest first: the
    /// window and, before it, as many ticks as a bridged gap may last (to
    /// tell whether a gap at the window's start began before it).
    joints: VecDeque<JointsAt>,
    /// Whether the joints were fresh at some tick (a run of stale ticks
    /// before that is the start, not a gap).
    joints_seen_fresh: bool,
    gaps: JointGaps,
    switches: u64,
    /// Networks the overload policy has set aside (`overload.rs`): not
    /// chosen while they are.
    set_aside: Vec<Ablation>,
}

/// Preference order: the most informed network first.
const PREFERENCE: [Ablation; 4] = [Ablation::EMP, Ablation::MP, Ablation::EP, Ablation::P];

/// The most informed of `available` that needs only the streams the
/// config provides (`camera = "none"`: no vision network): what the model
/// choice runs when nothing is lost, so running it is not a degradation.
pub fn best_configured(available: &[Ablation], camera: bool, plan: bool) -> Option<Ablation> {
    PREFERENCE
        .into_iter()
        .find(|a| available.contains(a) && (camera || !a.uses_vision()) && (plan || !a.uses_plan()))
}

impl ModelChoice {
    /// A choice among `available` for windows of `window_ticks` ticks that
    /// bridges no gap of the joints (each needs a whole window of fresh
    /// ticks; [`ModelChoice::bridging`] sets the bridge).
    pub fn new(available: Vec<Ablation>, window_ticks: usize) -> ModelChoice {
        ModelChoice {
            available,
            active: Ablation::EMP,
            runs: Default::default(),
            refill: crate::streams::PerStream {
                joints: window_ticks,
                camera: window_ticks,
                plan: 1,
            },
            window_ticks,
            max_held: 0,
            joints: VecDeque::with_capacity(window_ticks + 1),
            joints_seen_fresh: false,
            gaps: JointGaps::default(),
            switches: 0,
            set_aside: Vec::new(),
        }
    }

    /// The networks not to choose for overload (from the next tick on).
    pub fn set_aside(&mut self, networks: &[Ablation]) {
        self.set_aside = networks.to_vec();
    }

    /// Whether a lighter network than the active one is loaded and not set
    /// aside: one that reads a subset of its streams (EMP: MP, EP, P; MP
    /// and EP: P), so usable whenever the active one is.
    pub fn has_lighter(&self) -> bool {
        let active = self.active;
        self.available.iter().any(|&a| {
            a != active
                && !self.set_aside.contains(&a)
                && (active.uses_vision() || !a.uses_vision())
                && (active.uses_plan() || !a.uses_plan())
        })
    }

    /// The same choice, bridging a gap of at most `max_held_ticks` ticks of
    /// held joints (`[streams].joints_max_held_ticks`).
    pub fn bridging(mut self, max_held_ticks: usize) -> ModelChoice {
        self.max_held = max_held_ticks;
        self.joints = VecDeque::with_capacity(self.window_ticks + max_held_ticks + 1);
        self
    }

    /// `[streams].joints_max_held_ticks` as given to
    /// [`ModelChoice::bridging`].
    pub fn max_held_ticks(&self) -> usize {
        self.max_held
    }

    /// The ticks of the window (the last N updates) whose joints were not
    /// fresh: held past the bound (in a valid window: the bridged ones), or
    /// missing.
    pub fn stale_ticks(&self) -> usize {
        self.window().filter(|&j| j != JointsAt::Fresh).count()
    }

    /// The joints' gaps so far.
    pub fn joint_gaps(&self) -> JointGaps {
        self.gaps
    }

    /// The joints of the last N updates, oldest first.
    fn window(&self) -> impl Iterator<Item = JointsAt> + '_ {
        let skip = self.joints.len().saturating_sub(self.window_ticks);
        self.joints.iter().skip(skip).copied()
    }

    /// Whether the window's joints can be trusted: every tick fresh, or the
    /// newest fresh and each other one fresh or held (not missing) in a run
    /// of at most `max_held` held ticks (counted from where it began, also
    /// before the window), with at most `max_held` held ticks in the
    /// window.
    fn joints_usable(&self) -> bool {
        if self.runs.joints >= self.window_ticks {
            return true;
        }
        if self.max_held == 0 || self.runs.joints == 0 || self.joints.len() < self.window_ticks {
            return false;
        }
        let skip = self.joints.len().saturating_sub(self.window_ticks);
        let mut held = 0;
        // The run of held ticks being walked, and its length so far.
        let mut run = 0;
        for (i, &j) in self.joints.iter().enumerate() {
            match j {
                JointsAt::Fresh => run = 0,
                JointsAt::Missing if i >= skip => return false,
                // Before the window: only the length of a gap that goes on
                // into it counts.
                JointsAt::Missing => run = self.max_held,
                JointsAt::Held => {
                    run += 1;
                    if i >= skip {
                        held += 1;
                        if run > self.max_held || held > self.max_held {
                            return false;
                        }
                    }
                }
            }
        }
        true
    }

    pub fn active(&self) -> Ablation {
        self.active
    }

    pub fn switches(&self) -> u64 {
        self.switches
    }

    /// Consecutive fresh ticks of `stream` up to the last update.
    pub fn fresh_ticks(&self, stream: StreamKind) -> usize {
        self.runs[stream]
    }

    /// How many consecutive fresh ticks make `stream` usable again after it
    /// was stale: the joints and the camera frames are read over the whole
    /// window, so N (every tick of the window fresh again); the plan is read
    /// from the newest tick's plan message only (which holds the window's
    /// past and future plan), so 1: a fresh plan message is usable at once.
    pub fn refill_ticks(&self, stream: StreamKind) -> usize {
        self.refill[stream]
    }

    /// True when `stream` has been fresh for [`ModelChoice::refill_ticks`]
    /// ticks: a stream that was stale or absent counts as back only then,
    /// so that no window holding a stale value is trusted. The joints also
    /// count as back on the first fresh tick after a bridged gap (see the
    /// module docs): a window holding at most `joints_max_held_ticks` ticks
    /// of held joints, each in a gap no longer than that.
    pub fn refilled(&self, stream: StreamKind) -> bool {
        match stream {
            StreamKind::Joints => self.joints_usable(),
            _ => self.fresh_ticks(stream) >= self.refill_ticks(stream),
        }
    }

    /// Update with one tick's freshness; returns the new ablation if it
    /// changed. Joints that are not fresh count as missing (no gap of them
    /// is bridged: [`ModelChoice::update_ticks`] tells held from missing).
    pub fn update(&mut self, fresh: Freshness) -> Option<Ablation> {
        let joints = if fresh.joints {
            JointsAt::Fresh
        } else {
            JointsAt::Missing
        };
        self.update_ticks(fresh, joints)
    }

    /// Update with one tick's freshness and its joints (`Fresh` exactly
    /// when `fresh.joints`); returns the new ablation if it changed.
    pub fn update_ticks(&mut self, fresh: Freshness, joints: JointsAt) -> Option<Ablation> {
        let joints = match (fresh.joints, joints) {
            (true, _) => JointsAt::Fresh,
            (false, JointsAt::Fresh) => JointsAt::Missing,
            (false, other) => other,
        };
        let gap_over = fresh.joints && self.runs.joints == 0 && self.joints_seen_fresh;
        self.runs = self
            .runs
            .map(|kind, run| if fresh[kind] { run + 1 } else { 0 });
        if self.joints.len() == self.window_ticks + self.max_held {
            self.joints.pop_front();
        }
        self.joints.push_back(joints);
        if gap_over {
            if self.joints_usable() {
                self.gaps.bridged += 1;
            } else {
                self.gaps.refilled += 1;
            }
        }
        self.joints_seen_fresh |= fresh.joints;
        // A stream the active network reads may stay as long as it is fresh;
        // one it does not read must be back for a whole window first.
        let usable = |uses: bool, active_uses: bool, fresh: bool, stream: StreamKind| {
            !uses
                || if active_uses {
                    fresh
                } else {
                    self.refilled(stream)
                }
        };
        let current = self.active;
        let choice = PREFERENCE.into_iter().find(|&a| {
            self.available.contains(&a)
                && !self.set_aside.contains(&a)
                && usable(
                    a.uses_vision(),
                    current.uses_vision(),
                    fresh.camera,
                    StreamKind::Camera,
                )
                && usable(
                    a.uses_plan(),
                    current.uses_plan(),
                    fresh.plan,
                    StreamKind::Plan,
                )
        });
        match choice {
            Some(next) if next != current => {
                self.active = next;
                self.switches += 1;
                tracing::warn!(
                    from = ablation_name(current),
                    to = ablation_name(next),
                    camera_fresh = fresh.camera,
                    plan_fresh = fresh.plan,
                    "model switch"
                );
                Some(next)
            }
            _ => None,
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    const FRESH: Freshness = Freshness {
        joints: true,
        camera: true,
        plan: true,
    };

    fn all() -> Vec<Ablation> {
        vec![Ablation::EMP, Ablation::MP, Ablation::EP, Ablation::P]
    }

    #[test]
    fn degrades_per_lost_stream_and_returns_after_a_full_window() {
        let mut choice = ModelChoice::new(all(), 3);
        assert_eq!(choice.update(FRESH), None);
        assert_eq!(choice.active(), Ablation::EMP);
        let no_camera = Freshness {
            camera: false,
            ..FRESH
        };
        assert_eq!(choice.update(no_camera), Some(Ablation::MP));
        let neither = Freshness {
            camera: false,
            plan: false,
            ..FRESH
        };
        assert_eq!(choice.update(neither), Some(Ablation::P));
        let no_plan = Freshness {
            plan: false,
            ..FRESH
        };
        // Camera back: it must stay fresh for 3 ticks before EP takes over.
        assert_eq!(choice.update(no_plan), None);
        assert_eq!(choice.update(no_plan), None);
        assert_eq!(choice.update(no_plan), Some(Ablation::EP));
        // Plan back: its newest message is the whole plan input, so EMP
        // again at once.
        assert_eq!(choice.update(FRESH), Some(Ablation::EMP));
        assert_eq!(choice.switches(), 4);
        // The camera lost again and back: a whole window first.
        assert_eq!(choice.update(no_camera), Some(Ablation::MP));
        assert_eq!(choice.update(FRESH), None);
        assert_eq!(choice.update(FRESH), None);
        assert!(!choice.refilled(StreamKind::Camera));
        assert_eq!(choice.update(FRESH), Some(Ablation::EMP));
        assert!(choice.refilled(StreamKind::Camera) && choice.refilled(StreamKind::Plan));
    }

    #[test]
    fn the_joints_and_camera_refill_a_window_the_plan_one_tick() {
        let mut choice = ModelChoice::new(all(), 4);
        let stale = Freshness {
            joints: false,
            camera: false,
            plan: false,
        };
        choice.update(stale);
        choice.update(FRESH);
        assert!(choice.refilled(StreamKind::Plan));
        assert!(!choice.refilled(StreamKind::Joints));
        assert!(!choice.refilled(StreamKind::Camera));
        assert_eq!(choice.fresh_ticks(StreamKind::Joints), 1);
        assert_eq!(choice.refill_ticks(StreamKind::Joints), 4);
        assert_eq!(choice.refill_ticks(StreamKind::Camera), 4);
        assert_eq!(choice.refill_ticks(StreamKind::Plan), 1);
        for _ in 0..3 {
            choice.update(FRESH);
        }
        assert!(choice.refilled(StreamKind::Joints) && choice.refilled(StreamKind::Camera));
    }

    #[test]
    fn a_gap_of_held_joints_is_bridged_only_when_brief_and_read() {
        let stale = Freshness {
            joints: false,
            ..FRESH
        };
        // A window of 6 ticks bridging gaps of at most 2 held ticks.
        let run = |ticks: &[JointsAt]| {
            let mut choice = ModelChoice::new(all(), 6).bridging(2);
            let usable: Vec<bool> = ticks
                .iter()
                .map(|&j| {
                    let fresh = if j == JointsAt::Fresh { FRESH } else { stale };
                    choice.update_ticks(fresh, j);
                    choice.refilled(StreamKind::Joints)
                })
                .collect();
            (usable, choice)
        };
        use JointsAt::{Fresh as F, Held as H, Missing as M};
        // Two held ticks: not usable while held, usable on the first fresh
        // tick; the joints count as stale ticks of the window until they
        // have left it.
        let (usable, choice) = run(&[F, F, F, F, F, F, H, H, F, F]);
        assert_eq!(
            usable,
            [false, false, false, false, false, true, false, false, true, true]
        );
        assert_eq!(choice.stale_ticks(), 2);
        assert_eq!(
            choice.joint_gaps(),
            JointGaps {
                bridged: 1,
                refilled: 0
            }
        );
        // Three: waited out (usable once the window is fresh again).
        let (usable, choice) = run(&[F, F, F, F, F, F, H, H, H, F, F, F, F, F, F, F]);
        assert_eq!(
            &usable[9..],
            [false, false, false, false, false, true, true]
        );
        assert_eq!(
            choice.joint_gaps(),
            JointGaps {
                bridged: 0,
                refilled: 1
            }
        );
        // One tick with a joint not read: nothing to bridge with.
        let (usable, _) = run(&[F, F, F, F, F, F, M, F, F, F, F, F, F]);
        assert_eq!(&usable[7..], [false, false, false, false, false, true]);
        // A long gap (8 held ticks) whose last two are in the window of the
        // first fresh ticks: it began before the window, so it is not
        // brief, though only two of its ticks are left in the window.
        let (usable, _) = run(&[F, H, H, H, H, H, H, H, H, F, F, F, F, F, F]);
        assert_eq!(&usable[9..], [false, false, false, false, false, true]);
        // Two gaps of one held tick each, then a third: at most 2 in the
        // window.
        let (usable, choice) = run(&[F, F, F, F, F, F, H, F, H, F, H, F, F, F]);
        assert_eq!(
            &usable[6..],
            [false, true, false, true, false, false, true, true]
        );
        assert_eq!(
            choice.joint_gaps(),
            JointGaps {
                bridged: 2,
                refilled: 1
            }
        );
        // Bridging nothing: the old rule, a whole window of fresh ticks.
        let mut choice = ModelChoice::new(all(), 6);
        for j in [F, F, F, F, F, F, H] {
            choice.update_ticks(if j == F { FRESH } else { stale }, j);
        }
        for k in 1..=6 {
            choice.update_ticks(FRESH, F);
            assert_eq!(choice.refilled(StreamKind::Joints), k == 6, "{k}");
        }
    }

    #[test]
    fn a_missing_fallback_keeps_the_next_best() {
        let mut choice = ModelChoice::new(vec![Ablation::EMP, Ablation::P], 2);
        assert_eq!(
            choice.update(Freshness {
                camera: false,
                ..FRESH
            }),
            Some(Ablation::P)
        );
        // With only EMP, losing the camera leaves EMP active (forecasts invalid).
        let mut only = ModelChoice::new(vec![Ablation::EMP], 2);
        assert_eq!(
            only.update(Freshness {
                camera: false,
                ..FRESH
            }),
            None
        );
        assert_eq!(only.active(), Ablation::EMP);
    }

    #[test]
    fn the_best_configured_network_follows_the_configured_streams() {
        assert_eq!(best_configured(&all(), true, true), Some(Ablation::EMP));
        assert_eq!(best_configured(&all(), false, true), Some(Ablation::MP));
        assert_eq!(best_configured(&all(), true, false), Some(Ablation::EP));
        assert_eq!(best_configured(&all(), false, false), Some(Ablation::P));
        assert_eq!(
            best_configured(&[Ablation::EMP, Ablation::P], false, true),
            Some(Ablation::P)
        );
        assert_eq!(best_configured(&[Ablation::EMP], false, true), None);
    }
}
