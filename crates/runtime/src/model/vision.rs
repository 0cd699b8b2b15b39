//! Vision encoder (E): egocentric frames.
//!
//! In: low-passed frames `[B, 3, N, 2a, 2a]` (see [`lowpass_frames`]; the
//! low-pass is a fixed per-frame map, applied once per frame, outside the
//! trainable part). Out: features `[B, C_last · T' · h' · w']`.
//! `num_conv` layers of Inception3d (kernels 1 and 3, "same" padding) + ReLU +
//! max-pool halving height and width, and time too where the config says so.

use burn::prelude::*;
use burn::tensor::activation::relu;
use burn::tensor::module::max_pool2d;
use burn::tensor::ops::MaxPoolOptions;

use super::config::ModelConfig;
use super::host_conv::HostConv;
use super::inception::{FusedConv, Inception3d};
use super::spectral::lowpass_matrix_shared;

/// The vision encoder.
#[derive(Module, Debug)]
pub struct VisionEncoder {
    layers: Vec<Inception3d>,
    time_pool: Vec<bool>,
}

/// The fused convolutions of every layer, for inference.
#[derive(Debug, Clone)]
pub struct VisionFused {
    /// One fused 3x3x3 convolution per layer.
    pub layers: Vec<FusedConv<5>>,
    /// The same convolutions, one output time slice at a time (streaming).
    pub slices: Vec<HostConv>,
    /// Whether each layer's pool halves time.
    pub time_pool: Vec<bool>,
}

impl VisionEncoder {
    /// A freshly initialised encoder.
    pub fn new(cfg: &ModelConfig, device: &Device) -> Self {
        let mut c_in = 3;
        let layers = cfg
            .vision_channels
            .iter()
            .map(|&c_out| {
                let l = Inception3d::new(c_in, c_out, device);
                c_in = c_out;
                l
            })
            .collect();
        VisionEncoder {
            layers,
            time_pool: cfg.vision_time_pool.clone(),
        }
    }

    /// Number of features per sample.
    pub fn out_features(cfg: &ModelConfig) -> usize {
        cfg.vision_out_shape().iter().product()
    }

    /// Fuses every Inception block (inference).
    pub fn fuse(&self) -> VisionFused {
        let layers: Vec<FusedConv<5>> = self.layers.iter().map(Inception3d::fuse).collect();
        VisionFused {
            slices: layers.iter().map(HostConv::from_fused).collect(),
            layers,
            time_pool: self.time_pool.clone(),
        }
    }

    /// `[B, 3, N, s, s]` (low-passed) -> `[B, features]` (training). The
    /// layers run channel-major (`[C, B, T, H, W]`, see
    /// [`Inception3d::forward_channel_major`]): one permutation in, one out,
    /// the features in the same `(C, T, H, W)` order as [`VisionFused::forward`].
    pub fn forward(&self, frames: Tensor<5>) -> Tensor<2> {
        let mut x = frames.permute([1, 0, 2, 3, 4]);
        for (layer, &tp) in self.layers.iter().zip(&self.time_pool) {
            x = pool_channel_major(relu(layer.forward_channel_major(x)), tp);
        }
        x.permute([1, 0, 2, 3, 4]).flatten(1, 4)
    }
}

impl VisionFused {
    /// Whole-window forward with the fused kernels: `[B, 3, N, s, s]` -> `[B, features]`.
    pub fn forward(&self, frames: Tensor<5>) -> Tensor<2> {
        let mut x = frames;
        for (layer, &tp) in self.layers.iter().zip(&self.time_pool) {
            x = pool(relu(layer.forward(x)), tp);
        }
        x.flatten(1, 4)
    }
}

/// Max-pool halving height and width (`(1,2,2)`), and time too (`(2,2,2)`)
/// when `time` is set; an odd trailing slice is dropped (floor), as PyTorch does.
pub fn pool(x: Tensor<5>, time: bool) -> Tensor<5> {
    let x = spatial_pool(x);
    if time {
        time_pool(x)
    } else {
        x
    }
}

/// `(1,2,2)` max-pool: `[B, C, T, H, W]` -> `[B, C, T, H/2, W/2]`.
pub fn spatial_pool(x: Tensor<5>) -> Tensor<5> {
    let [b, c, t, h, w] = x.dims();
    let y = max_pool2d(x.reshape([b, c * t, h, w]), MaxPoolOptions::new([2, 2]));
    y.reshape([b, c, t, h / 2, w / 2])
}

/// Max over consecutive pairs of time slices: `[B, C, T, H, W]` -> `[B, C, T/2, H, W]`.
pub fn time_pool(x: Tensor<5>) -> Tensor<5> {
    let [b, c, t, h, w] = x.dims();
    let t2 = t / 2;
    let x = if t % 2 == 1 {
        x.slice([0..b, 0..c, 0..2 * t2, 0..h, 0..w])
    } else {
        x
    };
    x.reshape([b * c * t2, 2, h * w])
        .max_dim(1)
        .reshape([b, c, t2, h, w])
}

/// [`pool`] on channel-major activations: `[C, B, T, H, W]` ->
/// `[C, B, T or T/2, H/2, W/2]`.
fn pool_channel_major(x: Tensor<5>, time: bool) -> Tensor<5> {
    let [c, b, t, h, w] = x.dims();
    let x = max_pool2d(x.reshape([c, b * t, h, w]), MaxPoolOptions::new([2, 2]));
    let (h, w) = (h / 2, w / 2);
    if !time {
        return x.reshape([c, b, t, h, w]);
    }
    let t2 = t / 2;
    let x = x.reshape([c * b, t, h * w]);
    let x = if t % 2 == 1 {
        x.slice([0..c * b, 0..2 * t2, 0..h * w])
    } else {
        x
    };
    x.reshape([c * b, t2, 2, h * w])
        .max_dim(2)
        .reshape([c, b, t2, h, w])
}

/// Low-pass + decimation of raw frames: `[B, 3, N, S, S]` in `[0, 1]` ->
/// `[B, 3, N, 2a, 2a]` (`P · x · Pᵀ` per plane, two plain matmuls).
pub fn lowpass_frames(frames: Tensor<5>, a: usize) -> Tensor<5> {
    let [b, c, t, s, s2] = frames.dims();
    debug_assert_eq!(s, s2);
    let o = 2 * a;
    let device = frames.device();
    let p = Tensor::<2>::from_data(
        TensorData::new(lowpass_matrix_shared(a, s).to_vec(), [o, s]),
        &device,
    );
    let planes = b * c * t;
    // x · Pᵀ over width: [planes·S, S] · [S, o] -> [planes, S, o]
    let y = frames
        .reshape([planes * s, s])
        .matmul(p.clone().transpose());
    // then over height: transpose to [planes, o, S], times Pᵀ -> [planes, o(w), o(h)]
    let y = y
        .reshape([planes, s, o])
        .swap_dims(1, 2)
        .reshape([planes * o, s])
        .matmul(p.transpose());
    y.reshape([planes, o, o])
        .swap_dims(1, 2)
        .reshape([b, c, t, o, o])
}
