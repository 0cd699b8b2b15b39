//! Motion encoder (P): proprioception, siMLPe-style, lighter.
//!
//! In: standardised joint angles `[B, N, C]`. Out: features `[B, N·C]`.
//! DCT over time, spatial block, `num_temporal` residual temporal blocks,
//! spatial block, inverse DCT. `Norm_C` is a LayerNorm over the joint axis.

use std::sync::Arc;

use burn::nn::{LayerNorm, LayerNormConfig, Linear, LinearConfig};
use burn::prelude::*;

use super::config::ModelConfig;
use super::host_linear::{host_values, linear_values};
use super::spectral::dct_matrix_shared;

/// The layer norms' epsilon (burn's default, set explicitly so that the
/// host form below uses the same).
const NORM_EPS: f64 = 1e-5;

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
            norm_in: LayerNormConfig::new(c).with_epsilon(NORM_EPS).init(device),
            temporal: (0..cfg.num_temporal)
                .map(|_| TemporalBlock {
                    time: LinearConfig::new(n, n).init(device),
                    norm: LayerNormConfig::new(c).with_epsilon(NORM_EPS).init(device),
                })
                .collect(),
            spatial_out: LinearConfig::new(c, c).init(device),
            norm_out: LayerNormConfig::new(c).with_epsilon(NORM_EPS).init(device),
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

/// A layer norm over the last axis, on the host.
#[derive(Debug, Clone)]
struct HostNorm {
    gamma: Vec<f32>,
    beta: Vec<f32>,
}

impl HostNorm {
    fn of(norm: &LayerNorm) -> HostNorm {
        let gamma = host_values(norm.gamma.val());
        let beta = norm
            .beta
            .as_ref()
            .map_or_else(|| vec![0.0; gamma.len()], |b| host_values(b.val()));
        HostNorm { gamma, beta }
    }

    /// `row = (row - mean) / sqrt(var + eps) · gamma + beta` (biased
    /// variance, as burn's).
    #[inline(always)]
    fn apply(&self, row: &mut [f32]) {
        let n = row.len() as f32;
        let mean = row.iter().sum::<f32>() / n;
        let var = row.iter().map(|v| (v - mean) * (v - mean)).sum::<f32>() / n;
        let inv = 1.0 / (var + NORM_EPS as f32).sqrt();
        for ((v, g), b) in row.iter_mut().zip(&self.gamma).zip(&self.beta) {
            *v = (*v - mean) * inv * g + b;
        }
    }
}

/// `out[t, :] = Σ_i m[t, i] · x[i, :]` for `x` `[n, c]` and `m` `[n, n]`
/// row-major (each output row a sum of scaled input rows).
#[inline(always)]
fn mix_rows(m: &[f32], x: &[f32], c: usize, out: &mut [f32]) {
    let n = x.len() / c;
    for (t, row) in out.chunks_exact_mut(c).enumerate() {
        row.fill(0.0);
        for (i, xi) in x.chunks_exact(c).enumerate() {
            let a = m[t * n + i];
            for (o, v) in row.iter_mut().zip(xi) {
                *o += a * v;
            }
        }
    }
}

/// A spatial layer and the norm after it, on the host: each tick's row
/// `norm(row · W + b)`, `W` `[c, c]` row-major (`[in, out]`).
#[derive(Debug, Clone)]
struct HostSpatial {
    w: Vec<f32>,
    b: Vec<f32>,
    norm: HostNorm,
}

impl HostSpatial {
    fn of(linear: &Linear, norm: &LayerNorm) -> HostSpatial {
        let (w, b) = linear_values(linear);
        HostSpatial {
            w,
            b,
            norm: HostNorm::of(norm),
        }
    }

    /// Every row of `x` (`w` values apart, the first `tmp.len()` of each
    /// the joints) in place.
    #[inline(always)]
    fn rows(&self, x: &mut [f32], w: usize, tmp: &mut [f32]) {
        let c = tmp.len();
        for row in x.chunks_exact_mut(w) {
            let row = &mut row[..c];
            tmp.copy_from_slice(&self.b);
            for (i, &v) in row.iter().enumerate() {
                for (o, wv) in tmp.iter_mut().zip(&self.w[i * c..(i + 1) * c]) {
                    *o += v * wv;
                }
            }
            row.copy_from_slice(tmp);
            self.norm.apply(row);
        }
    }
}

/// `m` `[n, n]` row-major, transposed.
fn transposed(m: &[f32], n: usize) -> Vec<f32> {
    (0..n * n).map(|k| m[(k % n) * n + k / n]).collect()
}

/// The motion encoder for inference, on the host: the same operations as
/// [`MotionEncoder::forward`] on plain arrays. burn ran its fourteen small
/// products and seven layer norms as tensor operations, each with its
/// dispatch and allocations: 1.2 M instructions a forecast for 0.8 M
/// multiply-adds (`docs/performance.md`). Equal to the burn form within
/// rounding (tested).
#[derive(Debug, Clone)]
pub struct MotionHost {
    n: usize,
    c: usize,
    dct: Arc<[f32]>,
    /// `D^T`, `[n, n]`, for the inverse transform as the same row mix.
    dct_t: Vec<f32>,
    spatial_in: HostSpatial,
    /// Per temporal block: `U^T` `[out, in]` (rows mixed as `dct` is), its
    /// bias per output tick, and its norm.
    temporal: Vec<(Vec<f32>, Vec<f32>, HostNorm)>,
    spatial_out: HostSpatial,
}

impl MotionHost {
    pub fn of(enc: &MotionEncoder) -> MotionHost {
        let n = enc.n_ticks;
        let c = enc.spatial_in.weight.dims()[0];
        let dct = dct_matrix_shared(n);
        let dct_t = transposed(&dct, n);
        let temporal = enc
            .temporal
            .iter()
            .map(|b| {
                let (w, bias) = linear_values(&b.time);
                (transposed(&w, n), bias, HostNorm::of(&b.norm))
            })
            .collect();
        MotionHost {
            n,
            c,
            dct,
            dct_t,
            spatial_in: HostSpatial::of(&enc.spatial_in, &enc.norm_in),
            temporal,
            spatial_out: HostSpatial::of(&enc.spatial_out, &enc.norm_out),
        }
    }

    /// `[B, N, C]` -> `[B, N·C]`, as [`MotionEncoder::forward`].
    pub fn forward(&self, joints: Tensor<3>) -> Tensor<2> {
        let [b, n, c] = joints.dims();
        assert_eq!((n, c), (self.n, self.c), "motion input shape");
        let device = joints.device();
        let xs = host_values(joints);
        let mut out = vec![0.0f32; b * n * c];
        for (x, y) in xs.chunks_exact(n * c).zip(out.chunks_exact_mut(n * c)) {
            self.sample(x, y);
        }
        Tensor::<2>::from_data(TensorData::new(out, [b, n * c]), &device)
    }

    /// One sample: `joints` `[N, C]` -> `out` `[N·C]`; 8 lanes at a time
    /// where the CPU has AVX2 (the same operations in the same order per
    /// value, so the same bits as the portable loops).
    fn sample(&self, joints: &[f32], out: &mut [f32]) {
        #[cfg(target_arch = "x86_64")]
        {
            if std::arch::is_x86_feature_detected!("avx2") {
                // SAFETY: the CPU has AVX2 (checked just above).
                unsafe { self.sample_avx2(joints, out) };
                return;
            }
        }
        self.sample_portable(joints, out);
    }

    #[cfg(target_arch = "x86_64")]
    #[target_feature(enable = "avx2")]
    fn sample_avx2(&self, joints: &[f32], out: &mut [f32]) {
        self.sample_portable(joints, out);
    }

    #[inline(always)]
    fn sample_portable(&self, joints: &[f32], out: &mut [f32]) {
        let (n, c) = (self.n, self.c);
        // Rows padded with zeros to `w` values ([`PADDED`] when the joints
        // fit), so that a row mix keeps a whole row in registers.
        let w = if c <= PADDED { PADDED } else { c };
        let mix = |m: &[f32], x: &[f32], out: &mut [f32]| {
            if w == PADDED {
                mix_rows_padded(m, x, out);
            } else {
                mix_rows(m, x, w, out);
            }
        };
        let mut j = vec![0.0f32; n * w];
        for (row, src) in j.chunks_exact_mut(w).zip(joints.chunks_exact(c)) {
            row[..c].copy_from_slice(src);
        }
        let mut x = vec![0.0f32; n * w];
        let mut u = vec![0.0f32; n * w];
        let mut tmp = vec![0.0f32; c];
        mix(&self.dct, &j, &mut x);
        self.spatial_in.rows(&mut x, w, &mut tmp);
        for (w_t, bias, norm) in &self.temporal {
            mix(w_t, &x, &mut u);
            for ((ur, xr), b) in u.chunks_exact_mut(w).zip(x.chunks_exact_mut(w)).zip(bias) {
                let ur = &mut ur[..c];
                ur.iter_mut().for_each(|v| *v += b);
                norm.apply(ur);
                xr[..c]
                    .iter_mut()
                    .zip(ur.iter())
                    .for_each(|(xv, uv)| *xv += uv);
            }
        }
        self.spatial_out.rows(&mut x, w, &mut tmp);
        mix(&self.dct_t, &x, &mut u);
        for (dst, row) in out.chunks_exact_mut(c).zip(u.chunks_exact(w)) {
            dst.copy_from_slice(&row[..c]);
        }
    }
}

/// The padded row width of [`mix_rows_padded`]: Poppy's 25 joints fit.
const PADDED: usize = 32;

/// [`mix_rows`] for rows of [`PADDED`] values: each output row summed in
/// registers (the same operations in the same order per value).
#[inline(always)]
fn mix_rows_padded(m: &[f32], x: &[f32], out: &mut [f32]) {
    let n = x.len() / PADDED;
    let (rows, _) = x.as_chunks::<PADDED>();
    for (row, mt) in out.chunks_exact_mut(PADDED).zip(m.chunks_exact(n)) {
        let mut acc = [0.0f32; PADDED];
        for (xi, &a) in rows.iter().zip(mt) {
            for j in 0..PADDED {
                acc[j] += a * xi[j];
            }
        }
        row.copy_from_slice(&acc);
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::model::cpu_device;
    use burn::tensor::Distribution;

    /// The host form gives the burn form's features within rounding, on
    /// a trained-like encoder (random weights, norms not at their start).
    #[test]
    fn host_motion_equals_the_burn_encoder() {
        let device = cpu_device();
        let cfg = ModelConfig::lite(60, 25, vec![15, 30, 45, 60], 64);
        let mut enc = MotionEncoder::new(&cfg, &device);
        let shake = |t: Tensor<1>| t.clone() + t.random_like(Distribution::Normal(0.0, 0.3));
        enc.norm_in.gamma = enc.norm_in.gamma.clone().map(shake);
        for b in &mut enc.temporal {
            b.norm.gamma = b.norm.gamma.clone().map(shake);
            b.norm.beta = b.norm.beta.clone().map(|o| o.map(shake));
        }
        let host = MotionHost::of(&enc);
        let joints = Tensor::<3>::random([3, 60, 25], Distribution::Normal(0.0, 1.0), &device);
        let want: Vec<f32> = enc
            .forward(joints.clone())
            .into_data()
            .try_to_vec::<f32>()
            .expect("f32");
        let got: Vec<f32> = host
            .forward(joints)
            .into_data()
            .try_to_vec::<f32>()
            .expect("f32");
        assert_eq!(got.len(), want.len());
        let worst = got
            .iter()
            .zip(&want)
            .map(|(a, b)| (a - b).abs() / b.abs().max(1.0))
            .fold(0.0f32, f32::max);
        assert!(worst < 1e-4, "largest difference {worst}");
        assert!(
            want.iter().any(|v| v.abs() > 0.1),
            "features not all near zero"
        );
    }
}
