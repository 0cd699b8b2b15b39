//! Synthetic labelled windows in which falls are learnable: for tests of
//! the training loop (`crates/lab/tests`), never for a model that
//! ships.

use fall_guard_lab::{EpochSource, LabeledWindow, TrainError, WindowSet};
use fall_guard_runtime::model::ModelConfig;

/// Episodes with a lean that ramps up before the fall: joint 0 rises
/// linearly over `2 h_K` ticks up to the onset. Half never fall.
pub struct RampEpisodes {
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
                    episode: i,
                    scored_horizon: None,
                }
            })
            .collect()
    }
}

impl EpochSource for RampEpisodes {
    fn train_epoch(&mut self, epoch: usize) -> Result<Box<dyn WindowSet>, TrainError> {
        Ok(Box::new(self.windows(self.per_epoch, 100 + epoch as u64)))
    }
    fn validation(&mut self) -> Result<Box<dyn WindowSet>, TrainError> {
        Ok(Box::new(self.windows(64, 1)))
    }
}

/// A small but complete network configuration for the training tests: 24
/// ticks, 4 joints, horizons 3-12 ticks, 32 x 32 frames (the reference
/// sizes make tests slow in debug).
pub fn small_config() -> ModelConfig {
    let mut cfg = ModelConfig::lite(24, 4, vec![3, 6, 9, 12], 32);
    cfg.d_model = 128;
    cfg.inc_dim = 8;
    cfg.plan_d = 8;
    cfg
}
