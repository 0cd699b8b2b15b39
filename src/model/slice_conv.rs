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
//! `conv3d` directly below).

use std::cell::RefCell;
use std::sync::Arc;

use super::inception::FusedConv;

thread_local! {
    /// The im2col matrix, reused between calls (no allocation per slice).
    static SCRATCH: RefCell<Vec<f32>> = const { RefCell::new(Vec::new()) };
}

/// One fused `k x k x k` convolution, applied one output time slice at a time.
#[derive(Debug, Clone)]
pub struct SliceConv {
    k: usize,
    c_in: usize,
    c_out: usize,
    /// `[k·k·k·C_in, C_out]`, row `((kt·k + ky)·k + kx)·C_in + ci`.
    weight: Arc<[f32]>,
    bias: Arc<[f32]>,
}

impl SliceConv {
    /// From a fused 3-D convolution (`[C_out, C_in, k, k, k]`).
    pub fn from_fused(conv: &FusedConv<5>) -> SliceConv {
        let [c_out, c_in, k, k2, k3] = conv.weight.dims();
        assert!(k == k2 && k == k3, "cubic kernel");
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
        let mut weight = vec![0.0f32; k * k * k * c_in * c_out];
        for co in 0..c_out {
            for ci in 0..c_in {
                for tap in 0..k * k * k {
                    weight[(tap * c_in + ci) * c_out + co] = w[(co * c_in + ci) * k * k * k + tap];
                }
            }
        }
        SliceConv {
            k,
            c_in,
            c_out,
            weight: weight.into(),
            bias: bias.into(),
        }
    }

    /// Kernel side (time and space).
    pub fn kernel(&self) -> usize {
        self.k
    }

    /// One output slice: `inputs` the `k` input slices centred on it, each
    /// `[C_in, hw, hw]` channel-major (`None`: zeros, the window's end), ->
    /// ReLU(conv) max-pooled `2 x 2`, `[C_out, hw/2, hw/2]` channel-major.
    pub fn forward_pooled(&self, inputs: &[Option<&[f32]>], hw: usize) -> Vec<f32> {
        let (k, c_in, c_out) = (self.k, self.c_in, self.c_out);
        assert_eq!(inputs.len(), k, "one input slice per kernel time tap");
        let n = hw * hw;
        for s in inputs.iter().flatten() {
            assert_eq!(s.len(), c_in * n, "input slice size");
        }
        let kk = k * k * k * c_in;
        let half = (k / 2) as isize;
        let mut conv = vec![0.0f32; c_out * n];
        for (plane, &b) in conv.chunks_exact_mut(n).zip(self.bias.iter()) {
            plane.fill(b);
        }
        SCRATCH.with(|s| {
            let mut a = s.borrow_mut();
            a.clear();
            a.resize(kk * n, 0.0);
            // Column q = ((kt·k + ky)·k + kx)·C_in + ci holds, for every output
            // position m = y·hw + x, input[kt][ci][y + ky - k/2][x + kx - k/2]
            // (zero outside): a shifted copy of one input plane.
            for (kt, input) in inputs.iter().enumerate() {
                let Some(input) = input else { continue };
                for ky in 0..k {
                    let dy = ky as isize - half;
                    for kx in 0..k {
                        let dx = kx as isize - half;
                        let x0 = (-dx).max(0) as usize;
                        let x1 = (hw as isize - dx).min(hw as isize) as usize;
                        for ci in 0..c_in {
                            let q = ((kt * k + ky) * k + kx) * c_in + ci;
                            let col = &mut a[q * n..(q + 1) * n];
                            let plane = &input[ci * n..(ci + 1) * n];
                            for y in 0..hw {
                                let sy = y as isize + dy;
                                if sy < 0 || sy >= hw as isize || x0 >= x1 {
                                    continue;
                                }
                                let src = sy as usize * hw;
                                let (s0, s1) = (
                                    (src as isize + x0 as isize + dx) as usize,
                                    (src as isize + x1 as isize + dx) as usize,
                                );
                                col[y * hw + x0..y * hw + x1].copy_from_slice(&plane[s0..s1]);
                            }
                        }
                    }
                }
            }
            // SAFETY: `conv` is `n x c_out` stored channel-major (element
            // (m, co) at co·n + m), `a` is `n x kk` stored column-major
            // (element (m, q) at q·n + m), `weight` is `kk x c_out`
            // row-major; the sizes were checked or allocated above and no
            // two overlap.
            unsafe {
                gemm::gemm(
                    n,
                    c_out,
                    kk,
                    conv.as_mut_ptr(),
                    n as isize,
                    1,
                    true,
                    a.as_ptr(),
                    n as isize,
                    1,
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
        });
        // ReLU and the 2 x 2 max-pool (floor), per channel.
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

#[cfg(test)]
mod tests {
    use super::*;
    use crate::model::vision::spatial_pool;
    use burn::prelude::*;
    use burn::tensor::activation::relu;
    use burn::tensor::module::conv3d;
    use burn::tensor::ops::ConvOptions;

    fn values(n: usize, seed: u32) -> Vec<f32> {
        // A small deterministic sequence in [-1, 1].
        let mut s = seed.wrapping_mul(2_654_435_761).wrapping_add(1);
        (0..n)
            .map(|_| {
                s ^= s << 13;
                s ^= s >> 17;
                s ^= s << 5;
                (s as f32 / u32::MAX as f32) * 2.0 - 1.0
            })
            .collect()
    }

    /// Every output slice of a short sequence equals `conv3d` ("same"
    /// padding), ReLU and the spatial pool, the window's ends included.
    #[test]
    fn slices_equal_conv3d_same_padding() {
        let device = Default::default();
        let (c_in, c_out, k, hw, t) = (3, 5, 3, 8, 4);
        let weight = Tensor::<5>::from_data(
            TensorData::new(values(c_out * c_in * k * k * k, 1), [c_out, c_in, k, k, k]),
            &device,
        );
        let bias = Tensor::<1>::from_data(TensorData::new(values(c_out, 2), [c_out]), &device);
        let conv = FusedConv {
            weight: weight.clone(),
            bias: bias.clone(),
            kernel: k,
        };
        let x = values(c_in * t * hw * hw, 3);
        let xt = Tensor::<5>::from_data(TensorData::new(x.clone(), [1, c_in, t, hw, hw]), &device);
        let want = spatial_pool(relu(conv3d(
            xt,
            weight,
            Some(bias),
            ConvOptions::new([1, 1, 1], [1, 1, 1], [1, 1, 1], 1),
        )));
        let want: Vec<f32> = want.into_data().try_to_vec::<f32>().expect("f32");
        // Per-slice inputs [C_in, hw, hw].
        let plane = hw * hw;
        let slices: Vec<Vec<f32>> = (0..t)
            .map(|ti| {
                (0..c_in)
                    .flat_map(|ci| x[(ci * t + ti) * plane..(ci * t + ti + 1) * plane].to_vec())
                    .collect()
            })
            .collect();
        let sc = SliceConv::from_fused(&conv);
        let ho = hw / 2;
        for j in 0..t {
            let inputs: Vec<Option<&[f32]>> = (0..k)
                .map(|kt| {
                    let i = j as isize + kt as isize - 1;
                    (0..t as isize)
                        .contains(&i)
                        .then(|| slices[i as usize].as_slice())
                })
                .collect();
            let got = sc.forward_pooled(&inputs, hw);
            for co in 0..c_out {
                for m in 0..ho * ho {
                    let w = want[(co * t + j) * ho * ho + m];
                    let g = got[co * ho * ho + m];
                    assert!(
                        (g - w).abs() < 1e-5,
                        "slice {j} ch {co} pos {m}: {g} vs {w}"
                    );
                }
            }
        }
    }
}
