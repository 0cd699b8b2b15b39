//! Trajectory encoder (M): the planned motion, past and future, TimesNet-style.
//!
//! In: standardised plan `[B, L, C]`, `L = N + h_K`. Out: features `[B, L·d_t]`.
//! A linear embedding `C -> d_t`, then `num_times` TimesNet blocks: per sample,
//! the `top_k` periods of largest DFT amplitude (DC dropped), each folded into a
//! 2-D grid and passed through Inception2d -> GELU -> Inception2d, summed with
//! softmax weights of their amplitudes, residual, LayerNorm over `d_t`.

use std::sync::{Mutex, OnceLock};

use burn::nn::{LayerNorm, LayerNormConfig, Linear, LinearConfig};
use burn::prelude::*;
use burn::tensor::activation::{gelu, softmax};
use burn::tensor::IndexingUpdateOp;

use super::config::ModelConfig;
use super::grid_conv::WeightedGrid;
use super::host_conv::HostConv;
use super::inception::{FusedConv, Inception2d};
use super::spectral::dft_matrices;

/// One TimesNet block.
#[derive(Module, Debug)]
pub struct TimesBlock {
    conv_in: Inception2d,
    conv_out: Inception2d,
    norm: LayerNorm,
}

/// The trajectory encoder.
#[derive(Module, Debug)]
pub struct PlanEncoder {
    embed: Linear,
    blocks: Vec<TimesBlock>,
    top_k: usize,
}

/// The two fused convolutions of each block, for inference, the DFT
/// matrices of the plan length, made on the first forward (not every tick),
/// and each block's last tap products, kept for the next forward.
#[derive(Debug)]
pub struct PlanFused {
    blocks: Vec<[HostConv; 2]>,
    dft: OnceLock<Dft>,
    tap_rows: Vec<Mutex<TapRows>>,
}

impl Clone for PlanFused {
    /// The same weights; nothing kept from earlier forwards.
    fn clone(&self) -> Self {
        PlanFused {
            blocks: self.blocks.clone(),
            dft: self.dft.clone(),
            tap_rows: self.blocks.iter().map(|_| Mutex::default()).collect(),
        }
    }
}

/// A block's first-convolution tap products ([`HostConv::tap_products`]),
/// kept from one forward to the next. Between two plan messages the plan
/// window slides one tick over the same plan, so the first block's input
/// is the last one's rows moved up by one and a new last row; the products
/// of a row depend on that row alone, so only the new row is multiplied.
/// (The second block's input changes everywhere: it is computed whole.)
#[derive(Debug, Default)]
struct TapRows {
    /// The block's last input rows `[L, d]`, whichever way it was computed.
    x: Vec<f32>,
    /// Whether `y` holds the products of `x` (not when the block last
    /// folded each period on its own).
    has_y: bool,
    /// Rows `start..start + L` are the products of `x`, `taps·C_out` each;
    /// up to `2L` rows once the window has slid, so that a slide moves
    /// `start` instead of the rows (they are moved back once every `L`).
    y: Vec<f32>,
    start: usize,
    /// Rows multiplied and rows reused, for tests and benchmarks.
    computed: u64,
    reused: u64,
}

impl TapRows {
    /// Whether `x` (`[L, d]`) is the block's last input slid by one row
    /// (bit for bit).
    fn slides(&self, x: &[f32], d: usize) -> bool {
        let l = x.len() / d;
        l > 1
            && self.x.len() == x.len()
            && x[..(l - 1) * d]
                .iter()
                .zip(&self.x[d..])
                .all(|(a, b)| a.to_bits() == b.to_bits())
    }

    /// The block took its input `x` another way: no products kept, but
    /// the next input can still be seen to slide from it.
    fn without_products(&mut self, x: &[f32]) {
        self.x.clear();
        self.x.extend_from_slice(x);
        self.has_y = false;
    }

    /// The tap products of `x` (`[L, d]`), reusing the last call's rows
    /// where `x` is its input slid by one row (`slides`, as
    /// [`slides`](Self::slides) said of it; bit for bit).
    fn products(&mut self, conv: &HostConv, x: &[f32], d: usize, slides: bool) -> &[f32] {
        let l = x.len() / d;
        let n = conv.k() * conv.k() * conv.c_out();
        let slid = slides && self.has_y && self.y.len() >= l * n;
        if slid {
            if self.y.len() < 2 * l * n {
                self.y.resize(2 * l * n, 0.0);
            }
            if self.start + l == 2 * l {
                let from = (self.start + 1) * n;
                self.y.copy_within(from..from + (l - 1) * n, 0);
                self.start = 0;
            } else {
                self.start += 1;
            }
            let last = (self.start + l - 1) * n;
            conv.tap_products_of_rows(&x[(l - 1) * d..], &mut self.y[last..last + n]);
            self.computed += 1;
            self.reused += (l - 1) as u64;
        } else {
            if self.y.len() < l * n {
                self.y.resize(l * n, 0.0);
            }
            self.start = 0;
            conv.tap_products_of_rows(x, &mut self.y[..l * n]);
            self.computed += l as u64;
        }
        self.x.clear();
        self.x.extend_from_slice(x);
        self.has_y = true;
        &self.y[self.start * n..(self.start + l) * n]
    }
}

impl PlanFused {
    /// Every convolution's products in integers ([`HostConv::to_int8`]).
    pub fn to_int8(&mut self) {
        for block in &mut self.blocks {
            for conv in block.iter_mut() {
                *conv = conv.clone().to_int8();
            }
        }
        self.tap_rows.fill_with(Mutex::default);
    }

    /// The first block's tap-product rows reused from the forward before
    /// and those multiplied, since these convolutions were made.
    pub fn tap_rows(&self) -> (u64, u64) {
        self.tap_rows.first().map_or((0, 0), |rows| {
            let kept = rows.lock().unwrap_or_else(|e| e.into_inner());
            (kept.reused, kept.computed)
        })
    }
}

/// `cos` and `sin` DFT rows of one length, transposed: `[1, L, L/2 + 1]` each.
#[derive(Debug, Clone)]
struct Dft {
    len: usize,
    cos_t: Tensor<3>,
    sin_t: Tensor<3>,
}

impl Dft {
    fn new(l: usize, device: &Device) -> Dft {
        let (cos, sin) = dft_matrices(l);
        let nf = l / 2 + 1;
        let t = |m: Vec<f32>| {
            Tensor::<2>::from_data(TensorData::new(m, [nf, l]), device)
                .transpose()
                .unsqueeze::<3>()
        };
        Dft {
            len: l,
            cos_t: t(cos),
            sin_t: t(sin),
        }
    }
}

impl PlanEncoder {
    /// A freshly initialised encoder.
    pub fn new(cfg: &ModelConfig, device: &Device) -> Self {
        PlanEncoder {
            embed: LinearConfig::new(cfg.n_joints, cfg.plan_d).init(device),
            blocks: (0..cfg.num_times)
                .map(|_| TimesBlock {
                    conv_in: Inception2d::new(cfg.plan_d, cfg.inc_dim, cfg.num_kernels, device),
                    conv_out: Inception2d::new(cfg.inc_dim, cfg.plan_d, cfg.num_kernels, device),
                    norm: LayerNormConfig::new(cfg.plan_d).init(device),
                })
                .collect(),
            top_k: cfg.top_k,
        }
    }

    /// Number of features per sample, `L·d_t`.
    pub fn out_features(cfg: &ModelConfig) -> usize {
        cfg.plan_len() * cfg.plan_d
    }

    /// Fuses every Inception block (inference).
    pub fn fuse(&self) -> PlanFused {
        PlanFused {
            blocks: self
                .blocks
                .iter()
                .map(|b| {
                    [
                        HostConv::from_fused(&b.conv_in.fuse()).with_tap_products(),
                        HostConv::from_fused(&b.conv_out.fuse()),
                    ]
                })
                .collect(),
            dft: OnceLock::new(),
            tap_rows: self.blocks.iter().map(|_| Mutex::default()).collect(),
        }
    }

    /// The fused convolutions built with tensor ops from the branch
    /// parameters (training: gradients reach the branches).
    pub fn fuse_differentiable(&self) -> Vec<[FusedConv<4>; 2]> {
        self.blocks
            .iter()
            .map(|b| {
                [
                    b.conv_in.fuse_differentiable(),
                    b.conv_out.fuse_differentiable(),
                ]
            })
            .collect()
    }

    /// `[B, L, C]` -> `[B, L·d_t]`; `fused` selects the fused convolutions.
    pub fn forward(&self, plan: Tensor<3>, fused: Option<&PlanFused>) -> Tensor<2> {
        let [b, l, _] = plan.dims();
        let device = plan.device();
        let nf = l / 2 + 1;
        let fresh;
        let dft = match fused {
            Some(f) => {
                let d = f.dft.get_or_init(|| Dft::new(l, &device));
                if d.len == l {
                    d
                } else {
                    fresh = Dft::new(l, &device);
                    &fresh
                }
            }
            None => {
                fresh = Dft::new(l, &device);
                &fresh
            }
        };
        let (cos_t, sin_t) = (&dft.cos_t, &dft.sin_t);
        let mut x = self.embed.forward(plan); // [B, L, d]
        let d = x.dims()[2];
        // Training: the fused kernels built from the branch parameters with
        // tensor ops (differentiable), once per forward, not once per grid.
        let train_fused = match fused {
            Some(_) => Vec::new(),
            None => self.fuse_differentiable(),
        };
        for (bi, block) in self.blocks.iter().enumerate() {
            // Amplitude per frequency, averaged over channels: [B, F].
            let xt = x.clone().swap_dims(1, 2); // [B, d, L]
            let re = xt.clone().matmul(cos_t.clone());
            let im = xt.matmul(sin_t.clone());
            let amp = (re.powi_scalar(2) + im.powi_scalar(2))
                .add_scalar(1e-12)
                .sqrt();
            let amp = amp.mean_dim(1).reshape([b, nf]); // [B, F]
                                                        // Top-k frequencies per sample (not differentiated).
            let amp_host: Vec<f32> = amp
                .clone()
                .detach()
                .into_data()
                .try_to_vec::<f32>()
                .expect("f32 amplitudes");
            let k = self.top_k.min(nf.saturating_sub(1)).max(1);
            let mut onehot = vec![0.0f32; b * nf * k];
            let mut periods = vec![Vec::with_capacity(k); b];
            for s in 0..b {
                let row = &amp_host[s * nf..(s + 1) * nf];
                let freqs = top_frequencies(row, k);
                for (i, &f) in freqs.iter().enumerate() {
                    onehot[s * nf * k + f * k + i] = 1.0;
                    periods[s].push(l.div_ceil(f));
                }
            }
            let onehot = Tensor::<3>::from_data(TensorData::new(onehot, [b, nf, k]), &device);
            let weights = softmax(amp.unsqueeze_dim::<3>(1).matmul(onehot), 2); // [B, 1, k]
            let res = match fused {
                Some(f) => {
                    fused_periods(&f.blocks[bi], &f.tap_rows[bi], x.clone(), &periods, weights)
                }
                None => grouped_periods(&x, &periods, weights, &train_fused[bi]),
            };
            x = block.norm.forward(res + x);
        }
        x.reshape([b, l * d])
    }
}

/// The period branches of one block with the fused convolutions as im2col +
/// GEMM on the host ([`HostConv::forward_grid`]): `x` `[B, L, d]`, each sample's periods
/// and softmax weights `[B, 1, k]` -> `Σ_i w_i · conv_out(gelu(conv_in(grid_i)))`,
/// `[B, L, d]`. The same operations as the tensor path, without building
/// the padded, permuted grids.
fn fused_periods(
    convs: &[HostConv; 2],
    tap_rows: &Mutex<TapRows>,
    x: Tensor<3>,
    periods: &[Vec<usize>],
    weights: Tensor<3>,
) -> Tensor<3> {
    let [b, l, d] = x.dims();
    let device = x.device();
    let xs: Vec<f32> = x
        .into_data()
        .convert::<f32>()
        .try_into_vec()
        .expect("f32 features");
    let k = weights.dims()[2];
    let ws: Vec<f32> = weights
        .into_data()
        .convert::<f32>()
        .try_into_vec()
        .expect("f32 weights");
    let mid = convs[0].c_out();
    let mut res = vec![0.0f32; b * l * d];
    for (s, sample_periods) in periods.iter().enumerate() {
        let xs = &xs[s * l * d..(s + 1) * l * d];
        let acc = &mut res[s * l * d..(s + 1) * l * d];
        // Distinct frequencies can fold to the same period (`ceil(L/f)`:
        // 40, 41 and 39 all give 3 for L = 120); such branches are the same
        // computation, done once with their weights summed.
        let mut distinct: Vec<(usize, f32)> = Vec::with_capacity(sample_periods.len());
        for (i, &p) in sample_periods.iter().enumerate() {
            let w = ws[s * k + i];
            match distinct.iter_mut().find(|(q, _)| *q == p) {
                Some((_, sum)) => *sum += w,
                None => distinct.push((p, w)),
            }
        }
        // Every period's first convolution reads the same input: when
        // folding it at each period would multiply more than once per tap
        // and position, the tap products are made once and each period
        // only sums them. And whenever the input is the last one slid by
        // a row (the first block between two plan messages): then only
        // the new row is multiplied, while folding would multiply every
        // position again (at a new plan the block folds if that is
        // cheaper, and the next tick makes all the products once).
        let conv_in = &convs[0];
        let taps = conv_in.k() * conv_in.k();
        let folded: usize = distinct
            .iter()
            .map(|&(p, _)| {
                let rows = l.div_ceil(p);
                conv_in.grid_taps(l, rows, p, rows * p)
            })
            .sum();
        // Kept from one call to the next ([`TapRows`]): written by the
        // GEMM, neither zeroed nor reallocated per tick.
        let mut kept = tap_rows.lock().unwrap_or_else(|e| e.into_inner());
        let slides = kept.slides(xs, d);
        let use_shared = conv_in.has_tap_products() && (one_pass_pays(folded, l, taps) || slides);
        if !use_shared {
            kept.without_products(xs);
        }
        let shared = use_shared.then(|| kept.products(conv_in, xs, d, slides));
        let hidden: Vec<(usize, usize, f32, Vec<f32>)> = distinct
            .iter()
            .map(|&(p, w)| {
                let rows = l.div_ceil(p);
                let lp = rows * p;
                let mut h = match shared {
                    Some(y) => conv_in.forward_grid_from_taps(y, rows, p, lp),
                    None => conv_in.forward_grid(xs, rows, p, lp),
                };
                debug_assert_eq!(h.len(), lp * mid);
                gelu_in_place(&mut h);
                (p, rows, w, h)
            })
            .collect();
        drop(kept);
        // The second convolution is linear: when folding each period would
        // multiply more than the whole kernel once, the weighted periods
        // go through one GEMM together.
        let conv_out = &convs[1];
        let folded: usize = hidden
            .iter()
            .map(|(p, rows, _, h)| conv_out.grid_taps(h.len() / mid, *rows, *p, l))
            .sum();
        if one_pass_pays(folded, l, taps) {
            let grids: Vec<WeightedGrid> = hidden
                .iter()
                .map(|(p, rows, w, h)| WeightedGrid {
                    x: h,
                    rows: *rows,
                    p: *p,
                    weight: *w,
                })
                .collect();
            acc.copy_from_slice(&conv_out.forward_grids_summed(&grids, l));
        } else {
            for (i, (p, rows, w, h)) in hidden.iter().enumerate() {
                let y = conv_out.forward_grid(h, *rows, *p, l);
                if i == 0 {
                    acc.iter_mut().zip(&y).for_each(|(a, v)| *a = v * w);
                } else {
                    acc.iter_mut().zip(&y).for_each(|(a, v)| *a += v * w);
                }
            }
        }
    }
    Tensor::<3>::from_data(TensorData::new(res, [b, l, d]), &device)
}

/// Whether multiplying every kernel tap once per position (`len · taps`
/// products, then sums) is used instead of folding each period on its own
/// (`folded` products, [`HostConv::grid_taps`]): when folding would
/// multiply a quarter more. Criterion `trajectory_conv_in_3_periods`:
/// periods 2, 3 and 4 fold for 5,100 tap-positions against 3,000, 222 us
/// against 177 us shared, so the two break even near 1.35x; the rule leans
/// to the one pass, whose cost does not depend on the periods.
fn one_pass_pays(folded: usize, len: usize, taps: usize) -> bool {
    4 * folded > 5 * len * taps
}

/// GELU, `x/2 · (1 + erf(x/√2))`, on host values (inference), with erf as
/// a rational function (Eigen's `generic_fast_erf_float`: odd numerator of
/// degree 13 over an even denominator of degree 8, inputs clamped to
/// ±4 where erf is ±1 in f32). The loop has no call and no branch, so
/// it vectorises; burn Flex's `gelu` calls libm's `erff` per element, which
/// was a tenth of a streaming tick. Within 1e-6 · max(1, |x|) of that (tested).
pub fn gelu_in_place(x: &mut [f32]) {
    const A: [f32; 7] = [
        -2.726_142_3e-10,
        2.770_681_4e-8,
        -2.101_024e-6,
        -5.692_506_4e-5,
        -7.349_906_3e-4,
        -2.954_600_1e-3,
        -1.609_603_3e-2,
    ];
    const B: [f32; 5] = [
        -1.456_607_2e-5,
        -2.133_740_6e-4,
        -1.682_827e-3,
        -7.373_329e-3,
        -1.426_474e-2,
    ];
    for v in x.iter_mut() {
        let z = (*v * std::f32::consts::FRAC_1_SQRT_2).clamp(-4.0, 4.0);
        let z2 = z * z;
        let p = A.iter().fold(0.0f32, |acc, &a| acc * z2 + a) * z;
        let q = B.iter().fold(0.0f32, |acc, &b| acc * z2 + b);
        *v = 0.5 * *v * (1.0 + p / q);
    }
}

/// Training: the `(sample, period)` pairs of the whole batch through one
/// block's convolutions, one batch per distinct period, each convolution a
/// gather of its taps' rows and one matmul on channels-last rows (the
/// gradients: a GEMM for the kernel, a scatter-add for the input; no grid
/// permutation, no padded copy, no per-element im2col). The same function
/// as the per-sample loop of [`fused_periods`]: each grid is padded with
/// zeros past the plan and around its edges ("same" convolutions), and each
/// sample sums its periods' weighted outputs (in increasing period, not
/// top-k, order). `x` `[B, L, d]`, `weights` `[B, 1, k]` -> `[B, L, d]`.
pub(super) fn grouped_periods(
    x: &Tensor<3>,
    periods: &[Vec<usize>],
    weights: Tensor<3>,
    convs: &[FusedConv<4>; 2],
) -> Tensor<3> {
    let [b, l, d] = x.dims();
    let k = weights.dims()[2];
    let device = x.device();
    let weights = weights.reshape([b * k]);
    let index = |v: Vec<i64>| {
        let n = v.len();
        Tensor::<1, Int>::from_data(TensorData::new(v, [n]), &device)
    };
    // Kernel `[C_out, C_in, kh, kw]` as a `[kh·kw·C_in, C_out]` matrix, rows
    // in the gathered taps' (dy, dx, c) order.
    let as_matrix = |c: &FusedConv<4>| {
        let [c_out, c_in, kh, kw] = c.weight.dims();
        (
            c.weight
                .clone()
                .permute([2, 3, 1, 0])
                .reshape([kh * kw * c_in, c_out]),
            c.bias.clone().reshape([1, c_out]),
        )
    };
    let (w_in, b_in) = as_matrix(&convs[0]);
    let (w_out, b_out) = as_matrix(&convs[1]);
    let (kernel, mid) = (convs[0].kernel, w_in.dims()[1]);
    // The plan's rows, then one zero row: what a tap outside a grid reads.
    let rows_x = Tensor::cat(
        vec![
            x.clone().reshape([b * l, d]),
            Tensor::zeros([1, d], &device),
        ],
        0,
    );
    // Pairs by period, in increasing period (a deterministic order).
    let mut by_period: std::collections::BTreeMap<usize, Vec<(usize, usize)>> =
        std::collections::BTreeMap::new();
    for (s, sample_periods) in periods.iter().enumerate() {
        for (i, &p) in sample_periods.iter().enumerate() {
            by_period.entry(p).or_default().push((s, i));
        }
    }
    let mut res = Tensor::<2>::zeros([b * l, d], &device);
    for (p, pairs) in by_period {
        let g = pairs.len();
        let grid = GridTaps::new(l.div_ceil(p), p, kernel);
        let lp = grid.cells();
        // conv_in on every cell of each grid (cells past the plan read zeros).
        let taps = grid.rows(
            lp,
            |gi, cell| (cell < l).then(|| pairs[gi].0 * l + cell),
            g,
            b * l,
        );
        let h = rows_x
            .clone()
            .select(0, index(taps))
            .reshape([g * lp, kernel * kernel * d])
            .matmul(w_in.clone())
            + b_in.clone();
        let h = Tensor::cat(vec![gelu(h), Tensor::zeros([1, mid], &device)], 0);
        // conv_out on the cells that are plan ticks.
        let taps = grid.rows(l, |gi, cell| Some(gi * lp + cell), g, g * lp);
        let y = h
            .select(0, index(taps))
            .reshape([g * l, kernel * kernel * mid])
            .matmul(w_out.clone())
            + b_out.clone();
        let w = weights.clone().select(
            0,
            index(pairs.iter().map(|&(s, i)| (s * k + i) as i64).collect()),
        );
        let y = (y.reshape([g, l * d]) * w.reshape([g, 1])).reshape([g * l, d]);
        let dst = pairs
            .iter()
            .flat_map(|&(s, _)| (0..l).map(move |c| (s * l + c) as i64))
            .collect();
        res = res.select_assign(0, index(dst), y, IndexingUpdateOp::Add);
    }
    res.reshape([b, l, d])
}

/// The taps of a "same" square convolution over `rows x cols` grids laid
/// out as cells `r·cols + c`: which input row each (output cell, tap)
/// reads, for [`grouped_periods`]' gathers.
struct GridTaps {
    rows: usize,
    cols: usize,
    kernel: usize,
}

impl GridTaps {
    fn new(rows: usize, cols: usize, kernel: usize) -> GridTaps {
        GridTaps { rows, cols, kernel }
    }

    fn cells(&self) -> usize {
        self.rows * self.cols
    }

    /// For `grids` grids, their first `out_cells` cells, each tap in
    /// `(dy, dx)` order: `source(grid, cell)`'s row, or `zero` beyond the
    /// grid's edges or where `source` has none.
    fn rows(
        &self,
        out_cells: usize,
        source: impl Fn(usize, usize) -> Option<usize>,
        grids: usize,
        zero: usize,
    ) -> Vec<i64> {
        let (kernel, half) = (self.kernel, self.kernel / 2);
        let mut taps = Vec::with_capacity(grids * out_cells * kernel * kernel);
        for gi in 0..grids {
            for cell in 0..out_cells {
                let (r, c) = (cell / self.cols, cell % self.cols);
                for dy in 0..kernel {
                    for dx in 0..kernel {
                        let rr = (r + dy).checked_sub(half).filter(|&v| v < self.rows);
                        let cc = (c + dx).checked_sub(half).filter(|&v| v < self.cols);
                        let row = rr
                            .zip(cc)
                            .and_then(|(rr, cc)| source(gi, rr * self.cols + cc));
                        taps.push(row.unwrap_or(zero) as i64);
                    }
                }
            }
        }
        taps
    }
}

/// Indices (>= 1, DC dropped) of the `k` largest amplitudes, largest first;
/// ties go to the lower frequency, so the choice is deterministic.
fn top_frequencies(amp: &[f32], k: usize) -> Vec<usize> {
    let mut idx: Vec<usize> = (1..amp.len()).collect();
    idx.sort_by(|&a, &b| amp[b].total_cmp(&amp[a]).then(a.cmp(&b)));
    idx.truncate(k);
    idx
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::model::cpu_device;
    use burn::tensor::Distribution;

    /// A plan window sliding over one plan: the forward that reuses the
    /// first block's tap products equals, bit for bit, one made afresh at
    /// every tick, in f32 and in int8, and reuses all but one row a tick.
    #[test]
    fn sliding_window_reuses_tap_rows_bit_for_bit() {
        let device = cpu_device();
        let cfg = ModelConfig::lite(60, 25, vec![15, 30, 45, 60], 64);
        let enc = PlanEncoder::new(&cfg, &device);
        let (l, c, ticks) = (cfg.plan_len(), cfg.n_joints, 6);
        let plan = Tensor::<2>::random([l + ticks, c], Distribution::Normal(0.0, 1.0), &device);
        for int8 in [false, true] {
            let fused = || {
                let mut f = enc.fuse();
                if int8 {
                    f.to_int8();
                }
                f
            };
            let kept = fused();
            let window = |t: usize| plan.clone().slice([t..t + l, 0..c]).unsqueeze::<3>();
            for t in 0..ticks {
                let before = kept.tap_rows();
                let got = enc.forward(window(t), Some(&kept)).into_data();
                // The same path without kept rows: fresh convolutions that
                // saw only the window before (so that the window slides for
                // them too, and every row is multiplied).
                let fresh = fused();
                if t > 0 {
                    enc.forward(window(t - 1), Some(&fresh));
                }
                let want = enc.forward(window(t), Some(&fresh)).into_data();
                assert_eq!(got, want, "int8 {int8}, tick {t}");
                // From the third tick on (the first may fold, the second
                // then multiplies every row), one row multiplied a tick.
                if t >= 2 {
                    let (reused, computed) = kept.tap_rows();
                    assert_eq!(
                        (reused - before.0, computed - before.1),
                        ((l - 1) as u64, 1),
                        "int8 {int8}, tick {t}"
                    );
                }
            }
        }
    }

    /// A period that two or three frequencies fold to is computed once with
    /// the weights summed: the same sum as the training path, which takes
    /// every `(sample, period)` pair on its own.
    #[test]
    fn repeated_periods_equal_one_branch_each() {
        let device = cpu_device();
        let (d, mid, l) = (6usize, 8usize, 30usize);
        let conv_in = Inception2d::new(d, mid, 3, &device);
        let conv_out = Inception2d::new(mid, d, 3, &device);
        let host = [
            HostConv::from_fused(&conv_in.fuse()).with_tap_products(),
            HostConv::from_fused(&conv_out.fuse()),
        ];
        let train = [
            conv_in.fuse_differentiable(),
            conv_out.fuse_differentiable(),
        ];
        let periods = vec![vec![3, 3, 3], vec![4, 7, 4], vec![5, 6, 2]];
        let b = periods.len();
        let x = Tensor::<3>::random([b, l, d], Distribution::Normal(0.0, 1.0), &device);
        let weights = softmax(
            Tensor::<3>::random([b, 1, 3], Distribution::Normal(0.0, 1.0), &device),
            2,
        );
        let want: Vec<f32> = grouped_periods(&x, &periods, weights.clone(), &train)
            .into_data()
            .try_into_vec()
            .unwrap();
        let got: Vec<f32> = fused_periods(&host, &Mutex::default(), x, &periods, weights)
            .into_data()
            .try_into_vec()
            .unwrap();
        for (i, (g, w)) in got.iter().zip(&want).enumerate() {
            assert!(
                (g - w).abs() < 1e-5 * w.abs().max(1.0),
                "at {i}: {g} vs {w}"
            );
        }
    }
}
