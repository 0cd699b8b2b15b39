//! Training end to end on a synthetic task where falls are learnable.

use super::fit::*;
use crate::model::{save_model, Ablation, LoadedModel, ModelConfig, ModelMeta};

/// Episodes with a lean that ramps up before the fall: joint 0 rises
/// linearly over `2 h_K` ticks up to the onset. Half never fall.
pub(crate) struct RampEpisodes {
    pub cfg: ModelConfig,
    pub per_epoch: usize,
    pub seed: u64,
}

fn rng_next(s: &mut u64) -> f32 {
    *s ^= *s << 13;
    *s ^= *s >> 7;
    *s ^= *s << 17;
    (*s >> 40) as f32 / (1u64 << 24) as f32
}

impl RampEpisodes {
    pub fn windows(&self, count: usize, stream: u64) -> Vec<LabeledWindow> {
        let cfg = &self.cfg;
        let (n, c, l, s) = (cfg.n_ticks, cfg.n_joints, cfg.plan_len(), cfg.frame_size);
        let hk = cfg.max_horizon_ticks();
        let ramp = 2 * hk;
        let mut st = (self.seed * 1_000_003 + stream).wrapping_mul(0x9E3779B97F4A7C15) | 1;
        (0..count)
            .map(|i| {
                let falls = i % 2 == 0;
                let d = 1 + (rng_next(&mut st) * (ramp as f32)) as usize; // onset, ticks after window end
                let phase = rng_next(&mut st) * std::f32::consts::TAU;
                let mut joints = vec![0.0f32; n * c];
                for t in 0..n {
                    for j in 0..c {
                        let walk = 0.3 * ((t as f32) * 0.4 + phase + j as f32).sin();
                        joints[t * c + j] = walk + 0.05 * (rng_next(&mut st) - 0.5);
                    }
                    if falls {
                        let since_start = t as i64 - (n as i64 - 1 + d as i64 - ramp as i64);
                        if since_start > 0 {
                            joints[t * c] += 2.0 * since_start as f32 / ramp as f32;
                        }
                    }
                }
                let plan: Vec<f32> = (0..l * c)
                    .map(|k| 0.3 * ((k / c) as f32 * 0.4 + phase + (k % c) as f32).sin())
                    .collect();
                let frames = if cfg.n_ticks * s > 0 {
                    vec![0.5f32; 3 * n * s * s]
                } else {
                    vec![]
                };
                let labels = cfg
                    .horizons_ticks
                    .iter()
                    .map(|&h| f32::from(u8::from(falls && d <= h)))
                    .collect();
                LabeledWindow {
                    joints,
                    plan,
                    frames,
                    labels,
                }
            })
            .collect()
    }
}

impl EpochSource for RampEpisodes {
    fn train_epoch(&mut self, epoch: usize) -> Result<Vec<LabeledWindow>, TrainError> {
        Ok(self.windows(self.per_epoch, 100 + epoch as u64))
    }
    fn validation(&mut self) -> Result<Vec<LabeledWindow>, TrainError> {
        Ok(self.windows(64, 1))
    }
}

fn small_cfg() -> ModelConfig {
    let mut cfg = ModelConfig::lite(24, 4, vec![3, 6, 9, 12], 32);
    cfg.d_model = 128;
    cfg.inc_dim = 8;
    cfg.plan_d = 8;
    cfg
}

#[test]
fn learns_a_learnable_fall_task_and_the_file_reproduces_it() {
    let cfg = small_cfg();
    let names: Vec<String> = (0..cfg.n_joints).map(|i| format!("j{i}")).collect();
    let meta = ModelMeta::new(cfg.clone(), Ablation::P, 30.0, names);
    let mut source = RampEpisodes {
        cfg: cfg.clone(),
        per_epoch: 400,
        seed: 1,
    };
    let opts = FitOptions {
        seed: 1,
        progress: false,
        ..FitOptions::default()
    };
    let (meta, model) = fit(meta, &mut source, &opts).unwrap();
    assert!(meta.best_epoch >= 1 && !meta.history.is_empty());
    let dir = tempfile::tempdir().unwrap();
    let path = dir.path().join("ramp.bpk");
    save_model(&path, &meta, &model).unwrap();
    let loaded = LoadedModel::load(&path).unwrap();
    let test = source.windows(200, 999);
    let (mut correct, mut total) = (0usize, 0usize);
    for w in &test {
        let p = loaded
            .forecast_arrays(&w.joints, &w.plan, &w.frames)
            .unwrap();
        for (pi, yi) in p.iter().zip(&w.labels) {
            correct += usize::from((*pi >= 0.5) == (*yi > 0.5));
            total += 1;
        }
    }
    let acc = correct as f64 / total as f64;
    assert!(
        acc > 0.9,
        "test accuracy {acc:.3}; history {:?}",
        meta.history
    );
}

#[test]
fn training_is_deterministic_for_a_seed() {
    let cfg = small_cfg();
    let names: Vec<String> = (0..cfg.n_joints).map(|i| format!("j{i}")).collect();
    let run = || {
        let meta = ModelMeta::new(cfg.clone(), Ablation::MP, 30.0, names.clone());
        let mut source = RampEpisodes {
            cfg: cfg.clone(),
            per_epoch: 16,
            seed: 3,
        };
        let opts = FitOptions {
            seed: 7,
            max_epochs: 2,
            progress: false,
            ..FitOptions::default()
        };
        fit(meta, &mut source, &opts).unwrap().0.history
    };
    assert_eq!(run(), run());
}

#[test]
fn logistic_baseline_learns_the_ramp_task_and_round_trips() {
    use super::logreg::LogRegModel;
    let cfg = small_cfg();
    let source = RampEpisodes {
        cfg: cfg.clone(),
        per_epoch: 0,
        seed: 5,
    };
    let train = source.windows(300, 1);
    let names: Vec<String> = (0..cfg.n_joints).map(|i| format!("j{i}")).collect();
    let m = LogRegModel::fit(&train, cfg.horizons_ticks.clone(), 30.0, cfg.n_ticks, names).unwrap();
    let dir = tempfile::tempdir().unwrap();
    let path = dir.path().join("logreg.json");
    m.save(&path).unwrap();
    let m = LogRegModel::load(&path).unwrap().expect("a logreg file");
    let test = source.windows(200, 2);
    let (mut correct, mut total) = (0usize, 0usize);
    for w in &test {
        for (p, y) in m.predict(w).unwrap().iter().zip(&w.labels) {
            correct += usize::from((*p >= 0.5) == (*y > 0.5));
            total += 1;
        }
    }
    let acc = correct as f64 / total as f64;
    assert!(acc > 0.8, "baseline accuracy {acc:.3}");
}
