//! Inception blocks: the mean of parallel "same"-padded convolutions with
//! kernels `1, 3, 5, ...`, and their exact fusion into one convolution.
//!
//! The parameters are the branches' ([`Inception2d`], [`Inception3d`]: the
//! model file stores them). Both training and inference run one convolution
//! whose kernel is the mean of the zero-padded branch kernels (the same
//! linear map, fewer multiply-adds): inference fuses once at load time
//! ([`FusedConv`], on the host), training builds the same kernel from the
//! branch parameters with tensor ops every step
//! ([`Inception2d::fuse_differentiable`]), so gradients reach the branches.

use burn::module::Param;
use burn::nn::conv::{Conv2d, Conv2dConfig, Conv3d, Conv3dConfig};
use burn::prelude::*;
use burn::tensor::module::{conv2d, conv3d};
use burn::tensor::ops::{ConvOptions, PadMode};
use burn::tensor::IndexingUpdateOp;

/// Mean of `num_kernels` 2-D convolutions, square kernels `1, 3, 5, ...`.
#[derive(Module, Debug)]
pub struct Inception2d {
    branches: Vec<Conv2d>,
}

/// Mean of 3-D convolutions with cubic kernels `1` and `3`.
#[derive(Module, Debug)]
pub struct Inception3d {
    branches: Vec<Conv3d>,
}

impl Inception2d {
    /// `channels_in -> channels_out`, kernels `1, 3, ..., 2·num_kernels − 1`.
    pub fn new(
        channels_in: usize,
        channels_out: usize,
        num_kernels: usize,
        device: &Device,
    ) -> Self {
        let branches = (0..num_kernels)
            .map(|i| {
                let k = 2 * i + 1;
                Conv2dConfig::new([channels_in, channels_out], [k, k]).init(device)
            })
            .collect();
        Inception2d { branches }
    }

    /// `[B, C_in, H, W]` -> `[B, C_out, H, W]`: one convolution with the
    /// fused kernel, built from the branches with differentiable tensor ops.
    pub fn forward(&self, x: Tensor<4>) -> Tensor<4> {
        self.fuse_differentiable().forward(x)
    }

    /// The fused convolution built with tensor ops from the branch parameters
    /// (autodiff tracks it: gradients reach every branch). Build it once per
    /// step and apply it to many inputs.
    pub fn fuse_differentiable(&self) -> FusedConv<4> {
        fuse_differentiable(
            self.branches
                .iter()
                .map(|c| (c.weight.val(), c.bias.as_ref().map(Param::val))),
        )
    }

    /// The definition: the mean of the branches, each its own convolution
    /// (the reference the fused forms are checked against).
    pub fn forward_branches(&self, x: Tensor<4>) -> Tensor<4> {
        let n = self.branches.len() as f64;
        let mut acc: Option<Tensor<4>> = None;
        for conv in &self.branches {
            let k = conv.weight.dims()[2];
            let p = k / 2;
            let y = conv2d(
                x.clone(),
                conv.weight.val(),
                conv.bias.as_ref().map(Param::val),
                ConvOptions::new([1, 1], [p, p], [1, 1], 1),
            );
            acc = Some(match acc {
                None => y,
                Some(a) => a + y,
            });
        }
        acc.expect("an Inception block has at least one branch")
            .div_scalar(n)
    }

    /// The branch convolutions (the parameters).
    pub fn branches(&self) -> &[Conv2d] {
        &self.branches
    }

    /// The single equivalent convolution.
    pub fn fuse(&self) -> FusedConv<4> {
        let weights: Vec<(Tensor<4>, Option<Tensor<1>>)> = self
            .branches
            .iter()
            .map(|c| (c.weight.val(), c.bias.as_ref().map(Param::val)))
            .collect();
        fuse_branches(&weights)
    }
}

impl Inception3d {
    /// `channels_in -> channels_out`, kernels `1` and `3` (cubic).
    pub fn new(channels_in: usize, channels_out: usize, device: &Device) -> Self {
        let branches = [1usize, 3]
            .iter()
            .map(|&k| Conv3dConfig::new([channels_in, channels_out], [k, k, k]).init(device))
            .collect();
        Inception3d { branches }
    }

    /// `[B, C_in, T, H, W]` -> `[B, C_out, T, H, W]`, "same" padding
    /// everywhere (training): [`Inception3d::forward_channel_major`] between
    /// two layout permutations.
    pub fn forward(&self, x: Tensor<5>) -> Tensor<5> {
        self.forward_channel_major(x.permute([1, 0, 2, 3, 4]))
            .permute([1, 0, 2, 3, 4])
    }

    /// Channel-major `[C_in, B, T, H, W]` -> `[C_out, B, T, H, W]`
    /// (training): the fused kernel, built from the branches with
    /// differentiable tensor ops, applied as [`conv3d_channel_major`].
    pub fn forward_channel_major(&self, x: Tensor<5>) -> Tensor<5> {
        let f = self.fuse_differentiable();
        conv3d_channel_major(x, f.weight, f.bias)
    }

    /// As [`Inception2d::fuse_differentiable`].
    pub fn fuse_differentiable(&self) -> FusedConv<5> {
        fuse_differentiable(
            self.branches
                .iter()
                .map(|c| (c.weight.val(), c.bias.as_ref().map(Param::val))),
        )
    }

    /// The definition: the mean of the branches, each its own convolution.
    pub fn forward_branches(&self, x: Tensor<5>) -> Tensor<5> {
        let n = self.branches.len() as f64;
        let mut acc: Option<Tensor<5>> = None;
        for conv in &self.branches {
            let p = conv.weight.dims()[2] / 2;
            let y = conv3d(
                x.clone(),
                conv.weight.val(),
                conv.bias.as_ref().map(Param::val),
                ConvOptions::new([1, 1, 1], [p, p, p], [1, 1, 1], 1),
            );
            acc = Some(match acc {
                None => y,
                Some(a) => a + y,
            });
        }
        acc.expect("an Inception block has at least one branch")
            .div_scalar(n)
    }

    /// The branch convolutions (the parameters).
    pub fn branches(&self) -> &[Conv3d] {
        &self.branches
    }

    /// The single equivalent convolution.
    pub fn fuse(&self) -> FusedConv<5> {
        let weights: Vec<(Tensor<5>, Option<Tensor<1>>)> = self
            .branches
            .iter()
            .map(|c| (c.weight.val(), c.bias.as_ref().map(Param::val)))
            .collect();
        fuse_branches(&weights)
    }
}

/// One convolution with an odd cubic/square kernel and "same" padding:
/// the fused form of an Inception block, for inference.
#[derive(Debug, Clone)]
pub struct FusedConv<const D: usize> {
    /// `[C_out, C_in, k, k(, k)]`.
    pub weight: Tensor<D>,
    /// `[C_out]`.
    pub bias: Tensor<1>,
    /// Kernel side `k` (odd).
    pub kernel: usize,
}

/// A "same"-padded 3-D convolution with an odd cubic kernel `k` on
/// activations kept channel-major (`[C, B, T, H, W]`: each channel's planes
/// of every sample and time slice one after the other), written as plain
/// tensor ops whose gradients are plain GEMMs and gathers, every one of
/// them over the whole batch at once:
/// 1. the `kh·kw` spatial taps of every plane gathered by one `select`
///    (im2col: `[C_in·kh·kw, B·T·H·W]`, rows in the weight's `(c, dy, dx)`
///    order, columns every pixel of every slice);
/// 2. one GEMM by the `k` time slices of the kernel stacked as output
///    channels (`[k·C_out, C_in·kh·kw]`): `[k·C_out, B·T·H·W]`;
/// 3. output time `s` sums kernel slice `j` applied at input time
///    `s + j − k/2` (zero beyond the ends): one scatter-add of the rows.
///
/// The same linear map as `conv3d`. On the CPU backend the forward is one
/// GEMM and its backward two (the weight's with the whole batch as its
/// inner dimension, the input's), plus a scatter-add for the input and a
/// gather for the time offsets: not Flex's per-element im2col iterators,
/// nor one small GEMM per time slice, whose packing cost as much as the
/// multiply-adds in the weight gradient.
/// `x` `[C_in, B, T, H, W]`, `weight` `[C_out, C_in, k, kh, kw]` -> `[C_out, B, T, H, W]`.
pub fn conv3d_channel_major(x: Tensor<5>, weight: Tensor<5>, bias: Tensor<1>) -> Tensor<5> {
    let [c_in, b, t, h, w] = x.dims();
    let [c_out, _, k, kh, kw] = weight.dims();
    let (p, ph, pw) = (k / 2, kh / 2, kw / 2);
    let (hp, wp) = (h + 2 * ph, w + 2 * pw);
    let slices = b * t;
    let device = x.device();
    let index = |v: Vec<i64>| {
        let n = v.len();
        Tensor::<1, Int>::from_data(TensorData::new(v, [n]), &device)
    };
    // 1. Spatial taps: pixel (i, j) of tap (dy, dx) reads padded (i + dy, j + dx)
    // of the same plane; columns (tap, slice, i, j) of each channel's row.
    let planes = x.reshape([c_in * slices, h, w]);
    let planes = if ph + pw > 0 {
        planes.pad(vec![(ph, ph), (pw, pw)], PadMode::Constant(0.0))
    } else {
        planes
    };
    let mut taps = Vec::with_capacity(kh * kw * slices * h * w);
    for dy in 0..kh {
        for dx in 0..kw {
            for s in 0..slices {
                for i in 0..h {
                    let row = (s * hp + i + dy) * wp + dx;
                    taps.extend((row..row + w).map(|v| v as i64));
                }
            }
        }
    }
    let cols = planes
        .reshape([c_in, slices * hp * wp])
        .select(1, index(taps))
        .reshape([c_in * kh * kw, slices * h * w]);
    // 2. [C_out, C_in, k, kh, kw] -> [k·C_out, C_in·kh·kw], time offset major.
    let w2 = weight
        .permute([2, 0, 1, 3, 4])
        .reshape([k * c_out, c_in * kh * kw]);
    let z = w2.matmul(cols); // [k·C_out, B·T·H·W]: rows (j, c), columns (b, u, i, j)
    let y = if k == 1 {
        z.reshape([c_out, b, t, h, w])
    } else {
        // 3. Plane (j, c, b, u) of z feeds output (c, b, u + p − j): one
        // scatter-add of every plane; planes that would land beyond the
        // ends go to one extra plane, dropped.
        let dropped = (c_out * slices) as i64;
        let mut dst = Vec::with_capacity(k * c_out * slices);
        for j in 0..k {
            for c in 0..c_out {
                for bi in 0..b {
                    for u in 0..t {
                        let s = (u + p).checked_sub(j).filter(|&s| s < t);
                        dst.push(s.map_or(dropped, |s| ((c * b + bi) * t + s) as i64));
                    }
                }
            }
        }
        let plane = h * w;
        Tensor::<2>::zeros([c_out * slices + 1, plane], &device)
            .select_assign(
                0,
                index(dst),
                z.reshape([k * c_out * slices, plane]),
                IndexingUpdateOp::Add,
            )
            .slice([0..c_out * slices, 0..plane])
            .reshape([c_out, b, t, h, w])
    };
    y + bias.reshape([c_out, 1, 1, 1, 1])
}

/// [`fuse_branches`] with tensor ops on the device (differentiable): each
/// branch kernel zero-padded to the largest, their mean; the biases' mean.
fn fuse_differentiable<const D: usize>(
    branches: impl ExactSizeIterator<Item = (Tensor<D>, Option<Tensor<1>>)>,
) -> FusedConv<D> {
    let n = branches.len();
    let branches: Vec<_> = branches.collect();
    let kmax = branches.iter().map(|(w, _)| w.dims()[2]).max().unwrap_or(1);
    let c_out = branches[0].0.dims()[0];
    let device = branches[0].0.device();
    let mut weight: Option<Tensor<D>> = None;
    let mut bias: Option<Tensor<1>> = None;
    for (w, b) in branches {
        let off = (kmax - w.dims()[2]) / 2;
        let w = if off > 0 {
            w.pad(vec![(off, off); D - 2], PadMode::Constant(0.0))
        } else {
            w
        };
        weight = Some(match weight {
            None => w,
            Some(acc) => acc + w,
        });
        if let Some(b) = b {
            bias = Some(match bias {
                None => b,
                Some(acc) => acc + b,
            });
        }
    }
    FusedConv {
        weight: weight
            .expect("an Inception block has at least one branch")
            .div_scalar(n as f64),
        bias: bias
            .map(|b| b.div_scalar(n as f64))
            .unwrap_or_else(|| Tensor::zeros([c_out], &device)),
        kernel: kmax,
    }
}

fn fuse_branches<const D: usize>(branches: &[(Tensor<D>, Option<Tensor<1>>)]) -> FusedConv<D> {
    let kmax = branches.iter().map(|(w, _)| w.dims()[2]).max().unwrap_or(1);
    let dims0 = branches[0].0.dims();
    let (c_out, c_in) = (dims0[0], dims0[1]);
    let spatial = D - 2;
    let kvol = kmax.pow(spatial as u32);
    let mut fused = vec![0.0f32; c_out * c_in * kvol];
    let mut bias = vec![0.0f32; c_out];
    let n = branches.len() as f32;
    let device = branches[0].0.device();
    for (w, b) in branches {
        let k = w.dims()[2];
        let off = (kmax - k) / 2;
        let data: Vec<f32> = w
            .clone()
            .into_data()
            .try_to_vec::<f32>()
            .expect("f32 weights");
        let kv = k.pow(spatial as u32);
        for oc in 0..c_out * c_in {
            for idx in 0..kv {
                // Unravel idx over `spatial` dims of size k, re-ravel at size kmax with offset.
                let mut rem = idx;
                let mut dst = 0usize;
                let mut stride_src = kv;
                for _ in 0..spatial {
                    stride_src /= k;
                    let coord = rem / stride_src;
                    rem %= stride_src;
                    dst = dst * kmax + coord + off;
                }
                fused[oc * kvol + dst] += data[oc * kv + idx] / n;
            }
        }
        if let Some(b) = b {
            let bd: Vec<f32> = b.clone().into_data().try_to_vec::<f32>().expect("f32 bias");
            for (acc, v) in bias.iter_mut().zip(bd) {
                *acc += v / n;
            }
        }
    }
    let mut shape = vec![c_out, c_in];
    shape.extend(std::iter::repeat_n(kmax, spatial));
    FusedConv {
        weight: Tensor::<D>::from_data(TensorData::new(fused, shape), &device),
        bias: Tensor::<1>::from_data(TensorData::new(bias, [c_out]), &device),
        kernel: kmax,
    }
}

impl FusedConv<4> {
    /// `[B, C_in, H, W]` -> `[B, C_out, H, W]`, "same" padding.
    pub fn forward(&self, x: Tensor<4>) -> Tensor<4> {
        let p = self.kernel / 2;
        conv2d(
            x,
            self.weight.clone(),
            Some(self.bias.clone()),
            ConvOptions::new([1, 1], [p, p], [1, 1], 1),
        )
    }
}

impl FusedConv<5> {
    /// `[B, C_in, T, H, W]` -> `[B, C_out, T, H, W]`, "same" padding.
    pub fn forward(&self, x: Tensor<5>) -> Tensor<5> {
        let p = self.kernel / 2;
        conv3d(
            x,
            self.weight.clone(),
            Some(self.bias.clone()),
            ConvOptions::new([1, 1, 1], [p, p, p], [1, 1, 1], 1),
        )
    }
}
