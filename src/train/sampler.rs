//! The i.i.d. window sampler: which window of which episode goes into
//! training, and with which labels.
//!
//! Per epoch, one window per episode (never sliding windows), ending at a
//! random tick `e` such that the window is full, has every needed stream,
//! and holds NO fallen tick (`e < onset tick`). Labels: fallen at `e + h`
//! for each horizon `h` (sticky, from the metadata's fall onset mapped to the
//! tick grid). Classes are balanced at the balance horizon (default: the
//! middle one, index `(K - 1) / 2`) by rejection sampling: each episode is
//! given the class the epoch has fewer of so far (a coin flip on a tie), and
//! end ticks are drawn uniformly until one has that class; an episode that
//! cannot give it (a non-falling episode has no positive window) gives the
//! other. Deterministic for a seed (`StdRng`, ChaCha12).
//!
//! A non-falling episode's windows need `e + hK` inside the recording (the
//! label must be known); a falling episode's labels are known past its end
//! (sticky).

use rand::rngs::StdRng;
use rand::seq::SliceRandom;
use rand::{Rng, SeedableRng};

use crate::window::{EpisodeTicks, Streams};

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
        let max_h = *cfg.horizons_ticks.last()? as i64;
        let first = episode.first_complete_end_tick(cfg.n_ticks, cfg.needs)?;
        let last_tick = episode.last_tick()?;
        let last = match episode.fall_onset_tick {
            Some(onset) => (onset - 1).min(last_tick),
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

    /// The next epoch: one pick per usable episode, in random order.
    pub fn epoch(&mut self) -> Vec<WindowPick> {
        let mut order: Vec<usize> = (0..self.spans.len())
            .filter(|&i| self.spans[i].is_some())
            .collect();
        order.shuffle(&mut self.rng);
        let h_bal = self.cfg.horizons_ticks[self.cfg.balance_horizon_index] as i64;
        let (mut positives, mut negatives) = (0usize, 0usize);
        let mut picks = Vec::with_capacity(order.len());
        for episode in order {
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
        tracing::debug!(positives, negatives, "epoch drawn");
        picks
    }
}
