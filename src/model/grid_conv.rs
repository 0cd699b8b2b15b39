//! The trajectory encoder's fused Inception convolution as one im2col + GEMM,
//! read straight from the sequence (inference).
//!
//! A TimesNet block folds a sequence `[L, C]` (position-major) into a grid of
//! `rows x p` (position `n = r·p + c`, zeros after `L`) and convolves it with
//! a `k x k` kernel, "same" padding. Here the grid is never built: row `m`
//! of the im2col matrix holds, for each kernel tap `(ky, kx)`, the `C`
//! values of sequence position `(r + ky − k/2)·p + (c + kx − k/2)`, or zeros
//! where the tap leaves the grid or passes `L`. One GEMM with the weights as
//! `[k·k·C_in, C_out]` gives the outputs position-major, which is the layout
//! the next convolution reads; only the first `out_len` positions are
//! computed (the block keeps `L` of them).
//!
//! Same arithmetic as `burn`'s `conv2d` (f32 products summed, bias added),
//! in another order: equal to it within rounding (tested).

use std::cell::RefCell;
use std::sync::Arc;

use super::inception::FusedConv;

/// Output positions per im2col tile (keeps the tile in L2).
const TILE: usize = 32;

thread_local! {
    /// The im2col tile, reused between calls (no allocation per tick).
    static SCRATCH: RefCell<Vec<f32>> = const { RefCell::new(Vec::new()) };
}

/// One `k x k` "same" convolution over a folded sequence.
#[derive(Debug, Clone)]
pub struct GridConv {
    k: usize,
    c_in: usize,
    c_out: usize,
    /// `[k·k·C_in, C_out]`, row `(ky·k + kx)·C_in + ci`.
    weight: Arc<[f32]>,
    bias: Arc<[f32]>,
}

impl GridConv {
    /// From a fused 2-D convolution (`[C_out, C_in, k, k]`).
    pub fn from_fused(conv: &FusedConv<4>) -> GridConv {
        let [c_out, c_in, k, k2] = conv.weight.dims();
        assert_eq!(k, k2, "square kernel");
        let w: Vec<f32> = conv
            .weight
            .clone()
            .into_data()
            .convert::<f32>()
            .try_into_vec()
            .expect("f32 weights");
        let bias: Vec<f32> = conv
            .bias
            .clone()
            .into_data()
            .convert::<f32>()
            .try_into_vec()
            .expect("f32 bias");
        let mut weight = vec![0.0f32; k * k * c_in * c_out];
        for co in 0..c_out {
            for ci in 0..c_in {
                for ky in 0..k {
                    for kx in 0..k {
                        weight[((ky * k + kx) * c_in + ci) * c_out + co] =
                            w[((co * c_in + ci) * k + ky) * k + kx];
                    }
                }
            }
        }
        GridConv {
            k,
            c_in,
            c_out,
            weight: weight.into(),
            bias: bias.into(),
        }
    }

    /// Output channels.
    pub fn c_out(&self) -> usize {
        self.c_out
    }

    /// `x` `[len, C_in]` position-major, folded as `rows x p` (`len <= rows·p`,
    /// zeros after `len`) -> the first `out_len` positions of the output,
    /// `[out_len, C_out]`.
    pub fn forward(&self, x: &[f32], rows: usize, p: usize, out_len: usize) -> Vec<f32> {
        let (k, c_in, c_out) = (self.k, self.c_in, self.c_out);
        assert_eq!(x.len() % c_in, 0, "input width");
        let len = x.len() / c_in;
        assert!(
            len <= rows * p && out_len <= rows * p,
            "sequence fits the grid"
        );
        let kk = k * k * c_in;
        let half = (k / 2) as isize;
        let mut out = vec![0.0f32; out_len * c_out];
        for row in out.chunks_exact_mut(c_out) {
            row.copy_from_slice(&self.bias);
        }
        SCRATCH.with(|s| {
            let mut a = s.borrow_mut();
            a.resize(TILE * kk, 0.0);
            let mut m0 = 0;
            while m0 < out_len {
                let tile = TILE.min(out_len - m0);
                for t in 0..tile {
                    let m = m0 + t;
                    let (r, c) = ((m / p) as isize, (m % p) as isize);
                    let arow = &mut a[t * kk..(t + 1) * kk];
                    for ky in 0..k {
                        let rr = r + ky as isize - half;
                        for kx in 0..k {
                            let cc = c + kx as isize - half;
                            let dst = &mut arow[(ky * k + kx) * c_in..(ky * k + kx + 1) * c_in];
                            let inside =
                                rr >= 0 && rr < rows as isize && cc >= 0 && cc < p as isize;
                            let n = (rr * p as isize + cc) as usize;
                            if inside && n < len {
                                dst.copy_from_slice(&x[n * c_in..(n + 1) * c_in]);
                            } else {
                                dst.fill(0.0);
                            }
                        }
                    }
                }
                let dst = &mut out[m0 * c_out..(m0 + tile) * c_out];
                // SAFETY: `dst` is `tile x c_out`, `a` at least `tile x kk`,
                // `weight` `kk x c_out`, all row-major with the strides given;
                // no two overlap.
                unsafe {
                    gemm::gemm(
                        tile,
                        c_out,
                        kk,
                        dst.as_mut_ptr(),
                        1,
                        c_out as isize,
                        true,
                        a.as_ptr(),
                        1,
                        kk as isize,
                        self.weight.as_ptr(),
                        1,
                        c_out as isize,
                        1.0f32,
                        1.0f32,
                        false,
                        false,
                        false,
                        gemm::Parallelism::None,
                    );
                }
                m0 += tile;
            }
        });
        out
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::model::cpu_device;
    use crate::model::inception::Inception2d;
    use burn::prelude::*;
    use burn::tensor::Distribution;

    /// Against burn's conv2d on the explicitly folded, zero-padded grid.
    #[test]
    fn equals_conv2d_on_the_folded_grid() {
        let device = cpu_device();
        let (c_in, c_out, l) = (6usize, 5usize, 45usize);
        let fused = Inception2d::new(c_in, c_out, 3, &device).fuse();
        let conv = GridConv::from_fused(&fused);
        let x = Tensor::<2>::random([l, c_in], Distribution::Normal(0.0, 1.0), &device);
        let xs: Vec<f32> = x.clone().into_data().try_into_vec().unwrap();
        for p in [1usize, 2, 3, 4, 5, 7, 12, 45] {
            let rows = l.div_ceil(p);
            let lp = rows * p;
            let padded = if lp > l {
                Tensor::cat(vec![x.clone(), Tensor::zeros([lp - l, c_in], &device)], 0)
            } else {
                x.clone()
            };
            let grid = padded.reshape([1, rows, p, c_in]).permute([0, 3, 1, 2]);
            let want: Vec<f32> = fused
                .forward(grid)
                .permute([0, 2, 3, 1])
                .reshape([lp, c_out])
                .into_data()
                .try_into_vec()
                .unwrap();
            for out_len in [l, lp] {
                let got = conv.forward(&xs, rows, p, out_len);
                assert_eq!(got.len(), out_len * c_out);
                for (i, (g, w)) in got.iter().zip(&want).enumerate() {
                    assert!((g - w).abs() < 1e-5, "p {p} at {i}: {g} vs {w}");
                }
            }
        }
    }
}
