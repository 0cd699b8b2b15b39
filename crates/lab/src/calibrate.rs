//! `fall-guard-lab calibrate`: post-hoc calibration of a trained network on
//! held-out windows (per horizon, shortest first, Platt scaling or beta
//! calibration, whichever cross-validates better on those windows; each
//! fitted for the probability as published: above the running maximum of
//! the shorter horizons).
//!
//! In: a model file, a data set and a split that the network was not trained
//! on (validation by default). Out: the same model file with a
//! [`Calibration`] in its metadata, which the daemon, `eval` and `warnings`
//! apply to every forecast. Fitted on validation, judged on test.

use std::path::PathBuf;

use crate::error::{refused, CommandResult, Doing};

use super::commands::{needs_of_model, SplitWindows, EVAL_BATCH};
use super::dataset::{data_name, Dataset, Split};
use super::fit::for_each_batch;
use super::metrics::ece;
use super::sampler::Protocol;
use fall_guard_runtime::model::file::{load_emp, sigmoid};
use fall_guard_runtime::model::{Calibration, LoadedModel, WeightPrecision};

/// Arguments of `fall-guard-lab calibrate`.
#[derive(Debug, Clone)]
pub struct CalibrateOptions {
    /// Model file to calibrate (a network; any calibration it has is replaced).
    pub model: PathBuf,
    /// Data set directory.
    pub data: PathBuf,
    /// Split to fit on: never the one the model is judged on.
    pub split: String,
    /// Windows drawn per episode (each an independent draw).
    pub draws: usize,
    /// Seed of the window sampler.
    pub sample_seed: u64,
    /// How the fitting windows are drawn: `deployment` or `paper` (each
    /// horizon fitted on its own balanced set); see `train --protocol`.
    pub protocol: Protocol,
    /// Output model file (may be the input).
    pub out: PathBuf,
    /// Store the weights in half precision (f16).
    pub half: bool,
    /// The form of the map at each horizon.
    pub form: FormChoice,
}

/// The form of one horizon's calibration map (see [`Calibration`]).
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum CalibrationForm {
    /// `sigmoid(a·z + b)`: one slope.
    Platt,
    /// `sigmoid(a·softplus(z) - c·softplus(-z) + b)`: a slope per side of
    /// the logit.
    Beta,
}

impl CalibrationForm {
    /// The form's name, as `calibrate --form` takes it.
    pub fn name(self) -> &'static str {
        match self {
            CalibrationForm::Platt => "platt",
            CalibrationForm::Beta => "beta",
        }
    }
}

/// Which form `calibrate` fits at each horizon.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Default)]
pub enum FormChoice {
    /// The form with the lower cross-validated loss on the fitting windows
    /// (folds by episode, [`CV_FOLDS`] of them): beta calibration only
    /// where its extra slope pays on windows it was not fitted on.
    #[default]
    Auto,
    /// One form at every horizon.
    Fixed(CalibrationForm),
}

/// Folds of the cross-validation that chooses the form ([`FormChoice::Auto`]).
pub const CV_FOLDS: usize = 5;

/// A fitted map: `(a, c, b)` with `c = a` under Platt scaling.
type Map = (f32, f32, f32);

/// Fits `sigmoid(a·z + b)` to labels `y` by Newton's method on the mean
/// binary cross-entropy (Platt scaling), with a small ridge pulling towards
/// the identity `(1, 0)` so that a separable or one-class sample still gives
/// a finite answer. Returns `(a, b)`.
pub fn fit_platt(z: &[f32], y: &[bool]) -> (f32, f32) {
    let (a, _, b) = fit_above(CalibrationForm::Platt, z, y, &vec![0.0; z.len()]);
    (a, b)
}

/// [`fit_platt`] for the probability as it is applied: `max(floor_i,
/// sigmoid(a·z_i + b))`, where `floor_i` is what the shorter horizons
/// already give window `i` (the running maximum of [`Calibration::apply`]).
/// Where the floor stands above the fitted term, `(a, b)` do not change that
/// window's probability, so it adds nothing to the gradient. Starts from
/// the fit without floors and accepts only steps that lower the loss, so
/// the result is never worse than that fit on the applied probabilities.
/// With every floor 0 it is [`fit_platt`].
pub fn fit_platt_above(z: &[f32], y: &[bool], floor: &[f32]) -> (f32, f32) {
    let (a, _, b) = fit_above(CalibrationForm::Platt, z, y, floor);
    (a, b)
}

/// Fits one horizon's map of `form` for the probability as applied, above
/// `floor` (see [`fit_platt_above`]). Beta calibration starts from the Platt
/// fit (its special case), so on the fitting windows it is never worse.
/// Returns `(a, c, b)`.
pub fn fit_above(form: CalibrationForm, z: &[f32], y: &[bool], floor: &[f32]) -> Map {
    assert!(
        z.len() == y.len() && z.len() == floor.len(),
        "one label and one floor per logit"
    );
    let none = vec![0.0f32; z.len()];
    let floored = floor.iter().any(|&f| f > 0.0);
    match form {
        CalibrationForm::Platt => {
            let x: Vec<[f64; 2]> = z.iter().map(|&z| [f64::from(z), 1.0]).collect();
            let plain = newton(&x, y, &none, [1.0, 0.0], [1.0, 0.0]);
            let [a, b] = if floored {
                newton(&x, y, floor, plain, [1.0, 0.0])
            } else {
                plain
            };
            (a as f32, a as f32, b as f32)
        }
        CalibrationForm::Beta => {
            let platt = fit_above(CalibrationForm::Platt, z, y, floor);
            fit_beta_from(platt, z, y, floor)
        }
    }
}

/// Beta calibration above `floor`, Newton's method from the Platt fit
/// `platt` (its special case `c = a`).
fn fit_beta_from(platt: Map, z: &[f32], y: &[bool], floor: &[f32]) -> Map {
    let (a, _, b) = platt;
    let x: Vec<[f64; 3]> = z
        .iter()
        .map(|&z| {
            let z = f64::from(z);
            [softplus64(z), -softplus64(-z), 1.0]
        })
        .collect();
    let start = [f64::from(a), f64::from(a), f64::from(b)];
    let [a, c, b] = newton(&x, y, floor, start, [1.0, 1.0, 0.0]);
    (a as f32, c as f32, b as f32)
}

/// `ln(1 + e^s)`, stable.
fn softplus64(s: f64) -> f64 {
    if s > 0.0 {
        s + (-s).exp().ln_1p()
    } else {
        s.exp().ln_1p()
    }
}

fn sigmoid64(s: f64) -> f64 {
    if s >= 0.0 {
        1.0 / (1.0 + (-s).exp())
    } else {
        let e = s.exp();
        e / (1.0 + e)
    }
}

/// The smallest logit scale a fit takes.
const MIN_SCALE: f64 = 1e-3;

/// Newton's method with backtracking on the ridge-regularised mean
/// cross-entropy of `max(floor_i, sigmoid(w·x_i))`, from `start`, the ridge
/// pulling towards `centre` (the identity map). Every weight but the last
/// (the bias) is a scale, kept at or above [`MIN_SCALE`] so that the map
/// keeps the network's order.
fn newton<const D: usize>(
    x: &[[f64; D]],
    y: &[bool],
    floor: &[f32],
    start: [f64; D],
    centre: [f64; D],
) -> [f64; D] {
    const RIDGE: f64 = 1e-3;
    let n = x.len().max(1) as f64;
    let dot = |w: &[f64; D], xi: &[f64; D]| w.iter().zip(xi).map(|(a, b)| a * b).sum::<f64>();
    let loss = |w: &[f64; D]| -> f64 {
        let mut l = 0.0;
        for ((xi, &yi), &fi) in x.iter().zip(y).zip(floor) {
            let s = dot(w, xi);
            let fi = f64::from(fi);
            if fi > 0.0 && sigmoid64(s) < fi {
                // The floor is the probability: -log p or -log(1 - p).
                let p = fi.clamp(1e-7, 1.0 - 1e-7);
                l -= if yi { p.ln() } else { (1.0 - p).ln() };
                continue;
            }
            l += softplus64(s) - if yi { s } else { 0.0 };
        }
        let ridge: f64 = w.iter().zip(&centre).map(|(w, c)| (w - c).powi(2)).sum();
        l / n + 0.5 * RIDGE * ridge
    };
    let mut w = start;
    let mut current = loss(&w);
    for _ in 0..100 {
        let mut g = [0.0f64; D];
        let mut h = [[0.0f64; D]; D];
        for ((xi, &yi), &fi) in x.iter().zip(y).zip(floor) {
            let p = sigmoid64(dot(&w, xi));
            if p < f64::from(fi) {
                continue;
            }
            let r = p - if yi { 1.0 } else { 0.0 };
            let v = (p * (1.0 - p)).max(1e-12);
            for i in 0..D {
                g[i] += r * xi[i];
                for j in 0..D {
                    h[i][j] += v * xi[i] * xi[j];
                }
            }
        }
        for i in 0..D {
            g[i] = g[i] / n + RIDGE * (w[i] - centre[i]);
            for hij in h[i].iter_mut() {
                *hij /= n;
            }
            h[i][i] += RIDGE;
        }
        let Some(step) = solve(h, g) else { break };
        // Backtracking: never accept a step that raises the loss, nor one
        // that turns a scale below MIN_SCALE (a calibration keeps the
        // network's order).
        let mut t = 1.0;
        let mut improved = false;
        while t > 1e-6 {
            let mut next = w;
            for i in 0..D {
                next[i] -= t * step[i];
            }
            if next[..D - 1].iter().any(|&a| a < MIN_SCALE) {
                t *= 0.5;
                continue;
            }
            let l = loss(&next);
            if l <= current {
                improved = current - l > 1e-12;
                (w, current) = (next, l);
                break;
            }
            t *= 0.5;
        }
        if !improved || step.iter().map(|s| s.abs()).sum::<f64>() * t < 1e-9 {
            break;
        }
    }
    w
}

/// Solves `h·s = g` by Gaussian elimination with partial pivoting; none
/// when `h` is singular.
fn solve<const D: usize>(mut h: [[f64; D]; D], mut g: [f64; D]) -> Option<[f64; D]> {
    for col in 0..D {
        let pivot = (col..D).max_by(|&i, &j| h[i][col].abs().total_cmp(&h[j][col].abs()))?;
        if h[pivot][col].abs() < 1e-18 {
            return None;
        }
        h.swap(col, pivot);
        g.swap(col, pivot);
        for row in col + 1..D {
            let f = h[row][col] / h[col][col];
            let pivot_row = h[col];
            for (hk, pk) in h[row].iter_mut().zip(pivot_row).skip(col) {
                *hk -= f * pk;
            }
            g[row] -= f * g[col];
        }
    }
    let mut s = [0.0f64; D];
    for row in (0..D).rev() {
        let rest: f64 = (row + 1..D).map(|k| h[row][k] * s[k]).sum();
        s[row] = (g[row] - rest) / h[row][row];
    }
    Some(s)
}

/// Mean cross-entropy of the applied probabilities `max(floor_i, map(z_i))`.
fn applied_nll(map: Map, z: &[f32], y: &[bool], floor: &[f32]) -> f64 {
    let (a, c, b) = map;
    let n = z.len().max(1) as f64;
    z.iter()
        .zip(y)
        .zip(floor)
        .map(|((&z, &y), &f)| {
            let z = f64::from(z);
            let s = f64::from(a) * softplus64(z) - f64::from(c) * softplus64(-z) + f64::from(b);
            let p = sigmoid64(s).max(f64::from(f)).clamp(1e-7, 1.0 - 1e-7);
            -if y { p.ln() } else { (1.0 - p).ln() }
        })
        .sum::<f64>()
        / n
}

/// Cross-validated loss of Platt scaling and of beta calibration on one
/// horizon's windows: each of [`CV_FOLDS`] folds (by episode, so that the
/// draws of one episode stay together) is scored by the maps fitted on the
/// others (beta calibration from that fold's Platt fit, as [`fit_above`]
/// does). Returns the mean cross-entropy over all windows of each.
fn cross_validated_nll(z: &[f32], y: &[bool], floor: &[f32], episode: &[usize]) -> (f64, f64) {
    let (mut platt_total, mut beta_total) = (0.0, 0.0);
    for fold in 0..CV_FOLDS {
        let pick = |held: bool| {
            let idx: Vec<usize> = (0..z.len())
                .filter(|&i| (episode[i] % CV_FOLDS == fold) == held)
                .collect();
            (
                idx.iter().map(|&i| z[i]).collect::<Vec<f32>>(),
                idx.iter().map(|&i| y[i]).collect::<Vec<bool>>(),
                idx.iter().map(|&i| floor[i]).collect::<Vec<f32>>(),
            )
        };
        let (tz, ty, tf) = pick(false);
        let (hz, hy, hf) = pick(true);
        if hz.is_empty() {
            continue;
        }
        let platt = fit_above(CalibrationForm::Platt, &tz, &ty, &tf);
        let beta = fit_beta_from(platt, &tz, &ty, &tf);
        platt_total += applied_nll(platt, &hz, &hy, &hf) * hz.len() as f64;
        beta_total += applied_nll(beta, &hz, &hy, &hf) * hz.len() as f64;
    }
    let n = z.len().max(1) as f64;
    (platt_total / n, beta_total / n)
}

/// What calibration did to one horizon of the fitting split.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct HorizonFit {
    /// Horizon, ms.
    pub horizon_ms: u32,
    /// The form fitted.
    pub form: CalibrationForm,
    /// Fitted logit scale (of the positive side, under beta calibration).
    pub scale: f32,
    /// Fitted scale of the negative side (`scale` under Platt scaling).
    pub neg_scale: f32,
    /// Fitted logit offset.
    pub bias: f32,
    /// Cross-validated cross-entropy of Platt scaling and of beta
    /// calibration, when the form was chosen by it.
    pub cv_nll: Option<(f64, f64)>,
    /// ECE (15 bins) before, on the fitting windows.
    pub ece_before: f64,
    /// ECE after, on the fitting windows (with the running maximum).
    pub ece_after: f64,
    /// ECE of this horizon's own map alone, on the fitting windows (without
    /// the running maximum): what the maximum costs is the difference.
    pub ece_own: f64,
    /// Share of the fitting windows on which a shorter horizon's
    /// probability stands above this horizon's own (the maximum decides).
    pub held_by_shorter: f64,
}

/// Fits a [`Calibration`] per horizon to `logits` (one row of `K` per
/// window) and their labels (one row of `K` per window). `scored[i]`:
/// `Some(k)` when window `i` counts for horizon `k` only (paper protocol),
/// `None` when it counts for all; `episode[i]`: the episode window `i` was
/// drawn from (the folds of [`FormChoice::Auto`]).
pub fn fit_calibration(
    logits: &[Vec<f32>],
    labels: &[Vec<bool>],
    scored: &[Option<usize>],
    episode: &[usize],
    horizons_ms: &[u32],
    choice: FormChoice,
    fitted_on: String,
) -> (Calibration, Vec<HorizonFit>) {
    let k = horizons_ms.len();
    let mut cal = Calibration::identity(k);
    cal.neg_scale = Some(vec![1.0; k]);
    cal.fitted_on = fitted_on;
    let rows = |h: usize| (0..logits.len()).filter(move |&i| scored[i].is_none_or(|s| s == h));
    let mut forms = Vec::with_capacity(k);
    // Shortest horizon first: each is fitted for the probability applied,
    // above the running maximum of the shorter ones as already fitted.
    for h in 0..k {
        let z: Vec<f32> = rows(h).map(|i| logits[i][h]).collect();
        let y: Vec<bool> = rows(h).map(|i| labels[i][h]).collect();
        let floor: Vec<f32> = rows(h)
            .map(|i| h.checked_sub(1).map_or(0.0, |k| cal.apply(&logits[i])[k]))
            .collect();
        let (form, cv) = match choice {
            FormChoice::Fixed(form) => (form, None),
            FormChoice::Auto => {
                let ep: Vec<usize> = rows(h).map(|i| episode[i]).collect();
                let (platt, beta) = cross_validated_nll(&z, &y, &floor, &ep);
                let form = if beta < platt {
                    CalibrationForm::Beta
                } else {
                    CalibrationForm::Platt
                };
                (form, Some((platt, beta)))
            }
        };
        let (a, c, b) = fit_above(form, &z, &y, &floor);
        cal.scale[h] = a;
        cal.bias[h] = b;
        if let Some(neg) = cal.neg_scale.as_mut() {
            neg[h] = c;
        }
        forms.push((form, cv));
    }
    if !cal.is_beta() {
        // Platt at every horizon: stored as such (`a·z + b`).
        cal.neg_scale = None;
    }
    let before: Vec<Vec<f32>> = logits
        .iter()
        .map(|r| r.iter().map(|&z| sigmoid(z)).collect())
        .collect();
    let after: Vec<Vec<f32>> = logits.iter().map(|r| cal.apply(r)).collect();
    let own: Vec<Vec<f32>> = logits
        .iter()
        .map(|r| (0..k).map(|h| sigmoid(cal.logit(h, r[h]))).collect())
        .collect();
    let forms_named: Vec<&str> = forms.iter().map(|(f, _)| f.name()).collect();
    cal.fitted_on = format!(
        "{}; forms {} ({})",
        cal.fitted_on,
        forms_named.join(" / "),
        match choice {
            FormChoice::Auto => "chosen by cross-validation",
            FormChoice::Fixed(_) => "as asked",
        }
    );
    let fits = (0..k)
        .map(|h| {
            let y: Vec<bool> = rows(h).map(|i| labels[i][h]).collect();
            let col = |p: &[Vec<f32>]| rows(h).map(|i| p[i][h]).collect::<Vec<f32>>();
            HorizonFit {
                horizon_ms: horizons_ms[h],
                form: forms[h].0,
                scale: cal.scale[h],
                neg_scale: cal.neg_scale.as_ref().map_or(cal.scale[h], |c| c[h]),
                bias: cal.bias[h],
                cv_nll: forms[h].1,
                ece_before: ece(&col(&before), &y, 15),
                ece_after: ece(&col(&after), &y, 15),
                ece_own: ece(&col(&own), &y, 15),
                held_by_shorter: rows(h).filter(|&i| after[i][h] > own[i][h]).count() as f64
                    / y.len().max(1) as f64,
            }
        })
        .collect();
    (cal, fits)
}

/// What `fall-guard-lab calibrate` fitted: per horizon, the map and its
/// figures on the fitting split.
#[derive(Debug, Clone)]
pub struct CalibrateReport {
    /// The split fitted on.
    pub split: Split,
    /// Per horizon, shortest first.
    pub fits: Vec<HorizonFit>,
}

impl CalibrateReport {
    /// The fits as a Markdown table.
    pub fn table(&self) -> String {
        let mut t = format!(
            "| horizon | form | scale | negative-side scale | bias | CV loss Platt | CV loss beta | ECE before ({}) | ECE after | ECE of its own map | held by a shorter horizon |\n| --- | --- | --- | --- | --- | --- | --- | --- | --- | --- | --- |\n",
            self.split.name()
        );
        for f in &self.fits {
            let (platt, beta) = f.cv_nll.map_or(("-".into(), "-".into()), |(p, b)| {
                (format!("{p:.4}"), format!("{b:.4}"))
            });
            t += &format!(
                "| {} ms | {} | {:.3} | {:.3} | {:.3} | {platt} | {beta} | {:.4} | {:.4} | {:.4} | {:.1}% |\n",
                f.horizon_ms,
                f.form.name(),
                f.scale,
                f.neg_scale,
                f.bias,
                f.ece_before,
                f.ece_after,
                f.ece_own,
                100.0 * f.held_by_shorter
            );
        }
        t
    }
}

/// Runs `fall-guard-lab calibrate`: writes the calibrated model file and
/// returns the fits (a table the binary prints).
pub fn run_calibrate(args: &CalibrateOptions) -> CommandResult<CalibrateReport> {
    let split: Split = args.split.parse().map_err(refused)?;
    if split == Split::Train {
        return Err(refused(
            "--split train: calibrate on windows the network was not trained on (validation)",
        ));
    }
    // One read of the file: the trainable network is what gets written back.
    let device = fall_guard_runtime::model::cpu_device();
    let (meta, emp) = load_emp(&args.model, &device).doing(|| {
        format!(
            "reading {} (calibrate takes a network model file, not the logistic baseline)",
            args.model.display()
        )
    })?;
    let model = LoadedModel::from_parts(meta, &emp, device, args.model.clone());
    let meta = &model.meta;
    let dataset =
        Dataset::open(&args.data).doing(|| format!("opening data set {}", args.data.display()))?;
    let mut windows = SplitWindows::load(
        &dataset,
        split,
        &meta.window_spec(),
        needs_of_model(meta),
        &meta.horizons_ticks,
        args.sample_seed,
        args.protocol,
    )?;
    let (mut logits, mut labels, mut scored, mut episode) =
        (Vec::new(), Vec::new(), Vec::new(), Vec::new());
    // Built a batch at a time: only the logits and labels stay.
    for _ in 0..args.draws.max(1) {
        for_each_batch(&windows.epoch(), EVAL_BATCH, true, |batch| {
            for w in batch {
                logits.push(model.logits_arrays(&w.joints, &w.plan, &w.frames)?);
                labels.push(w.labels.iter().map(|&l| l > 0.5).collect::<Vec<bool>>());
                scored.push(w.scored_horizon);
                episode.push(w.episode);
            }
            Ok(())
        })?;
    }
    if logits.is_empty() {
        return Err(refused(format!(
            "the {} split of {} has no usable window",
            split.name(),
            args.data.display()
        )));
    }
    let fitted_on = format!(
        "{} split of {}, {} windows ({} draws per episode, sampler seed {}, {} protocol)",
        split.name(),
        data_name(&args.data),
        logits.len(),
        args.draws.max(1),
        args.sample_seed,
        args.protocol
    );
    let (cal, fits) = fit_calibration(
        &logits,
        &labels,
        &scored,
        &episode,
        &meta.horizons_ms(),
        args.form,
        fitted_on,
    );
    let mut meta = model.meta.clone();
    meta.calibration = Some(cal);
    let precision = if args.half {
        WeightPrecision::Half
    } else {
        WeightPrecision::Full
    };
    fall_guard_runtime::model::save_model_as(&args.out, &meta, &emp, precision)
        .doing(|| format!("writing {}", args.out.display()))?;
    LoadedModel::load(&args.out).doing(|| format!("reading back {}", args.out.display()))?;
    tracing::info!("calibrated model written to {}", args.out.display());
    Ok(CalibrateReport { split, fits })
}

#[cfg(test)]
mod tests {
    use super::*;
    use fall_guard_runtime::model::file::softplus;

    /// Logits of a miscalibrated model: the truth is `sigmoid(a·z + b)`.
    fn sample(a: f32, b: f32, n: usize) -> (Vec<f32>, Vec<bool>) {
        let mut state = 0x9e37_79b9_7f4a_7c15u64;
        let mut uniform = || {
            state ^= state << 13;
            state ^= state >> 7;
            state ^= state << 17;
            (state >> 11) as f64 / (1u64 << 53) as f64
        };
        (0..n)
            .map(|_| {
                let z = (uniform() * 8.0 - 4.0) as f32;
                let y = uniform() < f64::from(sigmoid(a * z + b));
                (z, y)
            })
            .unzip()
    }

    #[test]
    fn platt_recovers_a_known_miscalibration() {
        let (z, y) = sample(0.5, -0.7, 20_000);
        let (a, b) = fit_platt(&z, &y);
        assert!((a - 0.5).abs() < 0.05, "scale {a}");
        assert!((b + 0.7).abs() < 0.07, "bias {b}");
    }

    #[test]
    fn windows_under_the_floor_do_not_bend_the_fit() {
        // Calibrated windows, and windows the shorter horizons already give
        // 0.97, all positive at a low logit: fitted alone, those bend the
        // line; fitted above the floor, they leave it where it belongs.
        let (mut z, mut y) = sample(1.0, 0.0, 10_000);
        let mut floor = vec![0.0f32; z.len()];
        z.extend([-3.0f32; 3000]);
        y.extend([true; 3000]);
        floor.extend([0.97f32; 3000]);
        let plain = fit_platt(&z, &y);
        let above = fit_platt_above(&z, &y, &floor);
        assert!(
            (above.0 - 1.0).abs() < 0.08 && above.1.abs() < 0.08,
            "{above:?}"
        );
        assert!((plain.0 - 1.0).abs() + plain.1.abs() > 0.3, "{plain:?}");
        // On the probabilities as applied, the fit above the floor is better.
        let applied_loss = |(a, b): (f32, f32)| -> f64 {
            z.iter()
                .zip(&y)
                .zip(&floor)
                .map(|((&zi, &yi), &fi)| {
                    let p = f64::from(fi.max(sigmoid(a * zi + b))).clamp(1e-7, 1.0 - 1e-7);
                    -if yi { p.ln() } else { (1.0 - p).ln() }
                })
                .sum::<f64>()
        };
        assert!(applied_loss(above) < applied_loss(plain));
        // No floor: the plain fit.
        let none = vec![0.0f32; z.len()];
        assert_eq!(fit_platt_above(&z, &y, &none), plain);
    }

    #[test]
    fn the_fit_never_reverses_the_networks_order() {
        // Labels that run against the logits (the truth is sigmoid(-z), as
        // for the windows left above a floor that holds the positives): the
        // scale stops at its minimum, the probability near the base rate,
        // instead of turning negative.
        let (z, y) = sample(-1.0, 0.0, 4000);
        let (a, b) = fit_platt(&z, &y);
        assert!(a > 0.0 && a < 0.01, "{a}");
        assert!(b.abs() < 0.1, "{b}");
        let floor = vec![0.3f32; z.len()];
        let (a, _) = fit_platt_above(&z, &y, &floor);
        assert!(a > 0.0, "{a}");
    }

    #[test]
    fn platt_on_one_class_stays_finite() {
        let z = vec![0.3f32; 50];
        let y = vec![true; 50];
        let (a, b) = fit_platt(&z, &y);
        assert!(a.is_finite() && b.is_finite() && a > 0.0, "{a} {b}");
    }

    #[test]
    fn calibration_lowers_ece_and_keeps_horizons_ordered() {
        // Two horizons, an over-confident network (true scale 0.4).
        let (z, y1) = sample(0.4, 0.0, 5000);
        let (_, y2) = sample(0.4, 0.5, 5000);
        let logits: Vec<Vec<f32>> = z.iter().map(|&z| vec![z, z + 0.2]).collect();
        let labels: Vec<Vec<bool>> = y1.iter().zip(&y2).map(|(&a, &b)| vec![a, b]).collect();
        let scored = vec![None; logits.len()];
        let episode: Vec<usize> = (0..logits.len()).collect();
        let (cal, fits) = fit_calibration(
            &logits,
            &labels,
            &scored,
            &episode,
            &[500, 1000],
            FormChoice::Auto,
            "test".into(),
        );
        for f in &fits {
            assert!(f.ece_after < f.ece_before, "{f:?}");
            assert!(f.ece_after < 0.03, "{f:?}");
        }
        for r in &logits {
            let p = cal.apply(r);
            assert!(p[1] >= p[0], "{p:?}");
        }
    }

    /// Logits whose truth is beta calibration's `sigmoid(a·softplus(z) -
    /// c·softplus(-z) + b)`.
    fn beta_sample(a: f32, c: f32, b: f32, n: usize) -> (Vec<f32>, Vec<bool>) {
        let (z, _) = sample(1.0, 0.0, n);
        let mut state = 0x2545_f491_4f6c_dd1du64;
        let y = z
            .iter()
            .map(|&z| {
                state ^= state << 13;
                state ^= state >> 7;
                state ^= state << 17;
                let u = (state >> 11) as f64 / (1u64 << 53) as f64;
                u < f64::from(sigmoid(a * softplus(z) - c * softplus(-z) + b))
            })
            .collect();
        (z, y)
    }

    #[test]
    fn beta_recovers_a_one_sided_miscalibration() {
        // Over-confident on the negative side only: Platt's one slope cannot
        // follow it, beta calibration's two can.
        let (z, y) = beta_sample(1.0, 0.3, 0.2, 20_000);
        let none = vec![0.0f32; z.len()];
        let (a, c, b) = fit_above(CalibrationForm::Beta, &z, &y, &none);
        assert!((a - 1.0).abs() < 0.1, "a {a}");
        assert!((c - 0.3).abs() < 0.05, "c {c}");
        assert!((b - 0.2).abs() < 0.1, "b {b}");
        // On a Platt truth it finds the symmetric map.
        let (z, y) = sample(0.5, -0.7, 20_000);
        let (a, c, b) = fit_above(CalibrationForm::Beta, &z, &y, &none);
        assert!((a - 0.5).abs() < 0.06 && (c - 0.5).abs() < 0.06, "{a} {c}");
        assert!((b + 0.7).abs() < 0.1, "{b}");
    }

    #[test]
    fn auto_chooses_beta_where_it_pays_and_stores_it() {
        let (z, y) = beta_sample(1.0, 0.3, 0.2, 8000);
        let logits: Vec<Vec<f32>> = z.iter().map(|&z| vec![z]).collect();
        let labels: Vec<Vec<bool>> = y.iter().map(|&y| vec![y]).collect();
        let scored = vec![None; z.len()];
        // Two windows per episode: the folds keep them together.
        let episode: Vec<usize> = (0..z.len()).map(|i| i / 2).collect();
        let fit = |choice| {
            fit_calibration(
                &logits,
                &labels,
                &scored,
                &episode,
                &[500],
                choice,
                "t".into(),
            )
        };
        let (cal, fits) = fit(FormChoice::Auto);
        assert_eq!(fits[0].form, CalibrationForm::Beta, "{fits:?}");
        let (platt, beta) = fits[0].cv_nll.unwrap();
        assert!(beta < platt, "{fits:?}");
        assert!(cal.is_beta(), "{cal:?}");
        assert!(
            cal.fitted_on
                .ends_with("forms beta (chosen by cross-validation)"),
            "{}",
            cal.fitted_on
        );
        assert_eq!(fits[0].held_by_shorter, 0.0);
        assert_eq!(fits[0].ece_own, fits[0].ece_after);
        let (platt_cal, platt_fits) = fit(FormChoice::Fixed(CalibrationForm::Platt));
        assert!(platt_cal.neg_scale.is_none() && platt_fits[0].cv_nll.is_none());
        assert!(
            fits[0].ece_after < platt_fits[0].ece_after,
            "{fits:?} {platt_fits:?}"
        );
        // The stored map is the fitted one.
        let p = cal.apply(&[1.5])[0];
        let s = fits[0].scale * softplus(1.5) - fits[0].neg_scale * softplus(-1.5) + fits[0].bias;
        assert!((p - sigmoid(s)).abs() < 1e-6);
    }

    #[test]
    fn solve_matches_a_known_system() {
        let h = [[4.0, 1.0, 0.0], [1.0, 3.0, 1.0], [0.0, 1.0, 2.0]];
        let s = solve(h, [1.0, 2.0, 3.0]).unwrap();
        for (row, g) in h.iter().zip([1.0, 2.0, 3.0]) {
            let got: f64 = row.iter().zip(&s).map(|(a, b)| a * b).sum();
            assert!((got - g).abs() < 1e-12, "{s:?}");
        }
        assert!(solve([[1.0, 2.0], [2.0, 4.0]], [1.0, 1.0]).is_none());
    }
}
