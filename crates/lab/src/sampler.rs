//! The i.i.d. window sampler: which window of which episode goes into
//! training, and with which labels.
//!
//! Two protocols ([`Protocol`]), both one window per episode per draw (never
//! sliding windows), labels "fallen at `e + h`" for each horizon `h` (sticky,
//! from the metadata's fall onset mapped to the tick grid), classes balanced
//! by rejection sampling, deterministic for a seed (`StdRng`, ChaCha12).
//!
//! **Deployment** (the default, what the shipped models were trained and
//! scored with): one window set for all horizons. A window ends at a random
//! tick `e` such that it is full, has every needed stream, and holds NO
//! fallen tick (`e < onset tick`), the way the daemon sees an episode at any
//! tick before a fall. Classes are balanced at the balance horizon (the
//! middle one, index `(K - 1) / 2`); every horizon is scored on that set.
//!
//! **Paper** (the paper's "Datasets" section and its appendix figure "The
//! Z-coordinates of Poppy's head and the stop line for data sampling"): one
//! window set *per prediction span* `P`, each balanced at `P`, each with the
//! stop line of `P`. Our reading of the figure: the vertical line of span
//! `P` stands `P` ticks before the fall onset (the first tick the head is
//! below the threshold), it is "the latest possible frame" of a history
//! window, and "the last frame of history sequences cannot exceed" it. So a
//! falling episode's window at span `P` ends at `e <= onset - P`: the window
//! holds no fallen tick and none of the `P` ticks just before the onset. With
//! the sticky per-tick label "fallen at `e + P`", such a window is positive
//! only when it ends exactly on the stop line (`e + P = onset`); every
//! earlier one is negative. The positive class at span `P` is therefore "the
//! fall starts exactly `P` ticks from now" against "no fall within the next
//! `P` ticks" (later falls of the same episode included), which is what the
//! paper's sliding stop lines (further left for longer spans) imply. A
//! non-falling episode's window needs `e + P` inside the recording. Rejection
//! sampling: each episode's end tick is drawn uniformly until it has the
//! class the draw needs (equivalently, uniformly within that class), and when
//! one class runs out the surplus windows of the other class are rejected,
//! so that each span's set is exactly balanced (the paper: "rejection
//! sampling to ensure that class labels are balanced").
//!
//! Per draw, episodes that can give only one class (a non-falling episode has
//! no positive window) are drawn first, then each episode that can give both
//! is given the class the draw has fewer of so far (a coin flip on a tie),
//! and its end tick is drawn uniformly until one has that class. The picks
//! are then shuffled.
//!
//! A non-falling episode's windows need `e + h` inside the recording for the
//! longest scored horizon (the label must be known); a falling episode's
//! labels are known past its end (sticky).

use rand::rngs::StdRng;
use rand::seq::SliceRandom;
use rand::{Rng, SeedableRng};

use fall_guard_runtime::window::{EpisodeTicks, Streams};

/// Why a sampler could not be built.
#[derive(Debug, thiserror::Error)]
pub enum SamplerError {
    #[error("horizons must be non-empty and increasing (got {0:?})")]
    BadHorizons(Vec<usize>),
    #[error("balance horizon index {index} is out of range for {k} horizons")]
    BadBalanceIndex { index: usize, k: usize },
    #[error("no episode has a usable window ({n_episodes} episodes, window {n_ticks} ticks, longest horizon {max_horizon} ticks): episodes too short, or falling too early")]
    NoWindows {
        n_episodes: usize,
        n_ticks: usize,
        max_horizon: usize,
    },
}

/// Which windows are drawn and at which horizons they are scored (see the
/// module doc).
#[derive(Debug, Clone, Copy, PartialEq, Eq, Default)]
pub enum Protocol {
    /// One window set for all horizons, balanced at the middle horizon, no
    /// fallen tick in a window (as the daemon sees an episode).
    #[default]
    Deployment,
    /// The paper's: one window set per horizon `P`, balanced at `P`, windows
    /// ending at or before the stop line `onset - P`.
    Paper,
}

impl Protocol {
    /// Both, the default first.
    pub const ALL: [Protocol; 2] = [Protocol::Deployment, Protocol::Paper];

    /// The name on the command line and in reports.
    pub fn name(self) -> &'static str {
        match self {
            Protocol::Deployment => "deployment",
            Protocol::Paper => "paper",
        }
    }

    /// One line for reports.
    pub fn description(self) -> &'static str {
        match self {
            Protocol::Deployment => "one window per episode for all horizons, ending anywhere before the fall onset, classes balanced at the middle horizon",
            Protocol::Paper => "one window set per horizon P (one window per episode each), ending at or before the stop line onset - P, classes balanced at P by rejection sampling; horizon P scored on its own set",
        }
    }
}

impl std::fmt::Display for Protocol {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.write_str(self.name())
    }
}

/// How windows are drawn.
#[derive(Debug, Clone, PartialEq)]
pub struct SamplerConfig {
    /// `N`.
    pub n_ticks: usize,
    /// `H`, increasing.
    pub horizons_ticks: Vec<usize>,
    /// Index into `horizons_ticks` at which classes are balanced.
    pub balance_horizon_index: usize,
    /// Streams every tick of a window must have.
    pub needs: Streams,
    /// Draws per episode before giving up on the wanted class.
    pub max_tries: usize,
    /// Deployment: windows end before the onset and every horizon's label
    /// must be known. Paper: windows end at or before the balance horizon's
    /// stop line, only that horizon's label must be known, and surplus
    /// windows of the majority class are rejected.
    pub protocol: Protocol,
}

impl SamplerConfig {
    /// Balance at the middle horizon, all streams, 64 tries.
    pub fn new(n_ticks: usize, horizons_ticks: Vec<usize>) -> SamplerConfig {
        let k = horizons_ticks.len();
        SamplerConfig {
            n_ticks,
            horizons_ticks,
            balance_horizon_index: k.saturating_sub(1) / 2,
            needs: Streams::ALL,
            max_tries: 64,
            protocol: Protocol::Deployment,
        }
    }

    /// The paper's window set of one prediction span: balanced at
    /// `horizon_ticks`, stop line `onset - horizon_ticks`.
    pub fn paper(n_ticks: usize, horizon_ticks: usize) -> SamplerConfig {
        SamplerConfig {
            n_ticks,
            horizons_ticks: vec![horizon_ticks],
            balance_horizon_index: 0,
            needs: Streams::ALL,
            max_tries: 64,
            protocol: Protocol::Paper,
        }
    }

    /// The last tick a window of an episode with fall onset `onset` may end
    /// on: the stop line.
    pub fn stop_line(&self, onset: i64) -> i64 {
        match self.protocol {
            Protocol::Deployment => onset - 1,
            Protocol::Paper => onset - self.horizons_ticks[self.balance_horizon_index] as i64,
        }
    }
}

/// The end ticks an episode can give, and its fall onset.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub struct EpisodeSpan {
    /// Smallest usable end tick.
    pub first_end_tick: i64,
    /// Largest usable end tick (inclusive).
    pub last_end_tick: i64,
    pub fall_onset_tick: Option<i64>,
}

impl EpisodeSpan {
    /// The usable end ticks of `episode`, or `None` when it has none.
    pub fn of(episode: &EpisodeTicks, cfg: &SamplerConfig) -> Option<EpisodeSpan> {
        let max_h = match cfg.protocol {
            Protocol::Deployment => *cfg.horizons_ticks.last()?,
            Protocol::Paper => *cfg.horizons_ticks.get(cfg.balance_horizon_index)?,
        } as i64;
        let first = episode.first_complete_end_tick(cfg.n_ticks, cfg.needs)?;
        let last_tick = episode.last_tick()?;
        let last = match episode.fall_onset_tick {
            Some(onset) => cfg.stop_line(onset).min(last_tick),
            None => last_tick - max_h,
        };
        (first <= last).then_some(EpisodeSpan {
            first_end_tick: first,
            last_end_tick: last,
            fall_onset_tick: episode.fall_onset_tick,
        })
    }
}

/// Fallen at `end_tick + h` for each horizon (sticky).
pub fn labels_at(
    fall_onset_tick: Option<i64>,
    end_tick: i64,
    horizons_ticks: &[usize],
) -> Vec<bool> {
    horizons_ticks
        .iter()
        .map(|&h| fall_onset_tick.is_some_and(|o| end_tick + h as i64 >= o))
        .collect()
}

/// One drawn window.
#[derive(Debug, Clone, PartialEq, Eq)]
pub struct WindowPick {
    /// Index into the episodes given to [`WindowSampler::new`].
    pub episode: usize,
    pub end_tick: i64,
    /// One per horizon: fallen at `end_tick + h`.
    pub labels: Vec<bool>,
}

/// Draws one window per usable episode per epoch.
#[derive(Debug, Clone)]
pub struct WindowSampler {
    cfg: SamplerConfig,
    spans: Vec<Option<EpisodeSpan>>,
    rng: StdRng,
}

impl WindowSampler {
    pub fn new(
        episodes: &[EpisodeTicks],
        cfg: SamplerConfig,
        seed: u64,
    ) -> Result<WindowSampler, SamplerError> {
        let spans = episodes.iter().map(|e| EpisodeSpan::of(e, &cfg)).collect();
        Self::from_spans(spans, cfg, seed)
    }

    /// From precomputed spans (one per episode; `None` = unusable).
    pub fn from_spans(
        spans: Vec<Option<EpisodeSpan>>,
        cfg: SamplerConfig,
        seed: u64,
    ) -> Result<WindowSampler, SamplerError> {
        let h = &cfg.horizons_ticks;
        if h.is_empty() || h.windows(2).any(|w| w[0] >= w[1]) {
            return Err(SamplerError::BadHorizons(h.clone()));
        }
        if cfg.balance_horizon_index >= h.len() {
            return Err(SamplerError::BadBalanceIndex {
                index: cfg.balance_horizon_index,
                k: h.len(),
            });
        }
        if spans.iter().all(Option::is_none) {
            return Err(SamplerError::NoWindows {
                n_episodes: spans.len(),
                n_ticks: cfg.n_ticks,
                max_horizon: h[h.len() - 1],
            });
        }
        let unusable = spans.iter().filter(|s| s.is_none()).count();
        if unusable > 0 {
            tracing::warn!(
                unusable,
                total = spans.len(),
                "episodes without a usable window are skipped"
            );
        }
        Ok(WindowSampler {
            cfg,
            spans,
            rng: StdRng::seed_from_u64(seed),
        })
    }

    pub fn spans(&self) -> &[Option<EpisodeSpan>] {
        &self.spans
    }

    pub fn config(&self) -> &SamplerConfig {
        &self.cfg
    }

    /// The next epoch: one pick per usable episode (paper protocol: per
    /// usable episode that the balance keeps), in random order.
    pub fn epoch(&mut self) -> Vec<WindowPick> {
        let mut order: Vec<usize> = (0..self.spans.len())
            .filter(|&i| self.spans[i].is_some())
            .collect();
        order.shuffle(&mut self.rng);
        let h_bal = self.cfg.horizons_ticks[self.cfg.balance_horizon_index] as i64;
        // Episodes that can give only one class go first, so that the ones
        // that can give both make up the difference.
        let can_both = |span: &EpisodeSpan| {
            span.fall_onset_tick.is_some_and(|o| {
                let p = (o - h_bal).max(span.first_end_tick);
                p > span.first_end_tick && p <= span.last_end_tick
            })
        };
        let (flexible, forced): (Vec<usize>, Vec<usize>) = order
            .into_iter()
            .partition(|&i| self.spans[i].as_ref().is_some_and(can_both));
        let (mut positives, mut negatives) = (0usize, 0usize);
        let mut picks = Vec::with_capacity(flexible.len() + forced.len());
        for episode in forced.into_iter().chain(flexible) {
            let Some(span) = self.spans[episode] else {
                continue;
            };
            let want = match positives.cmp(&negatives) {
                std::cmp::Ordering::Less => true,
                std::cmp::Ordering::Greater => false,
                std::cmp::Ordering::Equal => self.rng.random_bool(0.5),
            };
            // can this episode give a window of class `want` at all?
            let positive_from = span
                .fall_onset_tick
                .map(|o| (o - h_bal).max(span.first_end_tick));
            let possible = match (want, positive_from) {
                (true, Some(p)) => p <= span.last_end_tick,
                (true, None) => false,
                (false, Some(p)) => p > span.first_end_tick,
                (false, None) => true,
            };
            let label_of = |e: i64| span.fall_onset_tick.is_some_and(|o| e + h_bal >= o);
            let mut end = self
                .rng
                .random_range(span.first_end_tick..=span.last_end_tick);
            if possible {
                let mut tries = 1;
                while label_of(end) != want && tries < self.cfg.max_tries.max(1) {
                    end = self
                        .rng
                        .random_range(span.first_end_tick..=span.last_end_tick);
                    tries += 1;
                }
                if label_of(end) != want {
                    // rare: fall back to a uniform draw within the wanted class
                    end = match (want, positive_from) {
                        (true, Some(p)) => self.rng.random_range(p..=span.last_end_tick),
                        (false, Some(p)) => self.rng.random_range(span.first_end_tick..p),
                        _ => end,
                    };
                }
            }
            let labels = labels_at(span.fall_onset_tick, end, &self.cfg.horizons_ticks);
            if labels[self.cfg.balance_horizon_index] {
                positives += 1;
            } else {
                negatives += 1;
            }
            picks.push(WindowPick {
                episode,
                end_tick: end,
                labels,
            });
        }
        if self.cfg.protocol == Protocol::Paper && positives != negatives {
            // Rejection: drop randomly chosen windows of the majority class.
            let majority = positives > negatives;
            let mut surplus = positives.abs_diff(negatives);
            picks.shuffle(&mut self.rng);
            let k = self.cfg.balance_horizon_index;
            picks.retain(|p| {
                if surplus > 0 && p.labels[k] == majority {
                    surplus -= 1;
                    false
                } else {
                    true
                }
            });
            (positives, negatives) = (positives.min(negatives), positives.min(negatives));
        }
        picks.shuffle(&mut self.rng);
        tracing::debug!(positives, negatives, "epoch drawn");
        picks
    }
}
