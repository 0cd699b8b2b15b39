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
//! computed (the block keeps `L` of them). The grid is taken a row at a
//! time, and the kernel rows that fall wholly above or below the grid's
//! data from that row are left out of the GEMM: a long period folds a plan
//! into few rows (2 rows for half the plan), where most of a 5x5 kernel
//! reads padding.
//!
//! A TimesNet block folds the same input at up to `top_k` periods, and its
//! second convolution's outputs are summed with weights. Two more entries
//! use that (the block chooses by [`HostConv::grid_taps`], the count of
//! products each way):
//! - [`HostConv::tap_products`] (`host_conv`) multiplies every input
//!   position by every kernel tap once; [`HostConv::forward_grid_from_taps`]
//!   then makes any period's output by sums alone (also taken, whatever
//!   the counts, when the block's input is its last one slid by a row and
//!   only the new row's products are made: `plan.rs`, `TapRows`);
//! - [`HostConv::forward_grids_summed`] runs the weighted periods through one
//!   GEMM (the weighted sum of their im2col matrices: the convolution is
//!   linear).
//!
//! Either way, a block costs about two full convolutions whatever its
//! periods; folding each period on its own cost up to six.
//!
//! Same arithmetic as `burn`'s `conv2d` (f32 products summed, bias added),
//! in another order: equal to it within rounding (tested).

use super::host_conv::{HostConv, Product, Strides};

/// One input of [`HostConv::forward_grids_summed`]: a sequence
/// `[len, C_in]`, its folding `rows x p` and its weight in the sum.
#[derive(Debug, Clone, Copy)]
pub struct WeightedGrid<'a> {
    pub x: &'a [f32],
    pub rows: usize,
    pub p: usize,
    pub weight: f32,
}

/// Output positions per im2col tile (keeps the tile in L2).
const TILE: usize = 32;

/// Periods up to this are convolved a grid column at a time
/// ([`HostConv::grid_by_column`]).
const BY_COLUMN_MAX_PERIOD: usize = 16;

/// Output positions per tile there (one GEMM per tile).
const COLUMN_TILE: usize = 64;

/// Positions of a sequence of `values` numbers, `width` per position,
/// checked to fit, with the `out_len` outputs, a `rows x p` grid.
fn grid_len(values: usize, width: usize, rows: usize, p: usize, out_len: usize) -> usize {
    assert!(values.is_multiple_of(width), "{width} values per position");
    let len = values / width;
    assert!(
        len <= rows * p && out_len <= rows * p,
        "sequence fits the grid"
    );
    len
}

/// The kernel taps of a `k x k` "same" convolution on a sequence of `len`
/// positions folded by period `p` that land on the sequence from output
/// position `m`, in row-major tap order: `f(tap, n)` with `n` the sequence
/// position the tap reads. Taps off the grid's columns, above its first
/// row or at or past `len` read zeros and are not given.
#[inline(always)]
fn for_each_landing_tap(k: usize, p: usize, len: usize, m: usize, mut f: impl FnMut(usize, usize)) {
    let (half, r, c) = (k / 2, m / p, m % p);
    // Kernel columns that stay in the grid's columns.
    let (kx_lo, kx_hi) = (half.saturating_sub(c), (p + half - c).min(k));
    for ky in half.saturating_sub(r)..k {
        // Sequence position of tap (ky, kx_lo); later taps follow it.
        let first = (r + ky - half) * p + c + kx_lo - half;
        for (kx, n) in (kx_lo..kx_hi).zip(first..len) {
            f(ky * k + kx, n);
        }
    }
}

impl HostConv {
    /// `x` `[len, C_in]` position-major, folded as `rows x p` (`len <= rows·p`,
    /// zeros after `len`) -> the first `out_len` positions of the output,
    /// `[out_len, C_out]`.
    pub fn forward_grid(&self, x: &[f32], rows: usize, p: usize, out_len: usize) -> Vec<f32> {
        let (k, c_in, c_out) = (self.k(), self.c_in(), self.c_out());
        let len = grid_len(x.len(), c_in, rows, p, out_len);
        let half = k / 2;
        // Rows of the grid holding any of the `len` positions; rows past
        // them, like rows past the grid, are zero padding.
        let data_rows = len.div_ceil(p);
        let mut out = vec![0.0f32; out_len * c_out];
        for row in out.chunks_exact_mut(c_out) {
            row.copy_from_slice(self.bias());
        }
        if p <= BY_COLUMN_MAX_PERIOD && p < rows {
            self.grid_by_column(x, p, &mut out);
            return out;
        }
        // The kernel rows that reach a data row from grid row `r`; the others
        // read only zeros and are left out of the GEMM.
        let kernel_rows = |r: usize| {
            (
                half.saturating_sub(r),
                (data_rows + half).saturating_sub(r).min(k),
            )
        };
        HostConv::with_scratch(TILE * k * k * c_in, |a| {
            // Runs of grid rows that use the same kernel rows (the interior
            // of the grid is one run), tiled by positions.
            let mut r = 0;
            while r * p < out_len {
                let (ky_lo, ky_hi) = kernel_rows(r);
                let mut r_end = r + 1;
                while r_end * p < out_len && kernel_rows(r_end) == (ky_lo, ky_hi) {
                    r_end += 1;
                }
                let run_end = (r_end * p).min(out_len);
                if ky_lo < ky_hi {
                    let kk = (ky_hi - ky_lo) * k * c_in;
                    let mut m0 = r * p;
                    while m0 < run_end {
                        let tile = TILE.min(run_end - m0);
                        for t in 0..tile {
                            let m = m0 + t;
                            let (rm, c) = (m / p, (m % p) as isize);
                            let arow = &mut a[t * kk..(t + 1) * kk];
                            for ky in ky_lo..ky_hi {
                                let rr = rm + ky - half;
                                for kx in 0..k {
                                    let cc = c + kx as isize - half as isize;
                                    let at = ((ky - ky_lo) * k + kx) * c_in;
                                    let dst = &mut arow[at..at + c_in];
                                    let n = rr * p + cc.max(0) as usize;
                                    if cc >= 0 && cc < p as isize && n < len {
                                        dst.copy_from_slice(&x[n * c_in..(n + 1) * c_in]);
                                    } else {
                                        dst.fill(0.0);
                                    }
                                }
                            }
                        }
                        let row_major = |cols| Strides { row: cols, col: 1 };
                        self.accumulate_taps(
                            ky_lo * k..ky_hi * k,
                            Product {
                                m: tile,
                                dst: &mut out[m0 * c_out..(m0 + tile) * c_out],
                                dst_s: row_major(c_out),
                                a: &a[..tile * kk],
                                a_s: row_major(kk),
                            },
                        );
                        m0 += tile;
                    }
                }
                r = r_end;
            }
        });
        out
    }

    /// [`forward_grid`](Self::forward_grid) from the input's
    /// [`tap_products`](Self::tap_products) `y` (`[len, taps·C_out]`): each
    /// output position is the bias plus the products of the taps that land
    /// on the sequence (row-major tap order), with no multiplication left.
    /// A block folds one input at up to `top_k` periods; with the products
    /// made once, each further period costs only these sums.
    pub fn forward_grid_from_taps(
        &self,
        y: &[f32],
        rows: usize,
        p: usize,
        out_len: usize,
    ) -> Vec<f32> {
        let (k, c_out) = (self.k(), self.c_out());
        let len = grid_len(y.len(), k * k * c_out, rows, p, out_len);
        let mut out = vec![0.0f32; out_len * c_out];
        #[cfg(target_arch = "x86_64")]
        {
            if std::arch::is_x86_feature_detected!("avx2") {
                // SAFETY: the CPU has AVX2 (checked just above).
                unsafe { self.sums_of_taps_avx2(y, p, len, &mut out) };
                return out;
            }
        }
        self.sums_of_taps(y, p, len, &mut out);
        out
    }

    /// [`forward_grid_from_taps`](Self::forward_grid_from_taps)'s sums
    /// with 8 lanes at a time (each value's additions the same and in the
    /// same order, so the same bits as the portable loop).
    #[cfg(target_arch = "x86_64")]
    #[target_feature(enable = "avx2")]
    fn sums_of_taps_avx2(&self, y: &[f32], p: usize, len: usize, out: &mut [f32]) {
        self.sums_of_taps(y, p, len, out);
    }

    /// `out` `[out_len, C_out]`: the bias plus the landing taps' products.
    #[inline(always)]
    fn sums_of_taps(&self, y: &[f32], p: usize, len: usize, out: &mut [f32]) {
        let (k, c_out) = (self.k(), self.c_out());
        let width = k * k * c_out;
        for (m, o) in out.chunks_exact_mut(c_out).enumerate() {
            o.copy_from_slice(self.bias());
            for_each_landing_tap(k, p, len, m, |tap, n| {
                let at = n * width + tap * c_out;
                for (a, v) in o.iter_mut().zip(&y[at..at + c_out]) {
                    *a += v;
                }
            });
        }
    }

    /// `Σ_i w_i · forward_grid(x_i, rows_i, p_i, out_len)` as one GEMM:
    /// the convolution is linear, so the weighted sum of the periods'
    /// im2col matrices times the weights is the weighted sum of their
    /// outputs. Each `x_i` is `[len_i, C_in]` position-major, folded as
    /// `rows_i x p_i`; the bias is added once, times `Σ_i w_i`. Every
    /// kernel tap is in the GEMM (`out_len · k²` multiplied, whatever the
    /// periods), so it pays when the periods together would multiply more.
    pub fn forward_grids_summed(&self, grids: &[WeightedGrid<'_>], out_len: usize) -> Vec<f32> {
        let (k, c_in, c_out) = (self.k(), self.c_in(), self.c_out());
        for g in grids {
            grid_len(g.x.len(), c_in, g.rows, g.p, out_len);
        }
        let w_sum: f32 = grids.iter().map(|g| g.weight).sum();
        let mut out = vec![0.0f32; out_len * c_out];
        for row in out.chunks_exact_mut(c_out) {
            for (o, b) in row.iter_mut().zip(self.bias()) {
                *o = b * w_sum;
            }
        }
        let kk = k * k * c_in;
        // Per im2col row: whether some grid lands on each tap.
        let mut landed = vec![false; k * k];
        HostConv::with_scratch(TILE * kk, |a| {
            let mut m0 = 0;
            while m0 < out_len {
                let tile = TILE.min(out_len - m0);
                let a = &mut a[..tile * kk];
                for (t, arow) in a.chunks_exact_mut(kk).enumerate() {
                    let m = m0 + t;
                    // A tap's first landing stores (`0 + w·v` is `w·v`:
                    // the same bits as adding to zeros), later ones add;
                    // the taps no grid lands on are zeroed once at the
                    // end, so the tile is not cleared first.
                    landed.fill(false);
                    for g in grids {
                        for_each_landing_tap(k, g.p, g.x.len() / c_in, m, |tap, n| {
                            let src = &g.x[n * c_in..(n + 1) * c_in];
                            let dst = &mut arow[tap * c_in..(tap + 1) * c_in];
                            if landed[tap] {
                                for (d, v) in dst.iter_mut().zip(src) {
                                    *d += g.weight * v;
                                }
                            } else {
                                landed[tap] = true;
                                for (d, v) in dst.iter_mut().zip(src) {
                                    *d = g.weight * v;
                                }
                            }
                        });
                    }
                    for (tap, &hit) in landed.iter().enumerate() {
                        if !hit {
                            arow[tap * c_in..(tap + 1) * c_in].fill(0.0);
                        }
                    }
                }
                let row_major = |cols| Strides { row: cols, col: 1 };
                self.accumulate_taps(
                    0..k * k,
                    Product {
                        m: tile,
                        dst: &mut out[m0 * c_out..(m0 + tile) * c_out],
                        dst_s: row_major(c_out),
                        a,
                        a_s: row_major(kk),
                    },
                );
                m0 += tile;
            }
        });
        out
    }

    /// Positions times kernel taps that [`forward_grid`](Self::forward_grid)
    /// multiplies for this folding (its GEMMs' rows times their taps), to
    /// choose between it and [`tap_products`](Self::tap_products), which
    /// multiplies `len · k²`.
    pub fn grid_taps(&self, len: usize, rows: usize, p: usize, out_len: usize) -> usize {
        let (k, half) = (self.k(), self.k() / 2);
        if p <= BY_COLUMN_MAX_PERIOD && p < rows {
            (0..p)
                .map(|c| {
                    let cols = (p + half - c).min(k) - half.saturating_sub(c);
                    let positions = (out_len + p - 1 - c) / p;
                    positions * cols * k
                })
                .sum()
        } else {
            let data_rows = len.div_ceil(p);
            (0..out_len.div_ceil(p))
                .map(|r| {
                    let lo = half.saturating_sub(r);
                    let hi = (data_rows + half).saturating_sub(r).min(k);
                    let positions = p.min(out_len - r * p);
                    positions * hi.saturating_sub(lo) * k
                })
                .sum()
        }
    }

    /// [`forward_grid`](Self::forward_grid) for a short period: the
    /// positions taken a grid column at a time, each with only the kernel
    /// columns that reach the grid from it (for `p = 3`, 3 of 5 from every
    /// column), one GEMM per tile with the weights laid out by kernel
    /// column ([`HostConv::accumulate_kernel_columns`]). Kernel rows are not restricted here: a
    /// short period folds the plan into many rows, where only the first
    /// and last `k/2` read padding. `out` holds the bias.
    fn grid_by_column(&self, x: &[f32], p: usize, out: &mut [f32]) {
        let (k, c_in, c_out) = (self.k(), self.c_in(), self.c_out());
        let (len, out_len, half) = (x.len() / c_in, out.len() / c_out, k / 2);
        let kernel_cols = |c: usize| (half.saturating_sub(c), (p + half - c).min(k));
        let mut tmp = vec![0.0f32; COLUMN_TILE * c_out];
        let mut positions: Vec<usize> = Vec::with_capacity(COLUMN_TILE);
        HostConv::with_scratch(COLUMN_TILE * k * k * c_in, |a| {
            let mut c0 = 0;
            while c0 < p {
                // Neighbouring columns with the same kernel columns (the
                // interior of a wide grid) are taken together.
                let (kx_lo, kx_hi) = kernel_cols(c0);
                let mut c1 = c0 + 1;
                while c1 < p && kernel_cols(c1) == (kx_lo, kx_hi) {
                    c1 += 1;
                }
                let nkx = kx_hi - kx_lo;
                let kk = k * nkx * c_in;
                let mut all = (0..out_len).filter(|m| (c0..c1).contains(&(m % p)));
                loop {
                    positions.clear();
                    positions.extend(all.by_ref().take(COLUMN_TILE));
                    if positions.is_empty() {
                        break;
                    }
                    let tile = positions.len();
                    for (t, &m) in positions.iter().enumerate() {
                        let (r, c) = ((m / p) as isize, m % p);
                        let arow = &mut a[t * kk..(t + 1) * kk];
                        for ky in 0..k {
                            let rr = r + ky as isize - half as isize;
                            for kx in kx_lo..kx_hi {
                                // In the grid's columns by the choice of kx.
                                let cc = c + kx - half;
                                let at = ((kx - kx_lo) * k + ky) * c_in;
                                let dst = &mut arow[at..at + c_in];
                                match usize::try_from(rr).map(|rr| rr * p + cc) {
                                    Ok(n) if n < len => {
                                        dst.copy_from_slice(&x[n * c_in..(n + 1) * c_in])
                                    }
                                    _ => dst.fill(0.0),
                                }
                            }
                        }
                    }
                    let out_tile = &mut tmp[..tile * c_out];
                    out_tile.fill(0.0);
                    let rows_of = |cols| Strides { row: cols, col: 1 };
                    self.accumulate_kernel_columns(
                        kx_lo..kx_hi,
                        Product {
                            m: tile,
                            dst: out_tile,
                            dst_s: rows_of(c_out),
                            a: &a[..tile * kk],
                            a_s: rows_of(kk),
                        },
                    );
                    for (&m, part) in positions.iter().zip(out_tile.chunks_exact(c_out)) {
                        for (o, v) in out[m * c_out..(m + 1) * c_out].iter_mut().zip(part) {
                            *o += v;
                        }
                    }
                }
                c0 = c1;
            }
        });
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::model::cpu_device;
    use crate::model::inception::Inception2d;
    use burn::prelude::*;
    use burn::tensor::Distribution;

    /// Against burn's conv2d on the explicitly folded, zero-padded grid,
    /// both ways: folded im2col and summed tap products.
    #[test]
    fn equals_conv2d_on_the_folded_grid() {
        let device = cpu_device();
        let (c_in, c_out, l) = (6usize, 5usize, 45usize);
        let fused = Inception2d::new(c_in, c_out, 3, &device).fuse();
        let conv = HostConv::from_fused(&fused).with_tap_products();
        let x = Tensor::<2>::random([l, c_in], Distribution::Normal(0.0, 1.0), &device);
        let xs: Vec<f32> = x.clone().into_data().try_into_vec().unwrap();
        let y = conv.tap_products(&xs);
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
                let folded = conv.forward_grid(&xs, rows, p, out_len);
                let from_taps = conv.forward_grid_from_taps(&y, rows, p, out_len);
                for (how, got) in [("folded", folded), ("from taps", from_taps)] {
                    assert_eq!(got.len(), out_len * c_out);
                    for (i, (g, w)) in got.iter().zip(&want).enumerate() {
                        assert!((g - w).abs() < 1e-5, "{how} p {p} at {i}: {g} vs {w}");
                    }
                }
            }
        }
    }

    /// The tap count is what the GEMMs multiply: a single-row fold
    /// (period = length) keeps one kernel row; a period of 2 keeps two
    /// kernel columns of every column's taps.
    #[test]
    fn grid_taps_counts_the_multiplied_taps() {
        let device = cpu_device();
        let conv = HostConv::from_fused(&Inception2d::new(2, 2, 3, &device).fuse());
        assert_eq!(conv.k(), 5);
        // One row: kernel row 2 only, all five columns (some read padding).
        assert_eq!(conv.grid_taps(45, 1, 45, 45), 45 * 5);
        // p = 2, 23 rows: every column reaches 2 kernel columns, 5 rows each.
        assert_eq!(conv.grid_taps(45, 23, 2, 46), 46 * 2 * 5);
    }

    /// One GEMM over the weighted periods equals the weighted sum of each
    /// period folded on its own, for short (by-column) and long (by-row)
    /// periods, each input as long as its grid (a block's hidden layer).
    #[test]
    fn summed_grids_equal_the_weighted_sum_of_each() {
        let device = cpu_device();
        let (c_in, c_out, l) = (6usize, 5usize, 45usize);
        let conv = HostConv::from_fused(&Inception2d::new(c_in, c_out, 3, &device).fuse());
        for periods in [[2usize, 3, 5], [7, 12, 45], [4, 23, 9]] {
            let weights = [0.5f32, 0.3, 0.2];
            let xs: Vec<Vec<f32>> = periods
                .iter()
                .map(|&p| {
                    let lp = l.div_ceil(p) * p;
                    Tensor::<1>::random([lp * c_in], Distribution::Normal(0.0, 1.0), &device)
                        .into_data()
                        .try_into_vec()
                        .unwrap()
                })
                .collect();
            let mut want = vec![0.0f32; l * c_out];
            for ((x, &p), &w) in xs.iter().zip(&periods).zip(&weights) {
                let y = conv.forward_grid(x, l.div_ceil(p), p, l);
                want.iter_mut().zip(&y).for_each(|(a, v)| *a += w * v);
            }
            let grids: Vec<WeightedGrid> = xs
                .iter()
                .zip(&periods)
                .zip(&weights)
                .map(|((x, &p), &weight)| WeightedGrid {
                    x,
                    rows: l.div_ceil(p),
                    p,
                    weight,
                })
                .collect();
            let got = conv.forward_grids_summed(&grids, l);
            assert_eq!(got.len(), want.len());
            for (i, (g, w)) in got.iter().zip(&want).enumerate() {
                assert!((g - w).abs() < 1e-5, "{periods:?} at {i}: {g} vs {w}");
            }
        }
    }
}
