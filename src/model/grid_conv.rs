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

use super::host_conv::{HostConv, Strides};

/// Output positions per im2col tile (keeps the tile in L2).
const TILE: usize = 32;

impl HostConv {
    /// `x` `[len, C_in]` position-major, folded as `rows x p` (`len <= rows·p`,
    /// zeros after `len`) -> the first `out_len` positions of the output,
    /// `[out_len, C_out]`.
    pub fn forward_grid(&self, x: &[f32], rows: usize, p: usize, out_len: usize) -> Vec<f32> {
        let (k, c_in, c_out) = (self.k(), self.c_in(), self.c_out());
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
            row.copy_from_slice(self.bias());
        }
        HostConv::with_scratch(TILE * kk, |a| {
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
                let row_major = |cols| Strides { row: cols, col: 1 };
                self.accumulate(
                    tile,
                    &mut out[m0 * c_out..(m0 + tile) * c_out],
                    row_major(c_out),
                    &a[..tile * kk],
                    row_major(kk),
                );
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
        let conv = HostConv::from_fused(&fused);
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
                let got = conv.forward_grid(&xs, rows, p, out_len);
                assert_eq!(got.len(), out_len * c_out);
                for (i, (g, w)) in got.iter().zip(&want).enumerate() {
                    assert!((g - w).abs() < 1e-5, "p {p} at {i}: {g} vs {w}");
                }
            }
        }
    }
}
