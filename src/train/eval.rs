//! Evaluation: per-horizon metrics of one or several model files (seeds) on
//! labelled windows, written as JSON and a Markdown table, plus PNG plots.
//!
//! In: models and [`LabeledWindow`]s (from the data plane's sampler on the
//! test split). Out: an [`EvalReport`] and files under the output directory.

use std::path::Path;

use serde::Serialize;

use super::fit::{LabeledWindow, TrainError};
use super::metrics::{metrics, Metrics};
use crate::model::LoadedModel;

/// Predictions of one model on a set of windows: `[window][horizon]`.
#[derive(Debug, Clone, Serialize)]
pub struct Predictions {
    /// Model file.
    pub model: String,
    /// Probabilities per window and horizon.
    pub probabilities: Vec<Vec<f32>>,
}

/// Mean and standard deviation over seeds (population std; 0 for one seed).
#[derive(Debug, Clone, Copy, Serialize)]
pub struct MeanStd {
    /// Mean.
    pub mean: f64,
    /// Standard deviation.
    pub std: f64,
}

fn mean_std(v: &[f64]) -> MeanStd {
    let v: Vec<f64> = v.iter().copied().filter(|x| x.is_finite()).collect();
    if v.is_empty() {
        return MeanStd {
            mean: f64::NAN,
            std: f64::NAN,
        };
    }
    let m = v.iter().sum::<f64>() / v.len() as f64;
    let var = v.iter().map(|x| (x - m).powi(2)).sum::<f64>() / v.len() as f64;
    MeanStd {
        mean: m,
        std: var.sqrt(),
    }
}

/// Aggregated metrics of one horizon.
#[derive(Debug, Clone, Serialize)]
pub struct HorizonReport {
    /// Horizon, ticks.
    pub horizon_ticks: usize,
    /// Horizon, milliseconds.
    pub horizon_ms: f64,
    /// Per model (seed).
    pub per_model: Vec<Metrics>,
    /// Accuracy over seeds.
    pub accuracy: MeanStd,
    /// F1 over seeds.
    pub f1: MeanStd,
    /// Precision over seeds.
    pub precision: MeanStd,
    /// Recall over seeds.
    pub recall: MeanStd,
    /// ECE over seeds.
    pub ece: MeanStd,
    /// ROC-AUC over seeds.
    pub roc_auc: MeanStd,
    /// Fraction of positive labels.
    pub positive_rate: f64,
}

/// The evaluation report.
#[derive(Debug, Clone, Serialize)]
pub struct EvalReport {
    /// Model files (one per seed).
    pub models: Vec<String>,
    /// Ablation.
    pub ablation: String,
    /// Split evaluated.
    pub split: String,
    /// Number of windows.
    pub windows: usize,
    /// Per horizon.
    pub horizons: Vec<HorizonReport>,
}

/// Runs every model on every window.
pub fn predict(model: &LoadedModel, windows: &[LabeledWindow]) -> Result<Predictions, TrainError> {
    let mut probabilities = Vec::with_capacity(windows.len());
    for w in windows {
        probabilities.push(model.forecast_arrays(&w.joints, &w.plan, &w.frames)?);
    }
    Ok(Predictions {
        model: model.path.display().to_string(),
        probabilities,
    })
}

/// Scores predictions of several models (seeds) against the windows' labels.
pub fn report(
    preds: &[Predictions],
    windows: &[LabeledWindow],
    horizons_ticks: &[usize],
    rate_hz: f64,
    ablation: &str,
    split: &str,
) -> EvalReport {
    let horizons = horizons_ticks
        .iter()
        .enumerate()
        .map(|(k, &h)| {
            let y: Vec<bool> = windows.iter().map(|w| w.labels[k] > 0.5).collect();
            let per_model: Vec<Metrics> = preds
                .iter()
                .map(|p| {
                    let pk: Vec<f32> = p.probabilities.iter().map(|row| row[k]).collect();
                    metrics(&pk, &y)
                })
                .collect();
            let col =
                |f: fn(&Metrics) -> f64| mean_std(&per_model.iter().map(f).collect::<Vec<_>>());
            HorizonReport {
                horizon_ticks: h,
                horizon_ms: h as f64 * 1000.0 / rate_hz,
                accuracy: col(|m| m.accuracy),
                f1: col(|m| m.f1),
                precision: col(|m| m.precision),
                recall: col(|m| m.recall),
                ece: col(|m| m.ece),
                roc_auc: col(|m| m.roc_auc),
                positive_rate: y.iter().filter(|&&v| v).count() as f64 / y.len().max(1) as f64,
                per_model,
            }
        })
        .collect();
    EvalReport {
        models: preds.iter().map(|p| p.model.clone()).collect(),
        ablation: ablation.into(),
        split: split.into(),
        windows: windows.len(),
        horizons,
    }
}

impl EvalReport {
    /// The Markdown table (mean ± std over seeds).
    pub fn markdown(&self) -> String {
        let mut s = format!(
            "# Evaluation: {} on the {} split ({} windows, {} model(s))\n\n",
            self.ablation,
            self.split,
            self.windows,
            self.models.len()
        );
        s.push_str(
            "| horizon | accuracy | F1 | precision | recall | ECE | ROC-AUC | positives |\n",
        );
        s.push_str("| --- | --- | --- | --- | --- | --- | --- | --- |\n");
        let f = |m: MeanStd| format!("{:.3} ± {:.3}", m.mean, m.std);
        for h in &self.horizons {
            s.push_str(&format!(
                "| {} ticks ({:.0} ms) | {} | {} | {} | {} | {} | {} | {:.2} |\n",
                h.horizon_ticks,
                h.horizon_ms,
                f(h.accuracy),
                f(h.f1),
                f(h.precision),
                f(h.recall),
                f(h.ece),
                f(h.roc_auc),
                h.positive_rate
            ));
        }
        s.push_str("\nModels:\n");
        for m in &self.models {
            s.push_str(&format!("- `{m}`\n"));
        }
        s
    }

    /// Writes `metrics.json` and `metrics.md` into `dir`.
    pub fn write(&self, dir: &Path) -> std::io::Result<()> {
        std::fs::create_dir_all(dir)?;
        std::fs::write(
            dir.join("metrics.json"),
            serde_json::to_string_pretty(self).map_err(std::io::Error::other)?,
        )?;
        std::fs::write(dir.join("metrics.md"), self.markdown())
    }
}
