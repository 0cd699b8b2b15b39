//! Inception blocks: the mean of parallel "same"-padded convolutions with
//! kernels `1, 3, 5, ...`, and their exact fusion into one convolution.
//!
//! Training uses the branches ([`Inception2d`], [`Inception3d`]); inference
//! uses [`FusedConv`], whose kernel is the mean of the zero-padded branch
//! kernels (the same linear map, fewer multiply-adds).

use burn::module::Param;
use burn::nn::conv::{Conv2d, Conv2dConfig, Conv3d, Conv3dConfig};
use burn::prelude::*;
use burn::tensor::module::{conv2d, conv3d};
use burn::tensor::ops::ConvOptions;

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

    /// `[B, C_in, H, W]` -> `[B, C_out, H, W]`.
    pub fn forward(&self, x: Tensor<4>) -> Tensor<4> {
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

    /// `[B, C_in, T, H, W]` -> `[B, C_out, T, H, W]`, "same" padding everywhere.
    pub fn forward(&self, x: Tensor<5>) -> Tensor<5> {
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

    /// As [`forward`](Self::forward) but without padding in time ("valid"):
    /// the streaming encoder inserts the zero slices itself, only where the
    /// window really ends.
    pub fn forward_valid_time(&self, x: Tensor<5>) -> Tensor<5> {
        let p = self.kernel / 2;
        conv3d(
            x,
            self.weight.clone(),
            Some(self.bias.clone()),
            ConvOptions::new([1, 1, 1], [0, p, p], [1, 1, 1], 1),
        )
    }
}
