//! The out-of-range guard's daemon side: which inputs of the forecast window
//! lie outside what the network was trained on, since when, and what the
//! forecast does then (`[model].out_of_range`).
//!
//! The network reports the excursions of the window it forecast
//! ([`StreamingForecaster::excursions`](crate::model::StreamingForecaster::excursions),
//! the values already held to their bounds); [`InputGuard::judge`] keeps,
//! per input, the tick its excursion began, and under the `hold` policy
//! makes the forecast not valid, naming the inputs, so that the latch
//! asserts `fall_imminent` (`docs/daemon.md`, "Inputs outside the training
//! range").

use std::collections::BTreeMap;

use crate::config::OutOfRange;
use crate::model::ranges::{Excursion, Input};
use crate::outputs::diagnostics::{GuardState, OutOfRangeInput};

/// Follows the excursions forecast by forecast.
#[derive(Debug)]
pub struct InputGuard {
    policy: OutOfRange,
    joint_names: Vec<String>,
    /// Per input outside now: (tick, stamp) its excursion began.
    since: BTreeMap<Input, (i64, i64)>,
    state: GuardState,
}

fn input_name(input: Input, joint_names: &[String]) -> String {
    let name = |j: usize| joint_names.get(j).map_or("?", String::as_str);
    match input {
        Input::Joint(j) => name(j).to_string(),
        Input::Plan(j) => format!("plan of {}", name(j)),
        Input::FrameMean => "camera brightness".to_string(),
        Input::FrameStd => "camera contrast".to_string(),
    }
}

impl InputGuard {
    pub fn new(policy: OutOfRange, joint_names: Vec<String>) -> InputGuard {
        InputGuard {
            policy,
            joint_names,
            since: BTreeMap::new(),
            state: GuardState {
                holds: policy == OutOfRange::Hold,
                ..GuardState::default()
            },
        }
    }

    /// Judges one forecast window (tick `tick` at `stamp_ns`) by its
    /// excursions; `bounds` says where its network's bounds come from.
    /// Returns the sentence for the forecast when an input is out
    /// (`None`: every input inside).
    pub fn judge(
        &mut self,
        tick: i64,
        stamp_ns: i64,
        excursions: &[Excursion],
        bounds: &str,
    ) -> Option<String> {
        self.state.windows += 1;
        self.state.bounds = bounds.to_string();
        self.since
            .retain(|input, _| excursions.iter().any(|e| e.input == *input));
        for e in excursions {
            self.since.entry(e.input).or_insert((tick, stamp_ns));
        }
        let mut sorted: Vec<&Excursion> = excursions.iter().collect();
        // Largest first, in units of their own range where the range has a
        // width (a joint out by 30 deg beside a brightness out by 0.1).
        let relative = |e: &Excursion| {
            let width = (e.bound[1] - e.bound[0]).abs().max(1e-6);
            e.beyond() / width
        };
        sorted.sort_by(|a, b| relative(b).total_cmp(&relative(a)));
        self.state.out_of_range = sorted
            .iter()
            .map(|e| OutOfRangeInput {
                input: input_name(e.input, &self.joint_names),
                detail: e.describe(&self.joint_names),
                since_ns: self.since.get(&e.input).map_or(stamp_ns, |s| s.1),
            })
            .collect();
        if excursions.is_empty() {
            return None;
        }
        self.state.windows_out_of_range += 1;
        Some(self.sentence())
    }

    /// [`GuardState::sentence`] of now.
    pub fn sentence(&self) -> String {
        self.state.sentence()
    }

    /// Under `hold`, an input outside its bound makes the forecast not valid.
    pub fn holds(&self) -> bool {
        self.policy == OutOfRange::Hold
    }

    pub fn state(&self) -> &GuardState {
        &self.state
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    fn excursion(input: Input, value: f32) -> Excursion {
        Excursion {
            input,
            value,
            bound: [-0.1, 0.1],
        }
    }

    #[test]
    fn names_the_inputs_largest_first_and_keeps_when_each_began() {
        let names = vec!["abs_x".to_string(), "bust_x".to_string()];
        let mut g = InputGuard::new(OutOfRange::Hold, names);
        assert_eq!(g.judge(59, 1_966_000_000, &[], "x"), None);
        let first = g
            .judge(60, 2_000_000_000, &[excursion(Input::Joint(1), 0.2)], "x")
            .expect("out");
        assert!(first.contains("bust_x 11.5 deg"), "{first}");
        assert!(first.contains("since t=2.000 s"), "{first}");
        let both = g
            .judge(
                61,
                2_033_000_000,
                &[
                    excursion(Input::Joint(0), 0.15),
                    excursion(Input::Joint(1), 0.6),
                ],
                "x",
            )
            .expect("out");
        // bust_x is out further and began earlier.
        assert!(
            both.find("bust_x").unwrap() < both.find("abs_x").unwrap(),
            "{both}"
        );
        assert!(both.contains("(since t=2.000 s)"), "{both}");
        assert!(both.contains("(since t=2.033 s)"), "{both}");
        assert_eq!(g.state().windows_out_of_range, 2);
        assert_eq!(g.state().windows, 3);
        // Back inside: nothing named, and a new excursion starts anew.
        assert_eq!(g.judge(62, 2_066_000_000, &[], "x"), None);
        assert!(g.state().out_of_range.is_empty());
        let again = g
            .judge(63, 2_100_000_000, &[excursion(Input::Joint(1), 0.2)], "x")
            .unwrap();
        assert!(again.contains("since t=2.100 s"), "{again}");
    }

    #[test]
    fn a_long_list_is_cut_after_three() {
        let names: Vec<String> = (0..5).map(|i| format!("j{i}")).collect();
        let mut g = InputGuard::new(OutOfRange::Forecast, names);
        let all: Vec<Excursion> = (0..5)
            .map(|j| excursion(Input::Joint(j), 0.2 + j as f32 * 0.1))
            .collect();
        let s = g.judge(1, 0, &all, "x").unwrap();
        assert!(
            s.starts_with("inputs outside the training range: j4 "),
            "{s}"
        );
        assert!(s.ends_with("and 2 more"), "{s}");
        assert!(!g.holds());
    }
}
