//! The classifier's input projection for inference, on the host, with its
//! weights kept at the precision the model file stored them in.
//!
//! In: features `[B, F]`. Out: `x · W + b`, `[B, d_model]`, f32.
//!
//! This one matrix is most of a network's weights (`F x d_model`, e.g.
//! 7,400 x 1,024 for EMP lite). Model files are written in f16; holding the
//! matrix as f16 halves the daemon's memory for it, and the product is
//! unchanged: every f16 value converts to f32 exactly, and the arithmetic
//! is f32. A matrix that is not exactly representable in f16 (a network
//! trained in this process, an f32 file) stays f32. One product per tick
//! reads the whole matrix once, so it is bound by memory bandwidth: half the
//! bytes is also less time.

use std::sync::Arc;

use burn::nn::Linear;
use burn::prelude::*;
use half::f16;
use half::slice::HalfFloatSliceExt;

/// Rows converted (f16) and accumulated per step: 8 x `d_model` f32 stay in L1.
const ROWS_PER_STEP: usize = 8;

#[derive(Debug, Clone)]
enum Weights {
    F32(Arc<[f32]>),
    F16(Arc<[f16]>),
    /// `w[r, j] ≈ q[r, j] · scale[r]`: symmetric int8 per input row
    /// ([`HostLinear::to_int8`]), stored by blocks of output columns
    /// ([`i8_index`]).
    I8 {
        q: Arc<[i8]>,
        scale: Arc<[f32]>,
    },
}

/// `y = x · W + b` with `W` `[in, out]` row-major.
#[derive(Debug, Clone)]
pub struct HostLinear {
    weight: Weights,
    bias: Arc<[f32]>,
    d_in: usize,
    d_out: usize,
}

impl HostLinear {
    /// From a burn [`Linear`] (weight `[in, out]`); f16 when that is lossless.
    pub fn from_linear(linear: &Linear) -> HostLinear {
        let [d_in, d_out] = linear.weight.dims();
        let (w, bias) = linear_values(linear);
        HostLinear::new(w, bias, d_in, d_out)
    }

    /// From row-major `[d_in, d_out]` weights; f16 when that is lossless.
    pub fn new(w: Vec<f32>, bias: Vec<f32>, d_in: usize, d_out: usize) -> HostLinear {
        assert_eq!(w.len(), d_in * d_out, "weight shape");
        assert_eq!(bias.len(), d_out, "bias shape");
        let lossless = w
            .iter()
            .all(|&v| f16::from_f32(v).to_f32().to_bits() == v.to_bits());
        let weight = if lossless {
            let mut h = vec![f16::ZERO; w.len()];
            h.convert_from_f32_slice(&w);
            Weights::F16(h.into())
        } else {
            Weights::F32(w.into())
        };
        HostLinear {
            weight,
            bias: bias.into(),
            d_in,
            d_out,
        }
    }

    /// Whether the matrix is held in f16.
    pub fn is_half(&self) -> bool {
        matches!(self.weight, Weights::F16(_))
    }

    /// Whether the matrix is held in int8.
    pub fn is_int8(&self) -> bool {
        matches!(self.weight, Weights::I8 { .. })
    }

    /// The matrix in int8, one scale per input row (symmetric, round to
    /// nearest: `scale[r] = max_j |w[r, j]| / 127`, so each weight moves by
    /// at most `scale[r] / 2`). Half the bytes of f16, and the product reads
    /// half as much memory per tick. The scale is applied to the input
    /// (`x[r] · scale[r]`), which is then rounded to 16-bit integers with
    /// one step for the vector ([`quantise_input`]), so that the product
    /// is integer multiply-adds (two rows per instruction on AVX2).
    /// Not lossless: the forecasts it changes, and by how much, are
    /// measured in the model card. Already int8: unchanged.
    pub fn to_int8(&self) -> HostLinear {
        let (d_in, n) = (self.d_in, self.d_out);
        let mut q = vec![0i8; d_in.next_multiple_of(2) * n];
        let mut scale = vec![0.0f32; d_in];
        let mut buf = vec![0.0f32; n];
        for r in 0..d_in {
            match &self.weight {
                Weights::F32(w) => buf.copy_from_slice(&w[r * n..(r + 1) * n]),
                Weights::F16(w) => w[r * n..(r + 1) * n].convert_to_f32_slice(&mut buf),
                Weights::I8 { .. } => return self.clone(),
            }
            let max = buf.iter().fold(0.0f32, |m, v| m.max(v.abs()));
            let s = if max > 0.0 { max / 127.0 } else { 1.0 };
            for (j, &v) in buf.iter().enumerate() {
                q[i8_index(d_in, n, r, j)] = (v / s).round().clamp(-127.0, 127.0) as i8;
            }
            // A row with a non-finite weight gives a non-finite product, as
            // in the f32 path: its scale is NaN (`max` alone would miss a
            // NaN, which `f32::max` skips).
            scale[r] = if buf.iter().all(|v| v.is_finite()) {
                s
            } else {
                f32::NAN
            };
        }
        HostLinear {
            weight: Weights::I8 {
                q: q.into(),
                scale: scale.into(),
            },
            bias: Arc::clone(&self.bias),
            d_in,
            d_out: n,
        }
    }

    /// Bytes the matrix and bias take.
    pub fn bytes(&self) -> usize {
        let w = match &self.weight {
            Weights::F32(w) => 4 * w.len(),
            Weights::F16(w) => 2 * w.len(),
            Weights::I8 { q, scale } => q.len() + 4 * scale.len(),
        };
        w + 4 * self.bias.len()
    }

    /// `[B, in]` -> `[B, out]`.
    pub fn forward(&self, x: Tensor<2>) -> Tensor<2> {
        let [b, d_in] = x.dims();
        assert_eq!(d_in, self.d_in, "HostLinear input width");
        let device = x.device();
        let xs: Vec<f32> = x
            .into_data()
            .convert::<f32>()
            .try_into_vec::<f32>()
            .expect("f32 features");
        let mut y = vec![0.0f32; b * self.d_out];
        for (xr, yr) in xs.chunks_exact(d_in).zip(y.chunks_exact_mut(self.d_out)) {
            self.row(xr, yr);
        }
        Tensor::<2>::from_data(TensorData::new(y, [b, self.d_out]), &device)
    }

    /// One row: `y = x · W + b`.
    fn row(&self, x: &[f32], y: &mut [f32]) {
        y.copy_from_slice(&self.bias);
        let n = self.d_out;
        match &self.weight {
            Weights::F32(w) => {
                for (xc, wc) in x.chunks(ROWS_PER_STEP).zip(w.chunks(ROWS_PER_STEP * n)) {
                    axpy_rows(xc, wc, y);
                }
            }
            Weights::F16(w) => {
                #[cfg(target_arch = "x86_64")]
                {
                    if std::arch::is_x86_feature_detected!("avx2")
                        && std::arch::is_x86_feature_detected!("fma")
                        && std::arch::is_x86_feature_detected!("f16c")
                    {
                        // SAFETY: the CPU has AVX2, FMA and F16C (checked just above).
                        unsafe { axpy_rows_f16_avx2(x, w, y) };
                        return;
                    }
                }
                let mut buf = vec![0.0f32; ROWS_PER_STEP * n];
                for (xc, wc) in x.chunks(ROWS_PER_STEP).zip(w.chunks(ROWS_PER_STEP * n)) {
                    let rows = &mut buf[..wc.len()];
                    wc.convert_to_f32_slice(rows);
                    axpy_rows(xc, rows, y);
                }
            }
            Weights::I8 { q, scale } => {
                let Some((qx, step)) = quantise_input(x, scale) else {
                    // A non-finite input or weight: no number to stand behind.
                    y.fill(f32::NAN);
                    return;
                };
                let mut acc = vec![0.0f32; n];
                #[cfg(target_arch = "x86_64")]
                {
                    if std::arch::is_x86_feature_detected!("avx2") {
                        // SAFETY: the CPU has AVX2 (checked just above).
                        unsafe { i8_product_avx2(&qx, q, &mut acc) };
                    } else {
                        i8_columns_generic(&qx, q, &mut acc, 0);
                    }
                }
                #[cfg(not(target_arch = "x86_64"))]
                i8_columns_generic(&qx, q, &mut acc, 0);
                for (yv, a) in y.iter_mut().zip(&acc) {
                    *yv += step * a;
                }
            }
        }
    }
}

/// A tensor's values on the host, in f32, row-major.
pub(super) fn host_values<const D: usize>(t: Tensor<D>) -> Vec<f32> {
    t.into_data()
        .convert::<f32>()
        .try_into_vec::<f32>()
        .expect("f32 values")
}

/// A burn [`Linear`]'s weight `[in, out]` row-major and its bias (zeros
/// when it has none), on the host.
pub(super) fn linear_values(linear: &Linear) -> (Vec<f32>, Vec<f32>) {
    let d_out = linear.weight.dims()[1];
    let w = host_values(linear.weight.val());
    let bias = linear
        .bias
        .as_ref()
        .map_or_else(|| vec![0.0; d_out], |b| host_values(b.val()));
    (w, bias)
}

/// The int8 product's input: `x[r] · scale[r]` (the rows' weight scales
/// moved onto the input) rounded to 16-bit integers with one step for the
/// whole vector (`max |x[r] · scale[r]| / 32767`), padded with a zero to an
/// even length (rows are taken in pairs). Each input moves by at most half
/// a step: relative to the largest, 1.5e-5, far below the int8 weights'
/// own rounding (half of 1/127 of each row's largest). `None` when a
/// value is not finite.
fn quantise_input(x: &[f32], scale: &[f32]) -> Option<(Vec<i16>, f32)> {
    let xs: Vec<f32> = x.iter().zip(scale).map(|(a, s)| a * s).collect();
    if !xs.iter().all(|v| v.is_finite()) {
        return None;
    }
    let max = xs.iter().fold(0.0f32, |m, v| m.max(v.abs()));
    let step = max / I16_MAX;
    let mut qx = vec![0i16; xs.len().next_multiple_of(2)];
    if step > 0.0 {
        for (q, v) in qx.iter_mut().zip(&xs) {
            *q = (v / step).round().clamp(-I16_MAX, I16_MAX) as i16;
        }
    }
    Some((qx, step))
}

/// The largest 16-bit input code.
const I16_MAX: f32 = 32767.0;

/// `y += Σ_r x[r] · w[r, :]` for up to [`ROWS_PER_STEP`] rows.
fn axpy_rows(x: &[f32], w: &[f32], y: &mut [f32]) {
    #[cfg(target_arch = "x86_64")]
    {
        if std::arch::is_x86_feature_detected!("avx2") && std::arch::is_x86_feature_detected!("fma")
        {
            // SAFETY: the CPU has AVX2 and FMA (checked just above).
            unsafe { axpy_rows_avx2(x, w, y) };
            return;
        }
    }
    axpy_rows_generic(x, w, y);
}

#[cfg(target_arch = "x86_64")]
#[target_feature(enable = "avx2,fma")]
unsafe fn axpy_rows_avx2(x: &[f32], w: &[f32], y: &mut [f32]) {
    axpy_rows_generic(x, w, y);
}

/// `y += Σ_r x[r] · w[r, :]` with `w` in f16, converted in registers (F16C):
/// the same fused multiply-adds as the f32 path, half the bytes read.
#[cfg(target_arch = "x86_64")]
#[target_feature(enable = "avx2,fma,f16c")]
fn axpy_rows_f16_avx2(x: &[f32], w: &[f16], y: &mut [f32]) {
    use std::arch::x86_64::{
        __m128i, _mm256_cvtph_ps, _mm256_fmadd_ps, _mm256_loadu_ps, _mm256_set1_ps,
        _mm256_storeu_ps, _mm_loadu_si128,
    };
    let n = y.len();
    for (r, &xr) in x.iter().enumerate() {
        let row = &w[r * n..(r + 1) * n];
        let xv = _mm256_set1_ps(xr);
        let mut j = 0;
        while j + 8 <= n {
            // SAFETY: `j + 8 <= n` = the length of `row` and of `y`; the
            // loads and the store are unaligned.
            unsafe {
                let wv = _mm256_cvtph_ps(_mm_loadu_si128(row.as_ptr().add(j).cast::<__m128i>()));
                let yv = _mm256_loadu_ps(y.as_ptr().add(j));
                _mm256_storeu_ps(y.as_mut_ptr().add(j), _mm256_fmadd_ps(xv, wv, yv));
            }
            j += 8;
        }
        for (yv, wv) in y[j..].iter_mut().zip(&row[j..]) {
            *yv = xr.mul_add(wv.to_f32(), *yv);
        }
    }
}

/// Output columns summed in registers at once (eight AVX2 registers).
const I8_BLOCK: usize = 64;

/// Row pairs summed in 32-bit integers before they are added to the f32
/// sums: a pair adds at most `2 · 127 · 32767` (< 2^23.0), so 128 pairs
/// stay below 2^30 and never overflow.
const PAIRS_PER_CHUNK: usize = 128;

/// `acc[j] = Σ_chunks f32(Σ_{r in chunk} qx[r] · q[r, j])`: 16-bit inputs
/// times int8 weights, each pair of rows one `vpmaddwd` (two products and
/// their sum per output, exact in 32 bits), a chunk of row pairs summed
/// in integers, then converted and added in f32. Per output the same
/// integers and the same f32 additions in the same order as
/// [`i8_columns_generic`], so the two give the same bits.
#[cfg(target_arch = "x86_64")]
#[target_feature(enable = "avx2")]
fn i8_product_avx2(qx: &[i16], q: &[i8], acc: &mut [f32]) {
    use std::arch::x86_64::{
        __m128i, __m256, __m256i, _mm256_add_epi32, _mm256_add_ps, _mm256_cvtepi32_ps,
        _mm256_cvtepi8_epi16, _mm256_loadu_ps, _mm256_madd_epi16, _mm256_set1_epi32,
        _mm256_setzero_si256, _mm256_storeu_ps, _mm_loadu_si128,
    };
    let (n, rows) = (acc.len(), qx.len());
    assert_eq!(q.len(), rows * n, "int8 matrix shape");
    assert!(rows.is_multiple_of(2), "rows in pairs");
    let blocks = n / I8_BLOCK * I8_BLOCK;
    let pair = |r: usize| (qx[r] as u16 as u32 | (qx[r + 1] as u16 as u32) << 16) as i32;
    for j0 in (0..blocks).step_by(I8_BLOCK) {
        // The block's row pairs are contiguous: `2 · I8_BLOCK` bytes each.
        let block = &q[j0 * rows..(j0 + I8_BLOCK) * rows];
        let mut r0 = 0;
        while r0 < rows {
            let r1 = rows.min(r0 + 2 * PAIRS_PER_CHUNK);
            let mut sum: [__m256i; I8_BLOCK / 8] = [_mm256_setzero_si256(); I8_BLOCK / 8];
            for r in (r0..r1).step_by(2) {
                let xv = _mm256_set1_epi32(pair(r));
                let base = r * I8_BLOCK;
                for (i, s) in sum.iter_mut().enumerate() {
                    // SAFETY: `base + 16·i + 16 <= (r + 2)·I8_BLOCK <=
                    // block.len()`; an unaligned 16-byte load.
                    unsafe {
                        let w =
                            _mm_loadu_si128(block.as_ptr().add(base + 16 * i).cast::<__m128i>());
                        *s = _mm256_add_epi32(*s, _mm256_madd_epi16(_mm256_cvtepi8_epi16(w), xv));
                    }
                }
            }
            for (i, s) in sum.iter().enumerate() {
                let at = j0 + 8 * i;
                // SAFETY: `at + 8 <= j0 + I8_BLOCK <= n` = the length of `acc`.
                unsafe {
                    let a: __m256 = _mm256_loadu_ps(acc.as_ptr().add(at));
                    _mm256_storeu_ps(
                        acc.as_mut_ptr().add(at),
                        _mm256_add_ps(a, _mm256_cvtepi32_ps(*s)),
                    );
                }
            }
            r0 = r1;
        }
    }
    if blocks < n {
        i8_columns_generic(qx, q, acc, blocks);
    }
}

/// Where `q[r, j]` of a `d_in x n` int8 matrix is stored: by blocks of
/// [`I8_BLOCK`] output columns (the last one narrower); in a block, by
/// pairs of rows (`d_in` rounded up to even, the extra row zeros), each
/// pair's two rows interleaved column by column, so that the product reads
/// memory in order and one 16-byte load holds two rows of eight outputs.
fn i8_index(d_in: usize, n: usize, r: usize, j: usize) -> usize {
    let rows = d_in.next_multiple_of(2);
    let j0 = j / I8_BLOCK * I8_BLOCK;
    let w = I8_BLOCK.min(n - j0);
    j0 * rows + (r / 2) * 2 * w + (j - j0) * 2 + r % 2
}

/// Columns `from..` of the int8 product (see [`i8_product_avx2`]) on any
/// CPU; the compiler vectorises it for NEON on aarch64.
fn i8_columns_generic(qx: &[i16], q: &[i8], acc: &mut [f32], from: usize) {
    let (n, rows) = (acc.len(), qx.len());
    let mut sum = [0i32; I8_BLOCK];
    let mut j0 = from;
    while j0 < n {
        let w = I8_BLOCK.min(n - j0);
        let block = &q[j0 * rows..(j0 + w) * rows];
        for (xc, bc) in qx
            .chunks(2 * PAIRS_PER_CHUNK)
            .zip(block.chunks(2 * PAIRS_PER_CHUNK * w))
        {
            let sum = &mut sum[..w];
            sum.fill(0);
            for (xp, pair) in xc.chunks_exact(2).zip(bc.chunks_exact(2 * w)) {
                let (x0, x1) = (i32::from(xp[0]), i32::from(xp[1]));
                for (s, wv) in sum.iter_mut().zip(pair.chunks_exact(2)) {
                    *s += x0 * i32::from(wv[0]) + x1 * i32::from(wv[1]);
                }
            }
            for (a, &s) in acc[j0..j0 + w].iter_mut().zip(sum.iter()) {
                *a += s as f32;
            }
        }
        j0 += w;
    }
}

#[inline(always)]
fn axpy_rows_generic(x: &[f32], w: &[f32], y: &mut [f32]) {
    let n = y.len();
    for (r, &xr) in x.iter().enumerate() {
        let row = &w[r * n..(r + 1) * n];
        for (yv, &wv) in y.iter_mut().zip(row) {
            *yv = xr.mul_add(wv, *yv);
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use burn::nn::LinearConfig;

    fn reference(x: &[f32], w: &[f32], b: &[f32], d_in: usize, d_out: usize) -> Vec<f32> {
        (0..d_out)
            .map(|j| {
                b[j] as f64
                    + (0..d_in)
                        .map(|i| x[i] as f64 * w[i * d_out + j] as f64)
                        .sum::<f64>()
            })
            .map(|v| v as f32)
            .collect()
    }

    #[test]
    fn equals_burn_linear_in_f32_and_is_f32_when_f16_would_lose() {
        let device = crate::model::cpu_device();
        let lin = LinearConfig::new(37, 21).init(&device);
        let host = HostLinear::from_linear(&lin);
        assert!(!host.is_half(), "random f32 weights are not f16 values");
        let x = Tensor::<2>::random([3, 37], burn::tensor::Distribution::Default, &device);
        let want: Vec<f32> = lin.forward(x.clone()).into_data().try_into_vec().unwrap();
        let got: Vec<f32> = host.forward(x).into_data().try_into_vec().unwrap();
        assert_eq!(want.len(), got.len());
        for (a, b) in want.iter().zip(&got) {
            assert!((a - b).abs() < 1e-5, "{a} vs {b}");
        }
    }

    #[test]
    fn f16_weights_are_kept_in_f16_and_give_the_f32_product() {
        let (d_in, d_out) = (45usize, 19usize); // not a multiple of the row step
        let w: Vec<f32> = (0..d_in * d_out)
            .map(|i| f16::from_f32(((i * 37 % 101) as f32 - 50.0) / 64.0).to_f32())
            .collect();
        let b: Vec<f32> = (0..d_out).map(|j| j as f32 * 0.25 - 1.0).collect();
        let x: Vec<f32> = (0..d_in)
            .map(|i| ((i * 13 % 7) as f32 - 3.0) * 0.3)
            .collect();
        let host = HostLinear::new(w.clone(), b.clone(), d_in, d_out);
        assert!(host.is_half());
        assert_eq!(host.bytes(), 2 * d_in * d_out + 4 * d_out);
        let mut y = vec![0.0; d_out];
        host.row(&x, &mut y);
        let want = reference(&x, &w, &b, d_in, d_out);
        for (a, b) in want.iter().zip(&y) {
            assert!((a - b).abs() < 1e-5, "{a} vs {b}");
        }
        // One weight that f16 cannot hold: the whole matrix stays f32.
        let mut w2 = w;
        w2[3] = 0.1;
        assert!(!HostLinear::new(w2, b, d_in, d_out).is_half());
    }

    #[test]
    fn int8_weights_are_the_f32_product_of_their_dequantised_matrix() {
        // Narrower than a register block, and wider with a remainder.
        for (d_in, d_out) in [
            (45usize, 19usize),
            (37, 2 * I8_BLOCK + 6),
            (2 * PAIRS_PER_CHUNK * 2 + 9, I8_BLOCK),
        ] {
            int8_product_case(d_in, d_out);
        }
    }

    fn int8_product_case(d_in: usize, d_out: usize) {
        let w: Vec<f32> = (0..d_in * d_out)
            .map(|i| ((i * 37 % 101) as f32 - 50.0) / 64.0 * (1.0 + (i / d_out) as f32))
            .collect();
        let b: Vec<f32> = (0..d_out).map(|j| j as f32 * 0.25 - 1.0).collect();
        let x: Vec<f32> = (0..d_in)
            .map(|i| ((i * 13 % 7) as f32 - 3.0) * 0.3)
            .collect();
        let full = HostLinear::new(w.clone(), b.clone(), d_in, d_out);
        let q = full.to_int8();
        assert!(q.is_int8() && !full.is_int8());
        let rows = d_in.next_multiple_of(2);
        assert_eq!(q.bytes(), rows * d_out + 4 * d_in + 4 * d_out);
        let Weights::I8 { q: qw, scale } = &q.weight else {
            unreachable!()
        };
        // Each weight within half a step of its row's scale, the largest
        // of each row exactly at ±127; the padding row (odd d_in) zeros.
        let mut deq = vec![0.0f32; d_in * d_out];
        for r in 0..d_in {
            let row = &w[r * d_out..(r + 1) * d_out];
            assert!((0..d_out).any(|j| qw[i8_index(d_in, d_out, r, j)].abs() == 127));
            for j in 0..d_out {
                let at = r * d_out + j;
                deq[at] = f32::from(qw[i8_index(d_in, d_out, r, j)]) * scale[r];
                assert!((deq[at] - row[j]).abs() <= scale[r] * 0.5001, "r {r} j {j}");
            }
        }
        for r in d_in..rows {
            assert!((0..d_out).all(|j| qw[i8_index(d_in, d_out, r, j)] == 0));
        }
        let mut y = vec![0.0; d_out];
        q.row(&x, &mut y);
        // The integer product, exactly (f64), times the input step.
        let (qx, step) = quantise_input(&x, scale).unwrap();
        for j in 0..d_out {
            let dot: f64 = (0..d_in)
                .map(|r| f64::from(qx[r]) * f64::from(qw[i8_index(d_in, d_out, r, j)]))
                .sum();
            let exact = f64::from(b[j]) + f64::from(step) * dot;
            assert!(
                (f64::from(y[j]) - exact).abs() < 1e-6 * exact.abs().max(1.0),
                "{} vs {exact}",
                y[j]
            );
        }
        // Against the dequantised weights times the f32 input: each input
        // moved by at most half a step.
        let want = reference(&x, &deq, &b, d_in, d_out);
        for (j, (a, got)) in want.iter().zip(&y).enumerate() {
            let bound: f32 = (0..d_in)
                .map(|r| 0.5 * step * f32::from(qw[i8_index(d_in, d_out, r, j)]).abs())
                .sum();
            assert!(
                (a - got).abs() <= bound + 1e-5,
                "{a} vs {got} (bound {bound})"
            );
        }
        // The generic kernel (aarch64) gives the same bits as the AVX2 one.
        let mut generic = vec![0.0f32; d_out];
        i8_columns_generic(&qx, qw, &mut generic, 0);
        #[cfg(target_arch = "x86_64")]
        if std::arch::is_x86_feature_detected!("avx2") {
            let mut avx2 = vec![0.0f32; d_out];
            // SAFETY: the CPU has AVX2 (checked just above).
            unsafe { i8_product_avx2(&qx, qw, &mut avx2) };
            assert_eq!(avx2, generic);
        }
        let from_generic: Vec<f32> = b
            .iter()
            .zip(&generic)
            .map(|(bv, a)| bv + step * a)
            .collect();
        assert_eq!(y, from_generic);
        // A zero row keeps scale 1 and all-zero codes.
        let mut wz = w;
        wz[..d_out].fill(0.0);
        let qz = HostLinear::new(wz, b, d_in, d_out).to_int8();
        let Weights::I8 { q: qzw, scale: sz } = &qz.weight else {
            unreachable!()
        };
        assert_eq!(sz[0], 1.0);
        assert!((0..d_out).all(|j| qzw[i8_index(d_in, d_out, 0, j)] == 0));
    }

    /// More rows than one integer chunk holds, at the largest codes: the
    /// chunked sums neither overflow nor lose the product.
    #[test]
    fn int8_product_of_many_rows_at_full_scale_does_not_overflow() {
        let (d_in, d_out) = (4 * PAIRS_PER_CHUNK * 2 + 3, I8_BLOCK);
        let w = vec![1.0f32; d_in * d_out];
        let host = HostLinear::new(w, vec![0.0; d_out], d_in, d_out).to_int8();
        let mut y = vec![0.0; d_out];
        host.row(&vec![2.0; d_in], &mut y);
        for v in y {
            assert!((v - 2.0 * d_in as f32).abs() < 1e-3 * d_in as f32, "{v}");
        }
    }

    #[test]
    fn a_non_finite_weight_gives_non_finite_outputs_in_int8_too() {
        for bad in [f32::NAN, f32::INFINITY] {
            let mut w = vec![0.5f32; 6];
            w[2] = bad;
            let host = HostLinear::new(w, vec![0.0; 2], 3, 2).to_int8();
            let mut y = vec![0.0; 2];
            host.row(&[1.0, 1.0, 1.0], &mut y);
            assert!(y.iter().all(|v| v.is_nan()), "{bad}: {y:?}");
        }
    }

    #[test]
    fn nan_input_gives_nan_output() {
        let host = HostLinear::new(vec![0.5; 6], vec![0.0; 2], 3, 2);
        let mut y = vec![0.0; 2];
        host.row(&[1.0, f32::NAN, 0.0], &mut y);
        assert!(y.iter().all(|v| v.is_nan()));
    }
}
