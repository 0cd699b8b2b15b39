//! Motion encoder (P): proprioception, siMLPe-style, lighter.
//!
//! In: standardised joint angles `[B, N, C]`. Out: features `[B, N·C]`.
//! DCT over time, spatial block, `num_temporal` residual temporal blocks,
//! spatial block, inverse DCT. `Norm_C` is a LayerNorm over the joint axis.

use burn::nn::{LayerNorm, LayerNormConfig, Linear, LinearConfig};
use burn::prelude::*;

use super::config::ModelConfig;
use super::spectral::dct_matrix_shared;

/// One `X = X + Norm_C(U · X + b)` block, `U` linear over time.
#[derive(Module, Debug)]
pub struct TemporalBlock {
    time: Linear,
    norm: LayerNorm,
}

/// The motion encoder.
#[derive(Module, Debug)]
pub struct MotionEncoder {
    spatial_in: Linear,
    norm_in: LayerNorm,
    temporal: Vec<TemporalBlock>,
    spatial_out: Linear,
    norm_out: LayerNorm,
    n_ticks: usize,
}

impl MotionEncoder {
    /// A freshly initialised encoder.
    pub fn new(cfg: &ModelConfig, device: &Device) -> Self {
        let (n, c) = (cfg.n_ticks, cfg.n_joints);
        MotionEncoder {
            spatial_in: LinearConfig::new(c, c).init(device),
            norm_in: LayerNormConfig::new(c).init(device),
            temporal: (0..cfg.num_temporal)
                .map(|_| TemporalBlock {
                    time: LinearConfig::new(n, n).init(device),
                    norm: LayerNormConfig::new(c).init(device),
                })
                .collect(),
            spatial_out: LinearConfig::new(c, c).init(device),
            norm_out: LayerNormConfig::new(c).init(device),
            n_ticks: n,
        }
    }

    /// Number of features per sample, `N·C`.
    pub fn out_features(cfg: &ModelConfig) -> usize {
        cfg.n_ticks * cfg.n_joints
    }

    /// `[B, N, C]` -> `[B, N·C]`.
    pub fn forward(&self, joints: Tensor<3>) -> Tensor<2> {
        let [b, n, c] = joints.dims();
        let device = joints.device();
        let d = Tensor::<2>::from_data(
            TensorData::new(dct_matrix_shared(self.n_ticks).to_vec(), [n, n]),
            &device,
        );
        let dt = d.clone().transpose();
        let mut x = d.unsqueeze::<3>().matmul(joints);
        x = self.norm_in.forward(self.spatial_in.forward(x));
        for block in &self.temporal {
            // U · X over time: put time last, apply the N -> N linear, put it back.
            let u = block
                .time
                .forward(x.clone().swap_dims(1, 2))
                .swap_dims(1, 2);
            x = x + block.norm.forward(u);
        }
        x = self.norm_out.forward(self.spatial_out.forward(x));
        let out = dt.unsqueeze::<3>().matmul(x);
        out.reshape([b, n * c])
    }
}
