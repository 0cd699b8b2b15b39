//! One time slice of a vision layer as one im2col + GEMM (inference).
//!
//! The streaming forecaster computes the vision encoder slice by slice: an
//! output slice of a fused `k x k x k` "same" convolution depends on the
//! `k` input slices around it (zeros where the window ends). Burn Flex's
//! generic `conv3d` on such a `[1, C_in, k, H, W]` input spent most of its
//! time building its im2col buffer; here each input plane is copied once
//! with its zero border, the output is computed on rows as wide as that
//! padded plane (the extra `k − 1` positions of each row are dropped), so
//! that every im2col column is one contiguous copy of a padded plane, and
//! one GEMM (the `gemm` crate, as Flex itself uses) writes the output
//! channel-major, followed by ReLU and the `2 x 2` spatial max-pool: the
//! layout the next layer and the cache read. (Row-by-row shifted copies
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
    /// One output slice: `inputs` the `k` input slices centred on it, each
    /// `[C_in, hw, hw]` channel-major (`None`: zeros, the window's end), ->
    /// ReLU(conv) max-pooled `2 x 2`, `[C_out, hw/2, hw/2]` channel-major.
    pub fn forward_slice_pooled(&self, inputs: &[Option<&[f32]>], hw: usize) -> Vec<f32> {
        let (k, c_in, c_out) = (self.k(), self.c_in(), self.c_out());
        assert_eq!(inputs.len(), k, "one input slice per kernel time tap");
        let n = hw * hw;
        for s in inputs.iter().flatten() {
            assert_eq!(s.len(), c_in * n, "input slice size");
        }
        // Outputs are computed on rows as wide as the padded input
        // (`w = hw + 2·half`; the last `2·half` of each row are not
        // outputs and are dropped by the pool), so that every im2col column
        // is one contiguous run of a zero-padded input plane.
        let half = k / 2;
        let w = hw + 2 * half;
        let wide = hw * w;
        // The padded plane, and `2·half` more zeros that the dropped
        // positions of the last row read.
        let padded_len = (hw + 2 * half) * w + 2 * half;
        let mut conv = vec![0.0f32; c_out * wide];
        for (plane, &b) in conv.chunks_exact_mut(wide).zip(self.bias()) {
            plane.fill(b);
        }
        // The time taps that read an input slice: at the window's ends the
        // others read the "same" padding, zeros, and are left out of the
        // im2col matrix and the GEMM (their weight rows are contiguous).
        let Some(kt_lo) = inputs.iter().position(Option::is_some) else {
            // Only padding: the bias alone, through ReLU and the pool below.
            return Self::relu_pool(&conv, c_out, hw, w);
        };
        let kt_hi = inputs
            .iter()
            .rposition(Option::is_some)
            .map_or(kt_lo, |i| i + 1);
        let taps_per_kt = k * k;
        let kk = (kt_hi - kt_lo) * taps_per_kt * c_in;
        let n_kt = kt_hi - kt_lo;
        HostConv::with_scratch(n_kt * c_in * padded_len, |padded| {
            // Each input plane once with its zero border: `hw + 2·half`
            // rows of `w` values.
            for (kt, input) in inputs.iter().enumerate().take(kt_hi).skip(kt_lo) {
                for ci in 0..c_in {
                    let dst = &mut padded[((kt - kt_lo) * c_in + ci) * padded_len..][..padded_len];
                    let Some(input) = input else {
                        dst.fill(0.0);
                        continue;
                    };
                    let plane = &input[ci * n..(ci + 1) * n];
                    // Only the border is zeroed: the top rows, each row's
                    // `2·half` zeros between two rows, the bottom rows.
                    dst[..half * w + half].fill(0.0);
                    for (y, row) in plane.chunks_exact(hw).enumerate() {
                        let at = (y + half) * w + half;
                        dst[at..at + hw].copy_from_slice(row);
                        let gap_end = (at + hw + 2 * half).min(padded_len);
                        dst[at + hw..gap_end].fill(0.0);
                    }
                    dst[(hw + half) * w + half..].fill(0.0);
                }
            }
            // Column q = (((kt - kt_lo)·k + ky)·k + kx)·C_in + ci holds, for
            // every wide position m = y·w + x, the padded plane at
            // m + ky·w + kx: a contiguous run of `padded`, read in place
            // by the GEMM (no im2col copy).
            let columns: Vec<usize> = (0..kk)
                .map(|q| {
                    let (ci, tap) = (q % c_in, q / c_in);
                    let (kt, ky, kx) = (tap / taps_per_kt, tap / k % k, tap % k);
                    (kt * c_in + ci) * padded_len + ky * w + kx
                })
                .collect();
            // `conv` is `wide x C_out` channel-major.
            self.accumulate_taps_gathered(
                kt_lo * taps_per_kt..kt_hi * taps_per_kt,
                Product {
                    m: wide,
                    dst: &mut conv,
                    dst_s: Strides { row: 1, col: wide },
                    a: padded,
                    a_s: Strides { row: 1, col: 0 },
                },
                &columns,
            );
        });
        Self::relu_pool(&conv, c_out, hw, w)
    }

    /// ReLU and the `2 x 2` max-pool (floor) of `[C_out, hw, hw]`, stored
    /// with rows `w` apart.
    fn relu_pool(conv: &[f32], c_out: usize, hw: usize, w: usize) -> Vec<f32> {
        let n = hw * w;
        let ho = hw / 2;
        let mut out = vec![0.0f32; c_out * ho * ho];
        for (dst, src) in out.chunks_exact_mut(ho * ho).zip(conv.chunks_exact(n)) {
            for y in 0..ho {
                let r0 = &src[2 * y * w..];
                let r1 = &src[(2 * y + 1) * w..];
                for x in 0..ho {
                    let m = r0[2 * x]
                        .max(r0[2 * x + 1])
                        .max(r1[2 * x])
                        .max(r1[2 * x + 1]);
                    dst[y * ho + x] = m.max(0.0);
                }
            }
        }
        out
    }
}
