//! What a safety engineer asks of the forecaster, measured the way the
//! daemon runs it: every episode of a split is replayed tick by tick through
//! the streaming forecaster (as `fall-guard-lab eval --recording`), the
//! forecasts feed the daemon's own [`SafetyLatch`], and we count
//!
//! - on falling episodes: whether `fall_imminent` went true before the fall
//!   onset, and the lead time (onset minus the first tick it went true);
//! - on non-falling episodes: false alarms (latch off -> on) per minute,
//!   and the time held: the share of their forecast time (once the window
//!   is full) with `fall_imminent` asserted. Triggers alone cannot see a
//!   latch that never lets go: a walk held from start to end counts one
//!   trigger, or none;
//! - on every tick before a fall: the share whose window holds an input
//!   outside the network's training range (the daemon's out-of-range
//!   guard; under `hold`, as the daemon's default, such a tick is not valid
//!   and asserts the latch).
//!
//! `fall-guard-lab warnings --choose` picks the trigger / release thresholds on
//! one split (the validation split: never the test split), reporting the
//! whole grid; `--trigger/--release` evaluates fixed thresholds (the test
//! split, with the thresholds chosen on validation).

use std::path::PathBuf;

use crate::error::{refused, CommandResult, Doing};
use serde::Serialize;

use super::commands::{forecast_ticks_judged, needs_of_model};
use super::dataset::{data_name, load_episode, Dataset, Split};
use fall_guard_runtime::model::LoadedModel;
use fall_guard_runtime::outputs::latch::{release_hold_ticks, SafetyLatch, Thresholds};

/// `fall-guard-lab warnings`.
#[derive(Debug)]
pub struct WarningsOptions {
    /// Model file (EMP, MP, EP or P).
    pub model: PathBuf,
    /// Data set directory (recordings + manifest.json).
    pub data: PathBuf,
    /// Split to replay: choose thresholds on `validation`, report on `test`.
    pub split: Split,
    /// Horizon the latch watches, ms (one of the model's horizons).
    pub horizon_ms: u32,
    /// Latch on at or above this probability.
    pub trigger: f32,
    /// Latch off below this probability...
    pub release: f32,
    /// ... for this long, ms (`[model].release_hold_ms`; 0: at once).
    pub release_hold_ms: u32,
    /// Search the thresholds on this split instead (trigger 0.30..0.95 by
    /// 0.05, then 0.97, 0.98, 0.99 and 0.995; release = trigger - 0.3, at
    /// least 0.05): the lowest trigger whose
    /// false-alarm rate is within --max-false-alarms-per-min.
    pub choose: bool,
    /// False-alarm budget for --choose, per minute of non-falling walking.
    pub max_false_alarms_per_min: f64,
    /// Time-held budget for --choose: share of non-falling time asserted.
    pub max_held_share: f64,
    /// A window with an input outside the training range asserts the
    /// latch (`[model].out_of_range = "hold"`).
    pub hold_out_of_range: bool,
    /// JSON report.
    pub out: Option<PathBuf>,
}

/// The forecasts of one episode at the watched horizon.
#[derive(Debug, Clone)]
pub struct EpisodeForecasts {
    pub name: String,
    /// Tick stamps (ns), probability at the horizon, and whether the window
    /// holds an input outside the training range, once the window is full.
    pub ticks: Vec<(i64, f32, bool)>,
    /// Fall onset stamp (ns), `None` for an episode that does not fall.
    pub onset_ns: Option<i64>,
}

/// The warning figures of one threshold pair on a split.
#[derive(Debug, Clone, Serialize, PartialEq)]
pub struct WarningStats {
    pub trigger: f32,
    pub release: f32,
    pub falling_episodes: usize,
    /// Falls with `fall_imminent` true before the onset.
    pub warned: usize,
    pub warned_share: f64,
    /// Falls warned at least [`EARLY_LEAD_S`] before the onset.
    pub warned_by_0_5s: usize,
    pub warned_by_0_5s_share: f64,
    /// Lead times of the warned falls, s.
    pub lead_median_s: Option<f64>,
    pub lead_p10_s: Option<f64>,
    pub non_falling_episodes: usize,
    /// Minutes of forecasts on non-falling episodes.
    pub non_falling_minutes: f64,
    pub false_alarms: u64,
    pub false_alarms_per_min: f64,
    /// Minutes of non-falling forecasts with `fall_imminent` asserted.
    pub held_minutes: f64,
    /// `held_minutes / non_falling_minutes`.
    pub held_share: f64,
    /// Share of the forecast ticks before any fall (every episode) whose
    /// window holds an input outside the training range.
    pub out_of_range_share: f64,
    /// Whether such a tick asserted the latch (`hold`).
    pub out_of_range_holds: bool,
}

/// The lead a warning needs for a safety node to brace in time, s.
pub const EARLY_LEAD_S: f64 = 0.5;

/// Nearest-rank quantile of sorted values.
fn quantile(sorted: &[f64], q: f64) -> Option<f64> {
    if sorted.is_empty() {
        return None;
    }
    let i = ((q * sorted.len() as f64).ceil() as usize).clamp(1, sorted.len()) - 1;
    Some(sorted[i])
}

/// Runs the daemon's latch over every episode's forecasts (released after
/// `hold_ticks` ticks in a row below `release`).
pub fn warning_stats(
    episodes: &[EpisodeForecasts],
    trigger: f32,
    release: f32,
    hold_ticks: usize,
    tick_s: f64,
    hold_out_of_range: bool,
) -> CommandResult<WarningStats> {
    let mut leads = Vec::new();
    let (mut falling, mut warned, mut calm, mut minutes, mut alarms) = (0, 0, 0, 0.0, 0u64);
    let (mut held_ticks, mut judged, mut out_of_range) = (0usize, 0usize, 0usize);
    // A tick is valid unless the guard holds it.
    let valid = |out: bool| !(out && hold_out_of_range);
    for ep in episodes {
        // The latch sees one probability: index 0 of a one-element forecast.
        let thresholds = Thresholds::new(trigger, release)
            .doing(|| format!("thresholds {trigger} / {release}"))?;
        let mut latch = SafetyLatch::new(0, thresholds)
            .with_release_hold(hold_ticks)
            .silent();
        match ep.onset_ns {
            Some(onset) => {
                falling += 1;
                for (_, _, out) in ep.ticks.iter().take_while(|(stamp, _, _)| *stamp < onset) {
                    judged += 1;
                    out_of_range += usize::from(*out);
                }
                let first = ep
                    .ticks
                    .iter()
                    .take_while(|(stamp, _, _)| *stamp < onset)
                    .find(|(_, p, out)| latch.update(&[*p], valid(*out)));
                if let Some((stamp, _, _)) = first {
                    warned += 1;
                    leads.push((onset - stamp) as f64 / 1e9);
                }
            }
            None => {
                calm += 1;
                minutes += ep.ticks.len() as f64 * tick_s / 60.0;
                for (_, p, out) in &ep.ticks {
                    judged += 1;
                    out_of_range += usize::from(*out);
                    held_ticks += usize::from(latch.update(&[*p], valid(*out)));
                }
                alarms += latch.triggers();
            }
        }
    }
    leads.sort_by(f64::total_cmp);
    let early = leads.iter().filter(|&&l| l >= EARLY_LEAD_S).count();
    let share = |n: usize| {
        if falling > 0 {
            n as f64 / falling as f64
        } else {
            f64::NAN
        }
    };
    Ok(WarningStats {
        trigger,
        release,
        falling_episodes: falling,
        warned,
        warned_share: share(warned),
        warned_by_0_5s: early,
        warned_by_0_5s_share: share(early),
        lead_median_s: quantile(&leads, 0.5),
        lead_p10_s: quantile(&leads, 0.1),
        non_falling_episodes: calm,
        non_falling_minutes: minutes,
        false_alarms: alarms,
        false_alarms_per_min: if minutes > 0.0 {
            alarms as f64 / minutes
        } else {
            f64::NAN
        },
        held_minutes: held_ticks as f64 * tick_s / 60.0,
        held_share: if minutes > 0.0 {
            held_ticks as f64 * tick_s / 60.0 / minutes
        } else {
            f64::NAN
        },
        out_of_range_share: if judged > 0 {
            out_of_range as f64 / judged as f64
        } else {
            f64::NAN
        },
        out_of_range_holds: hold_out_of_range,
    })
}

/// The threshold grid of `--choose`: 0.30..0.95 by 0.05, then the steps a
/// network trained on balanced windows needs at its top (its probabilities
/// crowd there on walking that a stop must leave alone).
pub fn threshold_grid() -> Vec<(f32, f32)> {
    (0..=13)
        .map(|i| 0.30 + 0.05 * i as f32)
        .chain([0.97, 0.98, 0.99, 0.995])
        .map(|trigger| (trigger, (trigger - 0.3).max(0.05)))
        .collect()
}

/// The lowest trigger within the false-alarm and time-held budgets (the
/// most falls warned).
pub fn choose(
    grid: &[WarningStats],
    max_false_alarms_per_min: f64,
    max_held_share: f64,
) -> Option<&WarningStats> {
    grid.iter()
        .filter(|s| {
            s.false_alarms_per_min <= max_false_alarms_per_min && s.held_share <= max_held_share
        })
        .min_by(|a, b| a.trigger.total_cmp(&b.trigger))
}

/// Replays every episode of the split through the streaming forecaster.
pub fn forecast_split(
    model: &LoadedModel,
    data: &Dataset,
    split: Split,
    horizon_index: usize,
) -> CommandResult<Vec<EpisodeForecasts>> {
    let spec = model.meta.window_spec();
    let needs = needs_of_model(&model.meta);
    let mut out = Vec::new();
    for path in data.paths(split) {
        let episode =
            load_episode(&path, &spec, needs).doing(|| format!("reading {}", path.display()))?;
        let onset_ns = episode.fall_onset_tick.map(|t| episode.grid.stamp_ns(t));
        let ticks = forecast_ticks_judged(model, &episode)?
            .into_iter()
            .map(|t| (t.stamp_ns, t.probabilities[horizon_index], t.out_of_range))
            .collect();
        out.push(EpisodeForecasts {
            name: path
                .file_name()
                .map(|n| n.to_string_lossy().into_owned())
                .unwrap_or_default(),
            ticks,
            onset_ns,
        });
    }
    Ok(out)
}

/// What `fall-guard-lab warnings` found: the latch's figures at each
/// threshold pair, and the pair chosen (with `--choose`).
#[derive(Debug, Clone)]
pub struct WarningsReport {
    /// The split replayed.
    pub split: Split,
    /// One row per threshold pair.
    pub grid: Vec<WarningStats>,
    /// Whether a pair was searched for (`--choose`).
    pub searched: bool,
    /// The pair chosen, if one keeps false alarms within the budget.
    pub chosen: Option<WarningStats>,
    /// The false-alarm budget of the search, per minute.
    pub max_false_alarms_per_min: f64,
    /// The time-held budget of the search, share of walking time.
    pub max_held_share: f64,
}

/// A threshold as the grid has it: two places, three where it has them (0.995).
fn threshold(x: f32) -> String {
    let three = format!("{x:.3}");
    match three.strip_suffix('0') {
        Some(two) => two.to_string(),
        None => three,
    }
}

impl WarningsReport {
    /// The figures as a Markdown table, and the choice.
    pub fn table(&self) -> String {
        let mut t = format!(
            "| trigger | release | falls warned | warned >= {EARLY_LEAD_S} s ahead | lead median s | lead p10 s | false alarms / min | time held | inputs out of range |\n| --- | --- | --- | --- | --- | --- | --- | --- | --- |\n"
        );
        let opt = |v: Option<f64>| v.map_or("-".to_string(), |x| format!("{x:.2}"));
        for s in &self.grid {
            t += &format!(
                "| {} | {} | {}/{} ({:.0}%) | {} ({:.0}%) | {} | {} | {:.2} ({} in {:.1} min) | {:.1}% ({:.2} min) | {:.2}% of ticks{} |\n",
                threshold(s.trigger),
                threshold(s.release),
                s.warned,
                s.falling_episodes,
                100.0 * s.warned_share,
                s.warned_by_0_5s,
                100.0 * s.warned_by_0_5s_share,
                opt(s.lead_median_s),
                opt(s.lead_p10_s),
                s.false_alarms_per_min,
                s.false_alarms,
                s.non_falling_minutes,
                100.0 * s.held_share,
                s.held_minutes,
                100.0 * s.out_of_range_share,
                if s.out_of_range_holds { ", held" } else { "" }
            );
        }
        if self.searched {
            t += &match &self.chosen {
                Some(c) => format!(
                    "chosen on {}: trigger {}, release {} (false alarms <= {} / min, time held <= {:.1}%)\n",
                    self.split,
                    threshold(c.trigger),
                    threshold(c.release),
                    self.max_false_alarms_per_min,
                    100.0 * self.max_held_share
                ),
                None => format!(
                    "no threshold on the grid keeps false alarms within {} / min and time held within {:.1}%\n",
                    self.max_false_alarms_per_min,
                    100.0 * self.max_held_share
                ),
            };
        }
        t
    }
}

/// `fall-guard-lab warnings`: the latch's figures (a table the binary
/// prints), written as JSON with `--out`.
pub fn run_warnings(args: &WarningsOptions) -> CommandResult<WarningsReport> {
    let model =
        LoadedModel::load(&args.model).doing(|| format!("reading {}", args.model.display()))?;
    let tick_s = 1.0 / model.meta.rate_hz;
    let hold_ticks = release_hold_ticks(args.release_hold_ms, model.meta.rate_hz);
    let horizons_ms = model.meta.horizons_ms();
    let horizon_index = horizons_ms
        .iter()
        .position(|&h| h == args.horizon_ms)
        .ok_or_else(|| {
            refused(format!(
                "--horizon-ms {}: the model's horizons are {horizons_ms:?} ms",
                args.horizon_ms
            ))
        })?;
    let data = Dataset::open(&args.data)?;
    let episodes = forecast_split(&model, &data, args.split, horizon_index)?;
    let pairs = if args.choose {
        threshold_grid()
    } else {
        vec![(args.trigger, args.release)]
    };
    let grid = pairs
        .iter()
        .map(|&(t, r)| warning_stats(&episodes, t, r, hold_ticks, tick_s, args.hold_out_of_range))
        .collect::<CommandResult<Vec<_>>>()?;
    let chosen = if args.choose {
        choose(&grid, args.max_false_alarms_per_min, args.max_held_share).cloned()
    } else {
        None
    };
    if let Some(out) = &args.out {
        let report = serde_json::json!({
            "model": data_name(&args.model),
            "data": data_name(&args.data),
            "split": args.split.name(),
            "horizon_ms": args.horizon_ms,
            "release_hold_ms": args.release_hold_ms,
            "grid": grid,
            "chosen": chosen,
            "max_false_alarms_per_min": args.max_false_alarms_per_min,
            "max_held_share": args.max_held_share,
            "out_of_range": if args.hold_out_of_range { "hold" } else { "forecast" },
            "input_ranges": model.meta.input_ranges.as_ref().map(|r| r.measured_on.clone()),
        });
        std::fs::write(out, serde_json::to_vec_pretty(&report)?)
            .doing(|| format!("writing {}", out.display()))?;
    }
    Ok(WarningsReport {
        split: args.split,
        grid,
        searched: args.choose,
        chosen,
        max_false_alarms_per_min: args.max_false_alarms_per_min,
        max_held_share: args.max_held_share,
    })
}

#[cfg(test)]
mod tests {
    use super::*;

    fn episode(ps: &[f32], onset_tick: Option<usize>) -> EpisodeForecasts {
        let tick_ns = 33_333_333;
        EpisodeForecasts {
            name: "e".into(),
            ticks: ps
                .iter()
                .enumerate()
                .map(|(i, &p)| (i as i64 * tick_ns, p, false))
                .collect(),
            onset_ns: onset_tick.map(|t| t as i64 * tick_ns),
        }
    }

    #[test]
    fn lead_time_and_false_alarms_follow_the_latch() {
        let tick_s = 1.0 / 30.0;
        // Falls at tick 60; warned from tick 30 on: lead 1 s.
        let mut warned = vec![0.1f32; 30];
        warned.extend(vec![0.9f32; 40]);
        // Falls at tick 60; only crosses after the onset: not warned.
        let mut late = vec![0.1f32; 65];
        late.extend(vec![0.9f32; 5]);
        // Falls at tick 60; warned from tick 55 on: lead 0.17 s, too short to brace.
        let mut short = vec![0.1f32; 55];
        short.extend(vec![0.9f32; 15]);
        // Does not fall; two separate alarms (released in between).
        let mut calm = vec![0.1f32; 1800];
        calm[100] = 0.8;
        calm[101] = 0.2;
        calm[500] = 0.75;
        let eps = vec![
            episode(&warned, Some(60)),
            episode(&late, Some(60)),
            episode(&short, Some(60)),
            episode(&calm, None),
        ];
        let s = warning_stats(&eps, 0.7, 0.4, 1, tick_s, true).unwrap();
        assert_eq!((s.falling_episodes, s.warned, s.warned_by_0_5s), (3, 2, 1));
        assert!((s.warned_by_0_5s_share - 1.0 / 3.0).abs() < 1e-12);
        // Leads 1 s and 0.17 s: the nearest-rank median is the shorter.
        assert!(
            (s.lead_median_s.unwrap() - 5.0 / 30.0).abs() < 1e-6,
            "{s:?}"
        );
        assert_eq!(s.false_alarms, 2);
        assert!((s.non_falling_minutes - 1.0).abs() < 1e-9);
        assert!((s.false_alarms_per_min - 2.0).abs() < 1e-9);
        // A higher trigger removes the alarms and the warning.
        let s = warning_stats(&eps, 0.95, 0.5, 1, tick_s, true).unwrap();
        assert_eq!((s.warned, s.warned_by_0_5s, s.false_alarms), (0, 0, 0));
        assert!(s.lead_median_s.is_none());
    }

    #[test]
    fn time_held_counts_every_asserted_tick_and_the_guard_holds_when_asked() {
        // One walk, 60 ticks of 1 s: latched from tick 10 to 39 (one trigger).
        let mut ps = vec![0.1f32; 60];
        ps[10..40].iter_mut().for_each(|p| *p = 0.92);
        let mut walk = episode(&ps, None);
        let s = warning_stats(std::slice::from_ref(&walk), 0.7, 0.4, 1, 1.0, true).unwrap();
        assert_eq!(s.false_alarms, 1);
        assert!((s.held_share - 0.5).abs() < 1e-9, "{s:?}");
        assert!((s.held_minutes - 0.5).abs() < 1e-9, "{s:?}");
        assert_eq!(s.out_of_range_share, 0.0);
        // Ticks 45..50 out of the training range: held under `hold` only.
        walk.ticks[45..50].iter_mut().for_each(|t| t.2 = true);
        let eps = vec![walk];
        let held = warning_stats(&eps, 0.7, 0.4, 1, 1.0, true).unwrap();
        assert!((held.held_share - 35.0 / 60.0).abs() < 1e-9, "{held:?}");
        assert_eq!(
            held.false_alarms, 1,
            "an assertion for the guard is no trigger"
        );
        assert!((held.out_of_range_share - 5.0 / 60.0).abs() < 1e-9);
        let forecast = warning_stats(&eps, 0.7, 0.4, 1, 1.0, false).unwrap();
        assert!((forecast.held_share - 0.5).abs() < 1e-9, "{forecast:?}");
        // The choice keeps time held within its budget: only a trigger
        // above 0.92 leaves the walk alone, and the guard's 5 ticks (8%)
        // exceed 1% at any trigger.
        let grid = |hold| {
            threshold_grid()
                .into_iter()
                .map(|(t, r)| warning_stats(&eps, t, r, 1, 1.0, hold).unwrap())
                .collect::<Vec<_>>()
        };
        let c = choose(&grid(false), 10.0, 0.01).map(|c| c.trigger);
        assert!(c.is_some_and(|t| (t - 0.95).abs() < 1e-6), "{c:?}");
        assert!(choose(&grid(true), 10.0, 0.01).is_none());
        assert!(choose(&grid(true), 10.0, 0.1).is_some());
    }

    #[test]
    fn thresholds_print_as_the_grid_has_them() {
        let printed: Vec<String> = threshold_grid()
            .iter()
            .map(|&(t, _)| threshold(t))
            .collect();
        assert_eq!(printed[0], "0.30");
        assert_eq!(printed[13], "0.95");
        assert_eq!(&printed[14..], ["0.97", "0.98", "0.99", "0.995"]);
    }

    #[test]
    fn choose_takes_the_lowest_trigger_within_budget() {
        let eps = vec![episode(&[0.1, 0.62, 0.1, 0.62, 0.1], None)];
        let grid: Vec<WarningStats> = threshold_grid()
            .into_iter()
            .map(|(t, r)| warning_stats(&eps, t, r, 1, 1.0, true).unwrap())
            .collect();
        // 5 ticks of 1 s: one alarm is 12 per min, over budget up to trigger 0.6.
        let c = choose(&grid, 1.0, 1.0).unwrap();
        assert!((c.trigger - 0.65).abs() < 1e-6, "{c:?}");
        assert!(threshold_grid().iter().all(|(t, r)| r < t && *r >= 0.05));
    }
}
