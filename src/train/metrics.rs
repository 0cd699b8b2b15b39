//! The paper's metrics, per horizon: accuracy, F1, precision, recall,
//! expected calibration error (15 equal-width bins) and ROC-AUC.
//!
//! In: predicted probabilities and 0/1 labels of one horizon. Out: [`Metrics`].

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
    let mut count = vec![0usize; bins];
    let mut conf = vec![0.0f64; bins];
    let mut pos = vec![0.0f64; bins];
    for (&pi, &yi) in p.iter().zip(y) {
        let b = ((pi as f64 * bins as f64) as usize).min(bins - 1);
        count[b] += 1;
        conf[b] += pi as f64;
        pos[b] += f64::from(u8::from(yi));
    }
    let n = p.len().max(1) as f64;
    (0..bins)
        .filter(|&b| count[b] > 0)
        .map(|b| count[b] as f64 / n * (pos[b] / count[b] as f64 - conf[b] / count[b] as f64).abs())
        .sum()
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
