//! The paper's metrics, per horizon: accuracy, F1, precision, recall,
//! expected calibration error (15 equal-width bins) and ROC-AUC.
//!
//! In: predicted probabilities and 0/1 labels of one horizon. Out: [`Metrics`],
//! and [`ece_bootstrap`]: a confidence interval of the ECE that resamples
//! whole episodes (windows of one episode are not independent), with the
//! ECE's noise floor on the same windows ([`ece_floor`]).

use rand::rngs::StdRng;
use rand::{Rng, SeedableRng};
use serde::{Deserialize, Serialize};

/// Metrics of one horizon.
#[derive(Debug, Clone, Copy, PartialEq, Serialize, Deserialize)]
pub struct Metrics {
    /// Fraction correct at threshold 0.5.
    pub accuracy: f64,
    /// Harmonic mean of precision and recall.
    pub f1: f64,
    /// TP / (TP + FP); 0 when nothing is predicted positive.
    pub precision: f64,
    /// TP / (TP + FN); 0 when there are no positives.
    pub recall: f64,
    /// Expected calibration error, 15 equal-width bins.
    pub ece: f64,
    /// Area under the ROC curve (ties count half); NaN with one class only.
    pub roc_auc: f64,
    /// Number of samples.
    pub count: usize,
}

/// Computes every metric for probabilities `p` and labels `y`.
pub fn metrics(p: &[f32], y: &[bool]) -> Metrics {
    assert_eq!(p.len(), y.len(), "one label per prediction");
    let (mut tp, mut fp, mut tn, mut fneg) = (0usize, 0usize, 0usize, 0usize);
    for (&pi, &yi) in p.iter().zip(y) {
        match (pi >= 0.5, yi) {
            (true, true) => tp += 1,
            (true, false) => fp += 1,
            (false, false) => tn += 1,
            (false, true) => fneg += 1,
        }
    }
    let n = p.len().max(1) as f64;
    let ratio = |a: usize, b: usize| if b == 0 { 0.0 } else { a as f64 / b as f64 };
    let precision = ratio(tp, tp + fp);
    let recall = ratio(tp, tp + fneg);
    let f1 = if precision + recall == 0.0 {
        0.0
    } else {
        2.0 * precision * recall / (precision + recall)
    };
    Metrics {
        accuracy: (tp + tn) as f64 / n,
        f1,
        precision,
        recall,
        ece: ece(p, y, 15),
        roc_auc: roc_auc(p, y),
        count: p.len(),
    }
}

/// Expected calibration error: bins of equal width on the predicted
/// probability of the positive class; `Σ |bin| / n · |mean(y) − mean(p)|`.
pub fn ece(p: &[f32], y: &[bool], bins: usize) -> f64 {
    let n = p.len().max(1) as f64;
    reliability(p, y, bins)
        .into_iter()
        .map(|(conf, pos, count)| count as f64 / n * (pos - conf).abs())
        .sum()
}

/// A bootstrap confidence interval of the ECE.
#[derive(Debug, Clone, Copy, PartialEq, Serialize, Deserialize)]
pub struct EceInterval {
    /// ECE of the sample itself.
    pub ece: f64,
    /// Lower bound (the `(1 - level) / 2` percentile of the resampled ECEs).
    pub lower: f64,
    /// Upper bound (the `(1 + level) / 2` percentile).
    pub upper: f64,
    /// Coverage, e.g. 0.95.
    pub level: f64,
    /// Number of resamples.
    pub resamples: usize,
    /// Number of episodes resampled.
    pub episodes: usize,
    /// The ECE a perfectly calibrated network shows on these windows, on
    /// average ([`ece_floor`]): what the sample's ECE is compared with.
    pub floor: f64,
    /// The `(1 + level) / 2` percentile of that calibrated network's ECE: a
    /// sample ECE above it shows miscalibration at this level.
    pub floor_upper: f64,
}

/// Per-bin sums of one episode's windows: count, sum of p, sum of y.
type BinSums = Vec<(f64, f64, f64)>;

/// Percentile bootstrap of the ECE (`bins` equal-width bins) by episode:
/// `resamples` times, draw as many episodes as there are, with replacement,
/// take all their windows, compute the ECE; the interval is the central
/// `level` share of those values. `episode[i]` names the episode of window
/// `i`. Deterministic for `seed`.
pub fn ece_bootstrap(
    p: &[f32],
    y: &[bool],
    episode: &[usize],
    bins: usize,
    resamples: usize,
    level: f64,
    seed: u64,
) -> EceInterval {
    assert!(
        p.len() == y.len() && p.len() == episode.len(),
        "one label and one episode per prediction"
    );
    let mut ids: Vec<usize> = episode.to_vec();
    ids.sort_unstable();
    ids.dedup();
    let mut groups: Vec<BinSums> = vec![vec![(0.0, 0.0, 0.0); bins]; ids.len()];
    for ((&pi, &yi), e) in p.iter().zip(y).zip(episode) {
        let g = ids.binary_search(e).expect("every episode listed");
        let b = ((pi as f64 * bins as f64) as usize).min(bins - 1);
        let s = &mut groups[g][b];
        s.0 += 1.0;
        s.1 += pi as f64;
        s.2 += f64::from(u8::from(yi));
    }
    let ece_of = |sums: &[(f64, f64, f64)]| -> f64 {
        let n: f64 = sums.iter().map(|s| s.0).sum();
        if n == 0.0 {
            return 0.0;
        }
        sums.iter()
            .filter(|s| s.0 > 0.0)
            .map(|s| (s.2 - s.1).abs() / n)
            .sum()
    };
    let sample = ece(p, y, bins);
    let mut rng = StdRng::seed_from_u64(seed);
    let mut values = Vec::with_capacity(resamples);
    let mut acc = vec![(0.0, 0.0, 0.0); bins];
    if !groups.is_empty() {
        for _ in 0..resamples {
            acc.iter_mut().for_each(|s| *s = (0.0, 0.0, 0.0));
            for _ in 0..groups.len() {
                let g = &groups[rng.random_range(0..groups.len())];
                for (a, s) in acc.iter_mut().zip(g) {
                    a.0 += s.0;
                    a.1 += s.1;
                    a.2 += s.2;
                }
            }
            values.push(ece_of(&acc));
        }
    }
    let mut floor = ece_floor(p, episode, bins, resamples, seed.wrapping_add(1));
    EceInterval {
        ece: sample,
        lower: percentile(&mut values, (1.0 - level) / 2.0),
        upper: percentile(&mut values, (1.0 + level) / 2.0),
        level,
        resamples: values.len(),
        episodes: groups.len(),
        floor: floor.iter().sum::<f64>() / floor.len().max(1) as f64,
        floor_upper: percentile(&mut floor, (1.0 + level) / 2.0),
    }
}

/// The `q` quantile (nearest rank) of `values`, sorting them; NaN when empty.
fn percentile(values: &mut [f64], q: f64) -> f64 {
    if values.is_empty() {
        return f64::NAN;
    }
    values.sort_by(f64::total_cmp);
    values[((values.len() - 1) as f64 * q).round() as usize]
}

/// The ECE's noise floor by consistency resampling: `resamples` times, draw
/// each window's label from its own predicted probability (what a perfectly
/// calibrated network's labels would be) and compute the ECE of `p` against
/// them. Returns those ECEs: on a few hundred episodes they are far from 0,
/// so a sample ECE means miscalibration only where it stands above them.
///
/// Windows of one episode with the same probability are one window drawn
/// again (the paper protocol draws an episode's window at its stop line in
/// every draw): they share a drawn label, as they share their true one.
/// Deterministic for `seed`.
pub fn ece_floor(
    p: &[f32],
    episode: &[usize],
    bins: usize,
    resamples: usize,
    seed: u64,
) -> Vec<f64> {
    assert_eq!(p.len(), episode.len(), "one episode per prediction");
    // Each window's distinct window, numbered in order of first appearance.
    let mut seen = std::collections::HashMap::new();
    let distinct: Vec<usize> = p
        .iter()
        .zip(episode)
        .map(|(pi, &e)| {
            let next = seen.len();
            *seen.entry((e, pi.to_bits())).or_insert(next)
        })
        .collect();
    let mut first_p = vec![0.0f32; seen.len()];
    for (&d, &pi) in distinct.iter().zip(p) {
        first_p[d] = pi;
    }
    let mut rng = StdRng::seed_from_u64(seed);
    let mut drawn = vec![false; first_p.len()];
    let mut y = vec![false; p.len()];
    (0..resamples)
        .map(|_| {
            for (d, &pd) in drawn.iter_mut().zip(&first_p) {
                *d = rng.random::<f32>() < pd;
            }
            for (yi, &d) in y.iter_mut().zip(&distinct) {
                *yi = drawn[d];
            }
            ece(p, &y, bins)
        })
        .collect()
}

/// ROC-AUC by the rank statistic (Mann-Whitney U), ties counted half.
pub fn roc_auc(p: &[f32], y: &[bool]) -> f64 {
    let mut idx: Vec<usize> = (0..p.len()).collect();
    idx.sort_by(|&a, &b| p[a].total_cmp(&p[b]));
    let mut ranks = vec![0.0f64; p.len()];
    let mut i = 0;
    while i < idx.len() {
        let mut j = i;
        while j + 1 < idx.len() && p[idx[j + 1]] == p[idx[i]] {
            j += 1;
        }
        let r = (i + j) as f64 / 2.0 + 1.0;
        for k in i..=j {
            ranks[idx[k]] = r;
        }
        i = j + 1;
    }
    let n_pos = y.iter().filter(|&&v| v).count() as f64;
    let n_neg = y.len() as f64 - n_pos;
    if n_pos == 0.0 || n_neg == 0.0 {
        return f64::NAN;
    }
    let sum_pos: f64 = ranks
        .iter()
        .zip(y)
        .filter(|(_, &v)| v)
        .map(|(r, _)| r)
        .sum();
    (sum_pos - n_pos * (n_pos + 1.0) / 2.0) / (n_pos * n_neg)
}

/// ROC curve points `(false positive rate, true positive rate)`, from (0,0) to (1,1).
pub fn roc_curve(p: &[f32], y: &[bool]) -> Vec<(f64, f64)> {
    let mut idx: Vec<usize> = (0..p.len()).collect();
    idx.sort_by(|&a, &b| p[b].total_cmp(&p[a]));
    let n_pos = y.iter().filter(|&&v| v).count().max(1) as f64;
    let n_neg = (y.len() - y.iter().filter(|&&v| v).count()).max(1) as f64;
    let (mut tp, mut fp) = (0.0, 0.0);
    let mut pts = vec![(0.0, 0.0)];
    let mut i = 0;
    while i < idx.len() {
        let t = p[idx[i]];
        while i < idx.len() && p[idx[i]] == t {
            if y[idx[i]] {
                tp += 1.0;
            } else {
                fp += 1.0;
            }
            i += 1;
        }
        pts.push((fp / n_neg, tp / n_pos));
    }
    pts
}

/// Reliability diagram bins: `(mean predicted, fraction positive, count)` per non-empty bin.
pub fn reliability(p: &[f32], y: &[bool], bins: usize) -> Vec<(f64, f64, usize)> {
    let mut count = vec![0usize; bins];
    let mut conf = vec![0.0f64; bins];
    let mut pos = vec![0.0f64; bins];
    for (&pi, &yi) in p.iter().zip(y) {
        let b = ((pi as f64 * bins as f64) as usize).min(bins - 1);
        count[b] += 1;
        conf[b] += pi as f64;
        pos[b] += f64::from(u8::from(yi));
    }
    (0..bins)
        .filter(|&b| count[b] > 0)
        .map(|b| {
            (
                conf[b] / count[b] as f64,
                pos[b] / count[b] as f64,
                count[b],
            )
        })
        .collect()
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn perfect_and_inverted_rankings() {
        let p = [0.1f32, 0.2, 0.8, 0.9];
        let y = [false, false, true, true];
        let m = metrics(&p, &y);
        assert_eq!(
            (m.accuracy, m.f1, m.precision, m.recall, m.roc_auc),
            (1.0, 1.0, 1.0, 1.0, 1.0)
        );
        let inv = [true, true, false, false];
        assert_eq!(roc_auc(&p, &inv), 0.0);
        assert_eq!(metrics(&p, &inv).accuracy, 0.0);
    }

    /// `episodes` episodes of `per_episode` windows; each window's
    /// probability uniform in [0, 1], its label drawn with probability
    /// `truth(p)`.
    fn sample(
        episodes: usize,
        per_episode: usize,
        truth: fn(f64) -> f64,
        seed: u64,
    ) -> (Vec<f32>, Vec<bool>, Vec<usize>) {
        let mut rng = StdRng::seed_from_u64(seed);
        let mut out = (Vec::new(), Vec::new(), Vec::new());
        for e in 0..episodes {
            for _ in 0..per_episode {
                let p: f64 = rng.random();
                out.0.push(p as f32);
                out.1.push(rng.random::<f64>() < truth(p));
                out.2.push(e);
            }
        }
        out
    }

    #[test]
    fn ece_bootstrap_of_a_calibrated_model_reaches_zero_and_covers_the_sample() {
        let (p, y, ep) = sample(2000, 10, |p| p, 1);
        let ci = ece_bootstrap(&p, &y, &ep, 15, 1000, 0.95, 7);
        assert_eq!((ci.resamples, ci.episodes), (1000, 2000));
        assert!(ci.lower <= ci.ece && ci.ece <= ci.upper, "{ci:?}");
        // A calibrated model's ECE is 0 up to sampling noise (with 15 bins
        // and 20000 windows, about 0.01): the interval starts near 0.
        assert!(ci.lower < 0.015, "{ci:?}");
        assert!(ci.upper < 0.03, "{ci:?}");
        // Deterministic for a seed, another seed another interval.
        assert_eq!(ci, ece_bootstrap(&p, &y, &ep, 15, 1000, 0.95, 7));
        assert_ne!(ci, ece_bootstrap(&p, &y, &ep, 15, 1000, 0.95, 8));
    }

    #[test]
    fn ece_bootstrap_of_a_miscalibrated_model_excludes_zero() {
        // True probability p^2: over-confident, ECE about 1/6.
        let (p, y, ep) = sample(300, 4, |p| p * p, 2);
        let ci = ece_bootstrap(&p, &y, &ep, 15, 1000, 0.95, 7);
        assert!(ci.lower <= ci.ece && ci.ece <= ci.upper, "{ci:?}");
        assert!(ci.lower > 0.1, "{ci:?}");
    }

    #[test]
    fn ece_bootstrap_resamples_episodes_not_windows() {
        // Each episode holds one window of each class at p = 0.5: every
        // resample of whole episodes is calibrated, a resample of single
        // windows would not be.
        let p = vec![0.5f32; 200];
        let y: Vec<bool> = (0..200).map(|i| i % 2 == 0).collect();
        let ep: Vec<usize> = (0..200).map(|i| i / 2).collect();
        let ci = ece_bootstrap(&p, &y, &ep, 15, 200, 0.95, 3);
        assert!(ci.upper < 1e-12, "{ci:?}");
    }

    #[test]
    fn the_ece_floor_holds_a_calibrated_sample_and_not_a_miscalibrated_one() {
        // 200 episodes of 5 windows: a calibrated network's ECE is well
        // above 0 there, and its floor says so.
        let (p, y, ep) = sample(200, 5, |p| p, 4);
        let ci = ece_bootstrap(&p, &y, &ep, 15, 1000, 0.95, 7);
        assert!(ci.ece > 0.02, "{ci:?}");
        assert!(ci.floor > 0.02 && ci.floor < ci.floor_upper, "{ci:?}");
        assert!(ci.ece <= ci.floor_upper, "{ci:?}");
        // Over-confident (true probability p^2) on the same windows: above it.
        let (p, y, ep) = sample(200, 5, |p| p * p, 4);
        let ci = ece_bootstrap(&p, &y, &ep, 15, 1000, 0.95, 7);
        assert!(ci.ece > ci.floor_upper, "{ci:?}");
    }

    #[test]
    fn a_window_drawn_again_shares_its_label_in_the_floor() {
        // The same windows each drawn 5 times in their episode: every
        // resampled ECE is the one of the windows drawn once.
        let (p, _, ep) = sample(100, 3, |p| p, 5);
        let once = ece_floor(&p, &ep, 15, 50, 9);
        fn five<T: Copy>(v: &[T]) -> Vec<T> {
            v.iter().flat_map(|&x| [x; 5]).collect()
        }
        let again = ece_floor(&five(&p), &five(&ep), 15, 50, 9);
        for (a, b) in once.iter().zip(&again) {
            assert!((a - b).abs() < 1e-12, "{a} {b}");
        }
        // Drawn independently instead, the repeats would average out: a
        // lower floor.
        let apart: Vec<usize> = (0..p.len() * 5).collect();
        let independent = ece_floor(&five(&p), &apart, 15, 50, 9);
        let mean = |v: &[f64]| v.iter().sum::<f64>() / v.len() as f64;
        assert!(mean(&independent) < mean(&once), "{independent:?}");
    }

    #[test]
    fn auc_counts_ties_half_and_ece_is_calibration_gap() {
        assert_eq!(roc_auc(&[0.5, 0.5], &[true, false]), 0.5);
        // All predictions 0.7, 70% positive: perfectly calibrated.
        let p = [0.7f32; 10];
        let y: Vec<bool> = (0..10).map(|i| i < 7).collect();
        assert!(ece(&p, &y, 15) < 1e-6);
        // All 0.9, none positive: gap 0.9.
        assert!((ece(&[0.9; 4], &[false; 4], 15) - 0.9).abs() < 1e-6);
        let m = metrics(&[0.6, 0.4, 0.7], &[true, true, false]);
        assert!((m.precision - 0.5).abs() < 1e-9 && (m.recall - 0.5).abs() < 1e-9);
    }
}
