//! `fall-guard calibrate`: post-hoc calibration of a trained network on
//! held-out windows (Platt scaling per horizon, shortest first, each fitted
//! for the probability as published: above the running maximum of the
//! shorter horizons).
//!
//! In: a model file, a data set and a split that the network was not trained
//! on (validation by default). Out: the same model file with a
//! [`Calibration`] in its metadata, which the daemon, `eval` and `warnings`
//! apply to every forecast. Fitted on validation, judged on test.

use std::path::PathBuf;

use crate::train::error::{refused, CommandResult, Doing};

use super::cli::{needs_of_model, SplitWindows, EVAL_BATCH};
use super::dataset::{Dataset, Split};
use super::fit::for_each_batch;
use super::metrics::ece;
use super::sampler::Protocol;
use crate::model::file::{load_emp, sigmoid};
use crate::model::{Calibration, LoadedModel, WeightPrecision};

/// Arguments of `fall-guard calibrate`.
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
}

/// Fits `sigmoid(a·z + b)` to labels `y` by Newton's method on the mean
/// binary cross-entropy (Platt scaling), with a small ridge pulling towards
/// the identity `(1, 0)` so that a separable or one-class sample still gives
/// a finite answer. Returns `(a, b)`.
pub fn fit_platt(z: &[f32], y: &[bool]) -> (f32, f32) {
    newton(z, y, &vec![0.0; z.len()], (1.0, 0.0))
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
    assert!(
        z.len() == y.len() && z.len() == floor.len(),
        "one label and one floor per logit"
    );
    let plain = fit_platt(z, y);
    if floor.iter().all(|&f| f <= 0.0) {
        return plain;
    }
    newton(z, y, floor, (f64::from(plain.0), f64::from(plain.1)))
}

/// The smallest logit scale a fit takes.
const MIN_SCALE: f64 = 1e-3;

/// Newton's method with backtracking on the ridge-regularised mean
/// cross-entropy of `max(floor_i, sigmoid(a·z_i + b))`, from `start`, the
/// scale kept at or above [`MIN_SCALE`].
fn newton(z: &[f32], y: &[bool], floor: &[f32], start: (f64, f64)) -> (f32, f32) {
    const RIDGE: f64 = 1e-3;
    let n = z.len().max(1) as f64;
    let loss = |a: f64, b: f64| -> f64 {
        let mut l = 0.0;
        for ((&zi, &yi), &fi) in z.iter().zip(y).zip(floor) {
            let s = a * f64::from(zi) + b;
            let fi = f64::from(fi);
            if fi > 0.0 && f64::from(sigmoid(s as f32)) < fi {
                // The floor is the probability: -log p or -log(1 - p).
                let p = fi.clamp(1e-7, 1.0 - 1e-7);
                l -= if yi { p.ln() } else { (1.0 - p).ln() };
                continue;
            }
            // log(1 + e^s) - y·s, stable.
            let softplus = if s > 0.0 {
                s + (-s).exp().ln_1p()
            } else {
                s.exp().ln_1p()
            };
            l += softplus - if yi { s } else { 0.0 };
        }
        l / n + 0.5 * RIDGE * ((a - 1.0).powi(2) + b * b)
    };
    let (mut a, mut b) = start;
    let mut current = loss(a, b);
    for _ in 0..100 {
        let (mut ga, mut gb, mut haa, mut hab, mut hbb) = (0.0, 0.0, 0.0, 0.0, 0.0);
        for ((&zi, &yi), &fi) in z.iter().zip(y).zip(floor) {
            let zi = f64::from(zi);
            let p = sigmoid((a * zi + b) as f32);
            if p < fi {
                continue;
            }
            let p = f64::from(p);
            let r = p - if yi { 1.0 } else { 0.0 };
            let w = (p * (1.0 - p)).max(1e-12);
            ga += r * zi;
            gb += r;
            haa += w * zi * zi;
            hab += w * zi;
            hbb += w;
        }
        ga = ga / n + RIDGE * (a - 1.0);
        gb = gb / n + RIDGE * b;
        haa = haa / n + RIDGE;
        hab /= n;
        hbb = hbb / n + RIDGE;
        let det = haa * hbb - hab * hab;
        if det.abs() < 1e-18 {
            break;
        }
        let da = (hbb * ga - hab * gb) / det;
        let db = (haa * gb - hab * ga) / det;
        // Backtracking: never accept a step that raises the loss, nor one
        // that turns the scale below MIN_SCALE (a calibration keeps the
        // network's order).
        let mut t = 1.0;
        let mut improved = false;
        while t > 1e-6 {
            let (na, nb) = (a - t * da, b - t * db);
            if na < MIN_SCALE {
                t *= 0.5;
                continue;
            }
            let l = loss(na, nb);
            if l <= current {
                improved = current - l > 1e-12;
                (a, b, current) = (na, nb, l);
                break;
            }
            t *= 0.5;
        }
        if !improved || (da.abs() + db.abs()) * t < 1e-9 {
            break;
        }
    }
    (a as f32, b as f32)
}

/// What calibration did to one horizon of the fitting split.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct HorizonFit {
    /// Horizon, ms.
    pub horizon_ms: u32,
    /// Fitted logit scale.
    pub scale: f32,
    /// Fitted logit offset.
    pub bias: f32,
    /// ECE (15 bins) before, on the fitting windows.
    pub ece_before: f64,
    /// ECE after, on the fitting windows (with the running maximum).
    pub ece_after: f64,
}

/// Fits a [`Calibration`] per horizon to `logits` (one row of `K` per
/// window) and their labels (one row of `K` per window). `scored[i]`:
/// `Some(k)` when window `i` counts for horizon `k` only (paper protocol),
/// `None` when it counts for all.
pub fn fit_calibration(
    logits: &[Vec<f32>],
    labels: &[Vec<bool>],
    scored: &[Option<usize>],
    horizons_ms: &[u32],
    fitted_on: String,
) -> (Calibration, Vec<HorizonFit>) {
    let k = horizons_ms.len();
    let mut cal = Calibration::identity(k);
    cal.fitted_on = fitted_on;
    let rows = |h: usize| (0..logits.len()).filter(move |&i| scored[i].is_none_or(|s| s == h));
    // Shortest horizon first: each is fitted for the probability applied,
    // above the running maximum of the shorter ones as already fitted.
    for h in 0..k {
        let z: Vec<f32> = rows(h).map(|i| logits[i][h]).collect();
        let y: Vec<bool> = rows(h).map(|i| labels[i][h]).collect();
        let floor: Vec<f32> = rows(h)
            .map(|i| h.checked_sub(1).map_or(0.0, |k| cal.apply(&logits[i])[k]))
            .collect();
        let (a, b) = fit_platt_above(&z, &y, &floor);
        cal.scale[h] = a;
        cal.bias[h] = b;
    }
    let before: Vec<Vec<f32>> = logits
        .iter()
        .map(|r| r.iter().map(|&z| sigmoid(z)).collect())
        .collect();
    let after: Vec<Vec<f32>> = logits.iter().map(|r| cal.apply(r)).collect();
    let fits = (0..k)
        .map(|h| {
            let y: Vec<bool> = rows(h).map(|i| labels[i][h]).collect();
            let col = |p: &[Vec<f32>]| rows(h).map(|i| p[i][h]).collect::<Vec<f32>>();
            HorizonFit {
                horizon_ms: horizons_ms[h],
                scale: cal.scale[h],
                bias: cal.bias[h],
                ece_before: ece(&col(&before), &y, 15),
                ece_after: ece(&col(&after), &y, 15),
            }
        })
        .collect();
    (cal, fits)
}

/// Runs `fall-guard calibrate`.
pub fn run_calibrate(args: &CalibrateOptions) -> CommandResult<()> {
    let split: Split = args.split.parse().map_err(refused)?;
    if split == Split::Train {
        return Err(refused(
            "--split train: calibrate on windows the network was not trained on (validation)",
        ));
    }
    // One read of the file: the trainable network is what gets written back.
    let device = crate::model::cpu_device();
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
    let (mut logits, mut labels, mut scored) = (Vec::new(), Vec::new(), Vec::new());
    // Built a batch at a time: only the logits and labels stay.
    for _ in 0..args.draws.max(1) {
        for_each_batch(&windows.epoch(), EVAL_BATCH, true, |batch| {
            for w in batch {
                logits.push(model.logits_arrays(&w.joints, &w.plan, &w.frames)?);
                labels.push(w.labels.iter().map(|&l| l > 0.5).collect::<Vec<bool>>());
                scored.push(w.scored_horizon);
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
        args.data.display(),
        logits.len(),
        args.draws.max(1),
        args.sample_seed,
        args.protocol
    );
    let (cal, fits) = fit_calibration(&logits, &labels, &scored, &meta.horizons_ms(), fitted_on);
    println!(
        "| horizon | scale | bias | ECE before ({}) | ECE after |",
        split.name()
    );
    println!("| --- | --- | --- | --- | --- |");
    for f in &fits {
        println!(
            "| {} ms | {:.3} | {:.3} | {:.4} | {:.4} |",
            f.horizon_ms, f.scale, f.bias, f.ece_before, f.ece_after
        );
    }
    let mut meta = model.meta.clone();
    meta.calibration = Some(cal);
    let precision = if args.half {
        WeightPrecision::Half
    } else {
        WeightPrecision::Full
    };
    crate::model::save_model_as(&args.out, &meta, &emp, precision)
        .doing(|| format!("writing {}", args.out.display()))?;
    LoadedModel::load(&args.out).doing(|| format!("reading back {}", args.out.display()))?;
    eprintln!("calibrated model written to {}", args.out.display());
    Ok(())
}

#[cfg(test)]
mod tests {
    use super::*;

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
        let (cal, fits) = fit_calibration(&logits, &labels, &scored, &[500, 1000], "test".into());
        for f in &fits {
            assert!(f.ece_after < f.ece_before, "{f:?}");
            assert!(f.ece_after < 0.03, "{f:?}");
        }
        for r in &logits {
            let p = cal.apply(r);
            assert!(p[1] >= p[0], "{p:?}");
        }
    }
}
