//! Evaluation: per-horizon metrics of one or several model files (seeds) on
//! labelled windows, written as JSON and a Markdown table, plus PNG plots.
//!
//! In: models and [`LabeledWindow`]s (from the data plane's sampler on the
//! test split, built and forecast a batch at a time), once per sampling
//! protocol; the windows' truths ([`WindowTruth`]) and the probabilities are
//! what is kept. Out: an [`EvalReport`] with one
//! [`ProtocolReport`] per protocol (deployment and paper, both always) and
//! files under the output directory. Horizon `k` is scored on the windows
//! that score it ([`WindowTruth::scores`]): all of them under the
//! deployment protocol, horizon `k`'s own set under the paper's. The ECE
//! comes with a 95% bootstrap interval that resamples episodes and with its
//! noise floor: the ECE a perfectly calibrated network shows on the same
//! windows.

use std::path::Path;

use serde::Serialize;

use super::fit::{LabeledWindow, WindowTruth};
use super::metrics::{ece_bootstrap, metrics, EceInterval, Metrics};
use super::sampler::Protocol;
use crate::error::TrainError;
use fall_guard_runtime::model::LoadedModel;

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
    /// Per model (seed): 95% bootstrap interval of the ECE, resampling
    /// episodes ([`ECE_RESAMPLES`] resamples).
    pub ece_ci95: Vec<EceInterval>,
    /// ROC-AUC over seeds.
    pub roc_auc: MeanStd,
    /// Windows scored at this horizon.
    pub windows: usize,
    /// Fraction of positive labels.
    pub positive_rate: f64,
}

/// Resamples of the ECE bootstrap.
pub const ECE_RESAMPLES: usize = 1000;

/// The metrics of one sampling protocol.
#[derive(Debug, Clone, Serialize)]
pub struct ProtocolReport {
    /// `deployment` or `paper`.
    pub protocol: String,
    /// How its windows are drawn.
    pub description: String,
    /// Number of windows (paper: all horizons' sets together).
    pub windows: usize,
    /// Per horizon.
    pub horizons: Vec<HorizonReport>,
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
    /// The protocol of `windows`, `horizons` and the plots (`eval --protocol`).
    pub protocol: String,
    /// Number of windows of `protocol`.
    pub windows: usize,
    /// Per horizon, under `protocol` (a copy of its entry in `protocols`).
    pub horizons: Vec<HorizonReport>,
    /// Every protocol, `protocol` first.
    pub protocols: Vec<ProtocolReport>,
}

/// Runs every model on every window.
pub fn predict(model: &LoadedModel, windows: &[LabeledWindow]) -> Result<Predictions, TrainError> {
    let mut probabilities = Vec::with_capacity(windows.len());
    for w in windows {
        probabilities.push(model.forecast_arrays(&w.joints, &w.plan, &w.frames)?);
    }
    Ok(Predictions {
        model: crate::dataset::data_name(&model.path),
        probabilities,
    })
}

/// Scores predictions of several models (seeds) against the windows' labels
/// under `protocol`: horizon `k` on the windows that score it. `seed` makes
/// the ECE bootstrap deterministic.
pub fn report(
    preds: &[Predictions],
    windows: &[WindowTruth],
    horizons_ticks: &[usize],
    rate_hz: f64,
    protocol: Protocol,
    seed: u64,
) -> ProtocolReport {
    let horizons = horizons_ticks
        .iter()
        .enumerate()
        .map(|(k, &h)| {
            let scored: Vec<usize> = (0..windows.len())
                .filter(|&i| windows[i].scores(k))
                .collect();
            let y: Vec<bool> = scored.iter().map(|&i| windows[i].labels[k] > 0.5).collect();
            let episodes: Vec<usize> = scored.iter().map(|&i| windows[i].episode).collect();
            let column = |p: &Predictions| -> Vec<f32> {
                scored.iter().map(|&i| p.probabilities[i][k]).collect()
            };
            let per_model: Vec<Metrics> = preds.iter().map(|p| metrics(&column(p), &y)).collect();
            let ece_ci95 = preds
                .iter()
                .map(|p| {
                    ece_bootstrap(
                        &column(p),
                        &y,
                        &episodes,
                        15,
                        ECE_RESAMPLES,
                        0.95,
                        seed ^ h as u64,
                    )
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
                ece_ci95,
                roc_auc: col(|m| m.roc_auc),
                windows: y.len(),
                positive_rate: y.iter().filter(|&&v| v).count() as f64 / y.len().max(1) as f64,
                per_model,
            }
        })
        .collect();
    ProtocolReport {
        protocol: protocol.name().into(),
        description: protocol.description().into(),
        windows: windows.len(),
        horizons,
    }
}

impl EvalReport {
    /// The report of `models` with one section per protocol, the first the
    /// primary one.
    pub fn new(
        models: Vec<String>,
        ablation: &str,
        split: &str,
        protocols: Vec<ProtocolReport>,
    ) -> EvalReport {
        let primary = protocols.first();
        EvalReport {
            models,
            ablation: ablation.into(),
            split: split.into(),
            protocol: primary.map(|p| p.protocol.clone()).unwrap_or_default(),
            windows: primary.map_or(0, |p| p.windows),
            horizons: primary.map(|p| p.horizons.clone()).unwrap_or_default(),
            protocols,
        }
    }

    /// The Markdown report: one table per protocol (mean ± std over seeds;
    /// the ECE interval is the first model's).
    pub fn markdown(&self) -> String {
        let mut s = format!(
            "# Evaluation: {} on the {} split ({} model(s))\n",
            self.ablation,
            self.split,
            self.models.len()
        );
        let f = |m: MeanStd| format!("{:.3} ± {:.3}", m.mean, m.std);
        for p in &self.protocols {
            s.push_str(&format!(
                "\n## Protocol: {} ({} windows)\n\n{}.\n\n",
                p.protocol, p.windows, p.description
            ));
            s.push_str(
                "| horizon | accuracy | F1 | precision | recall | ECE | ECE 95% CI | ECE floor | ROC-AUC | windows | positives |\n",
            );
            s.push_str("| --- | --- | --- | --- | --- | --- | --- | --- | --- | --- | --- |\n");
            for h in &p.horizons {
                let (ci, floor) = h
                    .ece_ci95
                    .first()
                    .map(|c| {
                        (
                            format!("[{:.3}, {:.3}]", c.lower, c.upper),
                            format!("{:.3} (97.5%: {:.3})", c.floor, c.floor_upper),
                        )
                    })
                    .unwrap_or_default();
                s.push_str(&format!(
                    "| {} ticks ({:.0} ms) | {} | {} | {} | {} | {} | {} | {} | {} | {} | {:.2} |\n",
                    h.horizon_ticks,
                    h.horizon_ms,
                    f(h.accuracy),
                    f(h.f1),
                    f(h.precision),
                    f(h.recall),
                    f(h.ece),
                    ci,
                    floor,
                    f(h.roc_auc),
                    h.windows,
                    h.positive_rate
                ));
            }
        }
        s.push_str(&format!(
            "\nECE 95% CI: percentile bootstrap over episodes, {ECE_RESAMPLES} resamples. ECE floor: the ECE a perfectly calibrated network shows on these windows (labels drawn from the probabilities, {ECE_RESAMPLES} times), mean and 97.5th percentile; an ECE above that percentile shows miscalibration. First model; every model's in metrics.json.\n\nModels:\n"
        ));
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
