//! One time slice of a vision layer (inference), as im2col + GEMM.
//!
//! The streaming forecaster computes the vision encoder slice by slice: an
//! output slice of a fused `k x k x k` "same" convolution is the bias plus
//! one term per time tap, each the `k x k` convolution of one input slice
//! (none where the window ends, whose padding is zeros). A term is computed
//! on its own ([`HostConv::slice_terms`]) and kept, so that an output slice
//! whose neighbourhood changed (at the window's two ends) is summed from
//! the terms of the input slices that did not change
//! ([`HostConv::pooled_of_terms`]: bias + terms, ReLU, the `2 x 2` spatial
//! max-pool, in one pass).
//!
//! A term: each input plane is copied once with its zero border, the
//! output is computed on rows as wide as that padded plane (the extra
//! `k − 1` positions of each row are dropped by the pool), so that every
//! im2col column is one contiguous run of a padded plane, read in place by
//! the GEMM kernel (no im2col copy), which writes the output channel-major:
//! the layout the next layer and the cache read. (Row-by-row shifted copies
//! took half of a slice's time; the wide rows cost up to 50% more GEMM on
//! the 4x4 layer and are still faster there: `cargo bench --bench
//! model_parts -- vision_slice`.)
//!
//! Same arithmetic as `conv3d` (f32 products summed, bias added), in
//! another order: equal to it within rounding (tested against the
//! whole-window forward, `streaming_equals_whole_window`, and against
//! `conv3d` directly, `slice_conv_equals_conv3d_same_padding` in the
//! model tests).

use super::host_conv::{HostConv, Product, Strides};

impl HostConv {
    /// The terms one input slice `input` (`[C_in, hw, hw]`) gives through
    /// the kernel's time taps `kts`, one each, without the bias:
    /// `[C_out, hw, w]` on wide rows (`w`: [`wide_row`](Self::wide_row)),
    /// for [`pooled_of_terms`](Self::pooled_of_terms). The padded planes
    /// are made once for all of them. Each term is stored into a buffer
    /// from `spare` (its contents are not read) or a new one. The
    /// streaming forecaster keeps these, so that an output slice whose
    /// neighbours changed is summed from the terms that did not change.
    pub fn slice_terms(
        &self,
        input: &[f32],
        kts: &[usize],
        hw: usize,
        spare: &mut Vec<Vec<f32>>,
    ) -> Vec<Vec<f32>> {
        let (k, c_in) = (self.k(), self.c_in());
        let n = hw * hw;
        assert_eq!(input.len(), c_in * n, "input slice size");
        assert!(kts.iter().all(|&kt| kt < k), "time taps inside the kernel");
        let half = k / 2;
        let w = self.wide_row(hw);
        let wide = hw * w;
        // The padded plane, and `2·half` more zeros that the dropped
        // positions of the last row read.
        let padded_len = (hw + 2 * half) * w + 2 * half;
        let taps_per_kt = k * k;
        HostConv::with_scratch(c_in * padded_len, |padded| {
            // Each input plane once with its zero border: `hw + 2·half`
            // rows of `w` values; only the border is zeroed: the top rows,
            // each row's `2·half` zeros between two rows, the bottom rows.
            for ci in 0..c_in {
                let dst = &mut padded[ci * padded_len..][..padded_len];
                let plane = &input[ci * n..(ci + 1) * n];
                dst[..half * w + half].fill(0.0);
                for (y, row) in plane.chunks_exact(hw).enumerate() {
                    let at = (y + half) * w + half;
                    dst[at..at + hw].copy_from_slice(row);
                    let gap_end = (at + hw + 2 * half).min(padded_len);
                    dst[at + hw..gap_end].fill(0.0);
                }
                dst[(hw + half) * w + half..].fill(0.0);
            }
            // Column q = (ky·k + kx)·C_in + ci holds, for every wide
            // position m = y·w + x, the padded plane at m + ky·w + kx: a
            // contiguous run of `padded`, read in place by the GEMM (no
            // im2col copy). The same columns serve every time tap.
            let columns: Vec<usize> = (0..taps_per_kt * c_in)
                .map(|q| {
                    let (ci, tap) = (q % c_in, q / c_in);
                    ci * padded_len + tap / k * w + tap % k
                })
                .collect();
            kts.iter()
                .map(|&kt| {
                    let mut term = spare.pop().unwrap_or_default();
                    term.resize(self.c_out() * wide, 0.0);
                    // `term` is `wide x C_out` channel-major.
                    self.store_taps_gathered(
                        kt * taps_per_kt..(kt + 1) * taps_per_kt,
                        Product {
                            m: wide,
                            dst: &mut term,
                            dst_s: Strides { row: 1, col: wide },
                            a: padded,
                            a_s: Strides { row: 1, col: 0 },
                        },
                        &columns,
                    );
                    term
                })
                .collect()
        })
    }

    /// ReLU(bias + the sum of `terms`) max-pooled `2 x 2`: one output slice
    /// `[C_out, hw/2, hw/2]` from its [`slice_terms`](Self::slice_terms)
    /// (none: the bias alone). The terms are summed in order, the pool
    /// taken, then the bias added (adding one value keeps the order of
    /// the four, so this is the maximum of the four sums with the bias).
    pub fn pooled_of_terms(&self, terms: &[&[f32]], hw: usize) -> Vec<f32> {
        let (c_out, w) = (self.c_out(), self.wide_row(hw));
        let len = c_out * hw * w;
        assert!(terms.iter().all(|t| t.len() == len), "term size");
        match terms {
            [] => Self::relu_pool(&vec![0.0; len], self.bias(), c_out, hw, w),
            [one] => Self::relu_pool(one, self.bias(), c_out, hw, w),
            [first, rest @ ..] => HostConv::with_scratch(len, |sum| {
                sum.copy_from_slice(first);
                add_terms(sum, rest);
                Self::relu_pool(sum, self.bias(), c_out, hw, w)
            }),
        }
    }

    /// The width of the rows an output slice is computed on: the padded
    /// input's (`hw + 2·half`; the last `2·half` of each row are not
    /// outputs and are dropped by the pool), so that every im2col column
    /// is one contiguous run of a zero-padded input plane.
    pub fn wide_row(&self, hw: usize) -> usize {
        hw + 2 * (self.k() / 2)
    }

    /// ReLU of the `2 x 2` max-pool (floor) of `conv + bias`, `conv`
    /// `[C_out, hw, hw]` stored with rows `w` apart.
    fn relu_pool(conv: &[f32], bias: &[f32], c_out: usize, hw: usize, w: usize) -> Vec<f32> {
        let n = hw * w;
        let ho = hw / 2;
        let mut out = vec![0.0f32; c_out * ho * ho];
        for ((dst, src), &b) in out
            .chunks_exact_mut(ho * ho)
            .zip(conv.chunks_exact(n))
            .zip(bias)
        {
            for y in 0..ho {
                let r0 = &src[2 * y * w..];
                let r1 = &src[(2 * y + 1) * w..];
                for x in 0..ho {
                    let m = r0[2 * x]
                        .max(r0[2 * x + 1])
                        .max(r1[2 * x])
                        .max(r1[2 * x + 1]);
                    dst[y * ho + x] = (m + b).max(0.0);
                }
            }
        }
        out
    }
}

/// `sum += term` for each term, in order; 8 lanes at a time where the CPU
/// has AVX2 (each value's additions the same and in the same order, so
/// the same bits as the portable loop).
fn add_terms(sum: &mut [f32], rest: &[&[f32]]) {
    #[cfg(target_arch = "x86_64")]
    {
        if std::arch::is_x86_feature_detected!("avx2") {
            // SAFETY: the CPU has AVX2 (checked just above).
            unsafe { add_terms_avx2(sum, rest) };
            return;
        }
    }
    add_terms_portable(sum, rest);
}

#[cfg(target_arch = "x86_64")]
#[target_feature(enable = "avx2")]
fn add_terms_avx2(sum: &mut [f32], rest: &[&[f32]]) {
    add_terms_portable(sum, rest);
}

#[inline(always)]
fn add_terms_portable(sum: &mut [f32], rest: &[&[f32]]) {
    for term in rest {
        sum.iter_mut().zip(term.iter()).for_each(|(s, t)| *s += t);
    }
}
