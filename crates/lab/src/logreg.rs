//! The shallow baseline: one logistic regression per horizon on the
//! flattened, standardised joints + plan window (linfa-logistic, L-BFGS).
//!
//! In: the same [`LabeledWindow`]s as the network. Out: a [`LogRegModel`],
//! saved as JSON (`"format": "fall-guard-logreg-v1"`) by `train --ablation logreg`.

use std::path::Path;

use linfa::prelude::*;
use linfa_logistic::LogisticRegression;
use ndarray::{Array1, Array2};
use serde::{Deserialize, Serialize};

use super::fit::LabeledWindow;
use crate::error::TrainError;

const FORMAT: &str = "fall-guard-logreg-v1";

/// A trained baseline.
#[derive(Debug, Clone, Serialize, Deserialize)]
pub struct LogRegModel {
    /// Always `fall-guard-logreg-v1`.
    pub format: String,
    /// Horizons, ticks.
    pub horizons_ticks: Vec<usize>,
    /// Tick rate, Hz.
    pub rate_hz: f64,
    /// Window length, ticks.
    pub n_ticks: usize,
    /// Joint names in model order.
    pub joint_names: Vec<String>,
    /// Per-feature mean (train split).
    pub feature_mean: Vec<f64>,
    /// Per-feature standard deviation (train split).
    pub feature_std: Vec<f64>,
    /// Per horizon: weights (empty when the train split had one class only).
    pub weights: Vec<Vec<f64>>,
    /// Per horizon: intercept (the log-odds of the only class when weights are empty).
    pub intercepts: Vec<f64>,
    /// Where the data came from.
    pub trained_on: String,
}

fn features(w: &LabeledWindow) -> impl Iterator<Item = f64> + '_ {
    w.joints.iter().chain(&w.plan).map(|&v| v as f64)
}

impl LogRegModel {
    /// Fits one regression per horizon (L2 `alpha`, at most 200 iterations).
    pub fn fit(
        windows: &[LabeledWindow],
        horizons_ticks: Vec<usize>,
        rate_hz: f64,
        n_ticks: usize,
        joint_names: Vec<String>,
    ) -> Result<LogRegModel, TrainError> {
        let first = windows
            .first()
            .ok_or_else(|| TrainError::Data("no training windows".into()))?;
        let d = first.joints.len() + first.plan.len();
        let mut x = Array2::<f64>::zeros((windows.len(), d));
        for (i, w) in windows.iter().enumerate() {
            if w.joints.len() + w.plan.len() != d {
                return Err(TrainError::Data(format!(
                    "window {i} has {} features, the first has {d}",
                    w.joints.len() + w.plan.len()
                )));
            }
            for (j, v) in features(w).enumerate() {
                x[[i, j]] = v;
            }
        }
        let mean = x
            .mean_axis(ndarray::Axis(0))
            .unwrap_or_else(|| Array1::zeros(d));
        let std = x.std_axis(ndarray::Axis(0), 0.0).mapv(|s| s.max(1e-6));
        let xs = (&x - &mean) / &std;
        let mut weights = Vec::new();
        let mut intercepts = Vec::new();
        for (k, &horizon) in horizons_ticks.iter().enumerate() {
            // The windows scored at this horizon (all of them, except under
            // the paper protocol: those drawn for it).
            let rows: Vec<usize> = (0..windows.len())
                .filter(|&i| windows[i].scores(k))
                .collect();
            let y: Array1<bool> = rows.iter().map(|&i| windows[i].labels[k] > 0.5).collect();
            let positives = y.iter().filter(|&&v| v).count();
            if positives == 0 || positives == y.len() {
                // One class only: a constant prediction (clamped log-odds).
                weights.push(Vec::new());
                intercepts.push(if positives == 0 { -10.0 } else { 10.0 });
                continue;
            }
            let ds = Dataset::new(xs.select(ndarray::Axis(0), &rows), y);
            let fitted = LogisticRegression::default()
                .alpha(1.0)
                .max_iterations(200)
                .fit(&ds)
                .map_err(|e| {
                    TrainError::Data(format!("logistic regression at horizon {}: {e}", horizon))
                })?;
            // linfa's probabilities are of its "positive" class; make them P(fallen).
            let sign = if fitted.labels().pos.class { 1.0 } else { -1.0 };
            weights.push(fitted.params().iter().map(|w| sign * w).collect());
            intercepts.push(sign * fitted.intercept());
        }
        Ok(LogRegModel {
            format: FORMAT.into(),
            horizons_ticks,
            rate_hz,
            n_ticks,
            joint_names,
            feature_mean: mean.to_vec(),
            feature_std: std.to_vec(),
            weights,
            intercepts,
            trained_on: String::new(),
        })
    }

    /// Probabilities per horizon for one window.
    pub fn predict(&self, w: &LabeledWindow) -> Result<Vec<f32>, TrainError> {
        let d = self.feature_mean.len();
        let xs: Vec<f64> = features(w).collect();
        if xs.len() != d {
            return Err(TrainError::Data(format!(
                "window has {} features, the baseline needs {d}",
                xs.len()
            )));
        }
        let z: Vec<f64> = xs
            .iter()
            .zip(&self.feature_mean)
            .zip(&self.feature_std)
            .map(|((x, m), s)| (x - m) / s)
            .collect();
        Ok(self
            .weights
            .iter()
            .zip(&self.intercepts)
            .map(|(wk, b)| {
                let logit = b + wk.iter().zip(&z).map(|(a, x)| a * x).sum::<f64>();
                (1.0 / (1.0 + (-logit).exp())) as f32
            })
            .collect())
    }

    /// Writes the model as JSON (as `NAME.partial`, then renamed).
    pub fn save(&self, path: &Path) -> Result<(), TrainError> {
        let s = serde_json::to_string(self).map_err(|e| TrainError::Data(e.to_string()))?;
        super::checkpoint::write_atomically(path, s.as_bytes())
    }

    /// Reads a model written by [`save`](Self::save); `None` if the file is not one.
    pub fn load(path: &Path) -> Result<Option<LogRegModel>, TrainError> {
        let bytes = std::fs::read(path)
            .map_err(|e| TrainError::Data(format!("reading {}: {e}", path.display())))?;
        if !bytes.starts_with(b"{") {
            return Ok(None);
        }
        let m: LogRegModel = serde_json::from_slice(&bytes)
            .map_err(|e| TrainError::Data(format!("{}: {e}", path.display())))?;
        if m.format != FORMAT {
            return Err(TrainError::Data(format!(
                "{}: format {:?}, expected {FORMAT}",
                path.display(),
                m.format
            )));
        }
        Ok(Some(m))
    }
}
