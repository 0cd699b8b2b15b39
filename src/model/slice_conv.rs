//! One time slice of a vision layer as one im2col + GEMM (inference).
//!
//! The streaming forecaster computes the vision encoder slice by slice: an
//! output slice of a fused `k x k x k` "same" convolution depends on the
//! `k` input slices around it (zeros where the window ends). Burn Flex's
//! generic `conv3d` on such a `[1, C_in, k, H, W]` input spent most of its
//! time building its im2col buffer; here the im2col matrix is built
//! column by column as shifted row copies of the channel-major input planes,
//! and one GEMM (the `gemm` crate, as Flex itself uses) writes the output
//! channel-major, followed by ReLU and the `2 x 2` spatial max-pool: the
//! layout the next layer and the cache read.
//!
//! Same arithmetic as `conv3d` (f32 products summed, bias added), in
//! another order: equal to it within rounding (tested against the
//! whole-window forward, `streaming_equals_whole_window`, and against
//! `conv3d` directly, `slice_conv_equals_conv3d_same_padding` in the
//! model tests).

use super::host_conv::{HostConv, Strides};

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
        let half = (k / 2) as isize;
        let mut conv = vec![0.0f32; c_out * n];
        for (plane, &b) in conv.chunks_exact_mut(n).zip(self.bias()) {
            plane.fill(b);
        }
        // The time taps that read an input slice: at the window's ends the
        // others read the "same" padding, zeros, and are left out of the
        // im2col matrix and the GEMM (their weight rows are contiguous).
        let Some(kt_lo) = inputs.iter().position(Option::is_some) else {
            // Only padding: the bias alone, through ReLU and the pool below.
            return Self::relu_pool(&conv, c_out, hw);
        };
        let kt_hi = inputs
            .iter()
            .rposition(Option::is_some)
            .map_or(kt_lo, |i| i + 1);
        let taps_per_kt = k * k;
        let kk = (kt_hi - kt_lo) * taps_per_kt * c_in;
        HostConv::with_scratch(kk * n, |a| {
            // Column q = (((kt - kt_lo)·k + ky)·k + kx)·C_in + ci holds, for
            // every output position m = y·hw + x,
            // input[kt][ci][y + ky - k/2][x + kx - k/2] (zero outside): a
            // shifted copy of one input plane. Every element is written
            // once (the zeros too: no clearing pass over the matrix).
            let per_kt = taps_per_kt * c_in * n;
            for (kt, input) in inputs.iter().enumerate().take(kt_hi).skip(kt_lo) {
                let block = &mut a[(kt - kt_lo) * per_kt..(kt - kt_lo + 1) * per_kt];
                let Some(input) = input else {
                    block.fill(0.0);
                    continue;
                };
                for ky in 0..k {
                    let dy = ky as isize - half;
                    for kx in 0..k {
                        let dx = kx as isize - half;
                        let x0 = ((-dx).max(0) as usize).min(hw);
                        let x1 = ((hw as isize - dx).min(hw as isize).max(0) as usize).max(x0);
                        for ci in 0..c_in {
                            let q = (ky * k + kx) * c_in + ci;
                            let col = &mut block[q * n..(q + 1) * n];
                            let plane = &input[ci * n..(ci + 1) * n];
                            for (y, row) in col.chunks_exact_mut(hw).enumerate() {
                                let sy = y as isize + dy;
                                if sy < 0 || sy >= hw as isize || x0 == x1 {
                                    row.fill(0.0);
                                    continue;
                                }
                                let src = (sy as usize * hw) as isize + dx;
                                row[..x0].fill(0.0);
                                row[x0..x1].copy_from_slice(
                                    &plane[(src + x0 as isize) as usize
                                        ..(src + x1 as isize) as usize],
                                );
                                row[x1..].fill(0.0);
                            }
                        }
                    }
                }
            }
            // `conv` is `n x C_out` channel-major, `a` `n x kk` column-major.
            let column_major = Strides { row: 1, col: n };
            self.accumulate_taps(
                kt_lo * taps_per_kt..kt_hi * taps_per_kt,
                n,
                &mut conv,
                column_major,
                a,
                column_major,
            );
        });
        Self::relu_pool(&conv, c_out, hw)
    }

    /// ReLU and the `2 x 2` max-pool (floor) of `[C_out, hw, hw]`.
    fn relu_pool(conv: &[f32], c_out: usize, hw: usize) -> Vec<f32> {
        let n = hw * hw;
        let ho = hw / 2;
        let mut out = vec![0.0f32; c_out * ho * ho];
        for (dst, src) in out.chunks_exact_mut(ho * ho).zip(conv.chunks_exact(n)) {
            for y in 0..ho {
                let r0 = &src[2 * y * hw..];
                let r1 = &src[(2 * y + 1) * hw..];
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
