//! The convolutions' GEMM in integers (inference): weights in int8 with one
//! scale per output column, each row of the im2col matrix in 7 bits with
//! one scale per row, products summed exactly in `i32`, the sum scaled back
//! to f32 once per output.
//!
//! Why 7 bits: AVX2 has no 8-bit dot product into 32 bits (that is VNNI);
//! its `vpmaddubsw` multiplies unsigned bytes by signed ones and adds
//! pairs into 16 bits with saturation. An activation `a` is held as
//! `q = round(a / s)` in `-63..=63` plus 64, in `1..=127`, so that a pair
//! is at most `2 · 127 · 127 = 32,258 < 2^15`: never saturated. The 64
//! added to each activation is taken out of the sum with the weights'
//! column sums. One AVX2 step then multiplies four rows of the matrix in
//! three instructions (`vpmaddubsw`, `vpmaddwd` against ones, `vpaddd`)
//! where f32 takes four fused multiply-adds, and loads and broadcasts a
//! quarter as often.
//!
//! Every product and sum is an integer, so the AVX2 kernel and the portable
//! one (aarch64, x86-64 without AVX2) give the same bits; the quantisation
//! and the scaling back are the same scalar f32 code on both.
//!
//! Weight rows are taken in groups of four; a product over a range of rows
//! that does not start and end on a group (three input channels a tap) is
//! left to the f32 kernel ([`Int8Weights::covers`]).
//!
//! Each row of the im2col matrix is quantised as it is multiplied, which
//! costs about one instruction per value with AVX2: it pays where a value
//! meets many output columns (the trajectory encoder: 32 and 800), not
//! where it meets 8-32 (the vision encoder's slices, which stay f32).

use std::cell::RefCell;
use std::ops::Range;
use std::sync::Arc;

use super::host_conv::Strides;

/// Activation levels either side of zero.
const A_LEVELS: f32 = 63.0;
/// Added to each quantised activation to make it unsigned.
const A_OFFSET: i32 = 64;
/// Weight levels either side of zero.
const W_LEVELS: f32 = 127.0;
/// Rows of a weight group: the four bytes `vpmaddubsw` + `vpmaddwd` sum.
const GROUP: usize = 4;

thread_local! {
    /// The quantised activations, their row scales and the column offsets
    /// of the current product, reused between calls.
    static SCRATCH: RefCell<Scratch> = RefCell::new(Scratch::default());
}

#[derive(Default)]
struct Scratch {
    a: Vec<u8>,
    scale: Vec<f32>,
    offset: Vec<i32>,
    sums: Vec<i32>,
}

/// One weight layout `[rows, n]` in int8, one scale per column.
#[derive(Debug, Clone)]
pub struct Int8Weights {
    n: usize,
    rows: usize,
    /// `[groups][n][4]`: the four rows of a group for one column side by
    /// side; rows past `rows` are zero.
    q: Arc<[i8]>,
    /// `[n]`: `w[p, j] ≈ q[p, j] · scale[j]`.
    scale: Arc<[f32]>,
    /// `[groups + 1][n]`: the sum of `q` over the groups before each.
    prefix: Arc<[i32]>,
}

impl Int8Weights {
    /// From row-major `[rows, n]` weights: symmetric, round to nearest
    /// even, `scale[j] = max_p |w[p, j]| / 127`.
    pub fn new(w: &[f32], n: usize) -> Int8Weights {
        assert!(n > 0 && w.len().is_multiple_of(n), "weight rows");
        let rows = w.len() / n;
        let groups = rows.div_ceil(GROUP);
        let scale: Vec<f32> = (0..n)
            .map(|j| {
                let max = (0..rows).map(|p| w[p * n + j].abs()).fold(0.0f32, f32::max);
                max / W_LEVELS
            })
            .collect();
        let mut q = vec![0i8; groups * n * GROUP];
        for p in 0..rows {
            for j in 0..n {
                let v = if scale[j] > 0.0 {
                    (w[p * n + j] / scale[j])
                        .round_ties_even()
                        .clamp(-W_LEVELS, W_LEVELS) as i8
                } else {
                    0
                };
                q[((p / GROUP) * n + j) * GROUP + p % GROUP] = v;
            }
        }
        let mut prefix = vec![0i32; (groups + 1) * n];
        for g in 0..groups {
            for j in 0..n {
                let s: i32 = q[(g * n + j) * GROUP..(g * n + j + 1) * GROUP]
                    .iter()
                    .map(|&v| i32::from(v))
                    .sum();
                prefix[(g + 1) * n + j] = prefix[g * n + j] + s;
            }
        }
        Int8Weights {
            n,
            rows,
            q: q.into(),
            scale: scale.into(),
            prefix: prefix.into(),
        }
    }

    /// Whether [`gemm`] can take the weight rows `rows`: whole groups.
    pub fn covers(&self, rows: &Range<usize>) -> bool {
        rows.start < rows.end
            && rows.end <= self.rows
            && rows.start.is_multiple_of(GROUP)
            && (rows.end.is_multiple_of(GROUP) || rows.end == self.rows)
    }
}

/// `dst (+)= a · w[rows]` in integers: `a` `m x rows.len()` read with its
/// strides (or its columns gathered from `columns`, as
/// `host_conv::gemm_rows` reads them), `dst` `m x n`. Bounds are the
/// caller's to check (`host_conv::gemm_rows` does); `rows` must be
/// [`Int8Weights::covers`]ed.
#[allow(clippy::too_many_arguments)]
pub(super) fn gemm(
    w: &Int8Weights,
    rows: Range<usize>,
    m: usize,
    a: &[f32],
    a_s: Strides,
    columns: Option<&[usize]>,
    dst: &mut [f32],
    dst_s: Strides,
    store: bool,
) {
    assert!(w.covers(&rows), "whole weight groups");
    let n = w.n;
    let kk = rows.len();
    let groups = kk.div_ceil(GROUP);
    let width = groups * GROUP;
    let (g0, g1) = (rows.start / GROUP, rows.start / GROUP + groups);
    SCRATCH.with(|s| {
        let s = &mut *s.borrow_mut();
        quantise_rows(m, kk, width, a, a_s, columns, s);
        s.offset.clear();
        s.offset
            .extend((0..n).map(|j| A_OFFSET * (w.prefix[g1 * n + j] - w.prefix[g0 * n + j])));
        let k = Kernel {
            m,
            n,
            groups,
            a: s.a.as_ptr(),
            a_scale: s.scale.as_ptr(),
            q: w.q[g0 * n * GROUP..].as_ptr(),
            w_scale: w.scale.as_ptr(),
            offset: s.offset.as_ptr(),
            dst: dst.as_mut_ptr(),
            dst_s,
            store,
        };
        #[cfg(target_arch = "x86_64")]
        {
            if has_simd_kernel() {
                // SAFETY: the CPU has AVX2 (`has_simd_kernel`); the
                // quantised rows are `m x width`, the weights from group
                // `g0` hold `groups` groups of `n` columns, the scales and
                // offsets `n`, and `dst` holds every `(i, j)` its strides
                // reach (the caller checked).
                unsafe { avx2::gemm(&k) };
                return;
            }
        }
        portable(&k, &mut s.sums);
    });
}

/// Whether this CPU runs the integer products in SIMD registers (the AVX2
/// kernel, x86-64); elsewhere they run in the portable loop, which takes
/// more instructions than the f32 kernels (`Convolutions::Auto` chooses by
/// this).
pub(super) fn has_simd_kernel() -> bool {
    #[cfg(target_arch = "x86_64")]
    {
        std::arch::is_x86_feature_detected!("avx2")
    }
    #[cfg(not(target_arch = "x86_64"))]
    {
        false
    }
}

/// Row `i` of `a` (`kk` values) into `s.a[i·width..]` as `q + 64`; its
/// scale into `s.scale[i]`. A row holding a NaN or an infinity gets a NaN
/// scale, so that its outputs are NaN as in f32.
fn quantise_rows(
    m: usize,
    kk: usize,
    width: usize,
    a: &[f32],
    a_s: Strides,
    columns: Option<&[usize]>,
    s: &mut Scratch,
) {
    // Not cleared: every byte a row's products read past `kk` meets a zero
    // weight, and a row left unwritten (all zeros, or not finite) has a
    // zero or NaN scale, which is its output whatever its bytes.
    if s.a.len() < m * width {
        s.a.resize(m * width, A_OFFSET as u8);
    }
    s.scale.clear();
    #[cfg(target_arch = "x86_64")]
    {
        if columns.is_none() && a_s.col == 1 && std::arch::is_x86_feature_detected!("avx2") {
            for i in 0..m {
                let row = &a[i * a_s.row..i * a_s.row + kk];
                let dst = &mut s.a[i * width..i * width + kk];
                // SAFETY: the CPU has AVX2; `row` and `dst` are `kk` long.
                s.scale.push(unsafe { avx2::quantise_row(row, dst) });
            }
            return;
        }
    }
    let at = |i: usize, p: usize| match columns {
        Some(cols) => a[i * a_s.row + cols[p]],
        None => a[i * a_s.row + p * a_s.col],
    };
    for i in 0..m {
        let mut max = 0.0f32;
        let mut finite = true;
        for p in 0..kk {
            let v = at(i, p);
            finite &= v.is_finite();
            max = max.max(v.abs());
        }
        if !finite {
            s.scale.push(f32::NAN);
            continue;
        }
        if max == 0.0 {
            s.scale.push(0.0);
            continue;
        }
        let inv = A_LEVELS / max;
        s.scale.push(max / A_LEVELS);
        let row = &mut s.a[i * width..i * width + kk];
        for (p, q) in row.iter_mut().enumerate() {
            let v = (at(i, p) * inv)
                .round_ties_even()
                .clamp(-A_LEVELS, A_LEVELS) as i32;
            *q = (v + A_OFFSET) as u8;
        }
    }
}

/// The raw operands of one product.
struct Kernel {
    m: usize,
    n: usize,
    groups: usize,
    /// `m x groups·4` quantised activations.
    a: *const u8,
    a_scale: *const f32,
    /// The weights from the first group of the product on.
    q: *const i8,
    w_scale: *const f32,
    /// `[n]`: 64 times each column's weight sum over the product's rows.
    offset: *const i32,
    dst: *mut f32,
    dst_s: Strides,
    store: bool,
}

impl Kernel {
    /// The output `(i, j)` from its integer sum: the same f32 operations,
    /// in the same order, on every path.
    ///
    /// # Safety
    /// `i < m`, `j < n`.
    #[inline(always)]
    unsafe fn write(&self, i: usize, j: usize, sum: i32) {
        // SAFETY: `i < m`, `j < n`, as the caller promises.
        unsafe {
            let v =
                ((sum - *self.offset.add(j)) as f32 * *self.a_scale.add(i)) * *self.w_scale.add(j);
            let d = self.dst.add(i * self.dst_s.row + j * self.dst_s.col);
            *d = if self.store { v } else { *d + v };
        }
    }
}

/// Any CPU: the sums one output row at a time.
fn portable(k: &Kernel, sums: &mut Vec<i32>) {
    let (n, width) = (k.n, k.groups * GROUP);
    sums.clear();
    sums.resize(n, 0);
    for i in 0..k.m {
        sums.fill(0);
        // SAFETY: row `i < m` of the `m x width` activations.
        let row = unsafe { std::slice::from_raw_parts(k.a.add(i * width), width) };
        for g in 0..k.groups {
            // SAFETY: group `g < groups` of the product's weights.
            let q = unsafe { std::slice::from_raw_parts(k.q.add(g * n * GROUP), n * GROUP) };
            let x = &row[g * GROUP..(g + 1) * GROUP];
            for (sum, w) in sums.iter_mut().zip(q.chunks_exact(GROUP)) {
                *sum += x
                    .iter()
                    .zip(w)
                    .map(|(&a, &b)| i32::from(a) * i32::from(b))
                    .sum::<i32>();
            }
        }
        for (j, &sum) in sums.iter().enumerate() {
            // SAFETY: `i < m`, `j < n`.
            unsafe { k.write(i, j, sum) };
        }
    }
}

#[cfg(target_arch = "x86_64")]
mod avx2 {
    use super::{Kernel, GROUP};
    use std::arch::x86_64::*;

    /// # Safety
    /// The CPU has AVX2; the operands as [`Kernel`] says.
    #[target_feature(enable = "avx2")]
    pub(super) unsafe fn gemm(k: &Kernel) {
        // SAFETY (all calls): `j0 + width <= n`.
        unsafe { column_blocks!(k.n, |j0| rows::<2>(k, j0), rows::<1>(k, j0), rest(k, j0)) }
    }

    /// Every block of rows for columns `j0..j0 + 8·V`.
    #[target_feature(enable = "avx2")]
    unsafe fn rows<const V: usize>(k: &Kernel, j0: usize) {
        // SAFETY (all calls): `i0 + R <= m`, `j0 + 8·V <= n`.
        unsafe { row_blocks!(k.m, |R, i0| block::<R, V>(k, i0, j0)) }
    }

    /// `R x 8·V` sums in registers: per group of four rows, each weight
    /// register loaded once, each row's four activations broadcast once.
    #[target_feature(enable = "avx2")]
    #[inline]
    unsafe fn block<const R: usize, const V: usize>(k: &Kernel, i0: usize, j0: usize) {
        let width = k.groups * GROUP;
        let ones = _mm256_set1_epi16(1);
        let mut acc: [[__m256i; V]; R] = [[_mm256_setzero_si256(); V]; R];
        // SAFETY: weight group `g < groups`, columns `j0..j0 + 8·V <= n`
        // (32 bytes a register); activation rows `i0..i0 + R <= m`, bytes
        // `4g..4g + 4 <= width`.
        unsafe {
            for g in 0..k.groups {
                let w: [__m256i; V] = std::array::from_fn(|v| {
                    _mm256_loadu_si256(k.q.add((g * k.n + j0 + 8 * v) * GROUP).cast())
                });
                for (r, row) in acc.iter_mut().enumerate() {
                    let four =
                        k.a.add((i0 + r) * width + g * GROUP)
                            .cast::<i32>()
                            .read_unaligned();
                    let x = _mm256_set1_epi32(four);
                    for (s, &wv) in row.iter_mut().zip(&w) {
                        let pairs = _mm256_maddubs_epi16(x, wv);
                        *s = _mm256_add_epi32(*s, _mm256_madd_epi16(pairs, ones));
                    }
                }
            }
            for (r, row) in acc.iter().enumerate() {
                let i = i0 + r;
                let a_scale = _mm256_set1_ps(*k.a_scale.add(i));
                for (v, &s) in row.iter().enumerate() {
                    let j = j0 + 8 * v;
                    let sum = _mm256_sub_epi32(s, _mm256_loadu_si256(k.offset.add(j).cast()));
                    let val = _mm256_mul_ps(
                        _mm256_mul_ps(_mm256_cvtepi32_ps(sum), a_scale),
                        _mm256_loadu_ps(k.w_scale.add(j)),
                    );
                    let d = k.dst.add(i * k.dst_s.row + j * k.dst_s.col);
                    if k.dst_s.col == 1 {
                        let out = if k.store {
                            val
                        } else {
                            _mm256_add_ps(_mm256_loadu_ps(d), val)
                        };
                        _mm256_storeu_ps(d, out);
                    } else {
                        let mut lanes = [0.0f32; 8];
                        _mm256_storeu_ps(lanes.as_mut_ptr(), val);
                        for (t, &l) in lanes.iter().enumerate() {
                            let at = d.add(t * k.dst_s.col);
                            *at = if k.store { l } else { *at + l };
                        }
                    }
                }
            }
        }
    }

    /// One contiguous row into `dst` as `q + 64` (what `quantise_rows`
    /// does, the same bits: the scale and its inverse are the same scalar
    /// operations, `vcvtps2dq` rounds to nearest even as `round_ties_even`
    /// does, and the clamp to `-63..=63` is kept); returns the scale.
    ///
    /// # Safety
    /// The CPU has AVX2; `dst.len() == row.len()`.
    #[target_feature(enable = "avx2")]
    pub(super) unsafe fn quantise_row(row: &[f32], dst: &mut [u8]) -> f32 {
        use super::{A_LEVELS, A_OFFSET};
        debug_assert_eq!(row.len(), dst.len());
        let kk = row.len();
        let body = kk - kk % 8;
        // SAFETY: every load is of 8 values at `p + 8 <= body <= kk`, every
        // store of 8 bytes at `p + 8 <= body`.
        unsafe {
            let sign = _mm256_set1_ps(-0.0);
            let (mut max, mut nan) = (_mm256_setzero_ps(), _mm256_setzero_ps());
            for p in (0..body).step_by(8) {
                let v = _mm256_loadu_ps(row.as_ptr().add(p));
                max = _mm256_max_ps(max, _mm256_andnot_ps(sign, v));
                nan = _mm256_or_ps(nan, _mm256_cmp_ps::<_CMP_UNORD_Q>(v, v));
            }
            let mut lanes = [0.0f32; 8];
            _mm256_storeu_ps(lanes.as_mut_ptr(), max);
            let mut m = lanes.iter().fold(0.0f32, |a, &b| a.max(b));
            let mut finite = _mm256_movemask_ps(nan) == 0;
            for &v in &row[body..] {
                finite &= v.is_finite();
                m = m.max(v.abs());
            }
            if !finite || !m.is_finite() {
                return f32::NAN;
            }
            if m == 0.0 {
                return 0.0;
            }
            let inv = A_LEVELS / m;
            let inv8 = _mm256_set1_ps(inv);
            let (lo, hi) = (_mm256_set1_epi32(-63), _mm256_set1_epi32(63));
            let offset = _mm_set1_epi8(A_OFFSET as i8);
            for p in (0..body).step_by(8) {
                let v = _mm256_mul_ps(_mm256_loadu_ps(row.as_ptr().add(p)), inv8);
                let q = _mm256_min_epi32(_mm256_max_epi32(_mm256_cvtps_epi32(v), lo), hi);
                let words =
                    _mm_packs_epi32(_mm256_castsi256_si128(q), _mm256_extracti128_si256::<1>(q));
                let bytes = _mm_add_epi8(_mm_packs_epi16(words, words), offset);
                _mm_storel_epi64(dst.as_mut_ptr().add(p).cast(), bytes);
            }
            for p in body..kk {
                let v = (row[p] * inv).round_ties_even().clamp(-A_LEVELS, A_LEVELS) as i32;
                dst[p] = (v + A_OFFSET) as u8;
            }
            m / A_LEVELS
        }
    }

    /// The last columns (fewer than 8), one at a time.
    ///
    /// # Safety
    /// As [`gemm`], `j0 < n`.
    unsafe fn rest(k: &Kernel, j0: usize) {
        let width = k.groups * GROUP;
        for i in 0..k.m {
            for j in j0..k.n {
                let mut sum = 0i32;
                for g in 0..k.groups {
                    for t in 0..GROUP {
                        // SAFETY: inside the activations and the weights.
                        unsafe {
                            sum += i32::from(*k.a.add(i * width + g * GROUP + t))
                                * i32::from(*k.q.add((g * k.n + j) * GROUP + t));
                        }
                    }
                }
                // SAFETY: `i < m`, `j < n`.
                unsafe { k.write(i, j, sum) };
            }
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    /// `len` values in `[-1, 1)` from the bench's noise.
    fn values(len: usize, seed: u64) -> Vec<f32> {
        crate::model::bench::noise(len, seed)
            .into_iter()
            .map(|v| 2.0 * v - 1.0)
            .collect()
    }

    fn reference(w: &[f32], n: usize, rows: Range<usize>, a: &[f32], m: usize) -> Vec<f32> {
        let kk = rows.len();
        let mut out = vec![0.0f32; m * n];
        for i in 0..m {
            for j in 0..n {
                out[i * n + j] = (0..kk)
                    .map(|p| a[i * kk + p] * w[(rows.start + p) * n + j])
                    .sum();
            }
        }
        out
    }

    /// Within the quantisation's error of the f32 product, for every block
    /// shape (rows 1-7, columns 16 + 8 + 3), a row range inside the
    /// weights, stored and added.
    #[test]
    fn near_the_f32_product() {
        let (n, total) = (27usize, 40usize);
        let w = values(total * n, 1);
        let q = Int8Weights::new(&w, n);
        for m in 1..=7 {
            for rows in [0..total, 8..36, 4..8] {
                let kk = rows.len();
                let a = values(m * kk, m as u64 + 7);
                let want = reference(&w, n, rows.clone(), &a, m);
                let mut got = vec![1.0f32; m * n];
                let s = Strides { row: kk, col: 1 };
                let d = Strides { row: n, col: 1 };
                gemm(&q, rows.clone(), m, &a, s, None, &mut got, d, false);
                // |a| <= 1, |w| <= 1: each activation within half a step
                // (1/126) of its value, each weight within 1/254, so each
                // product within 0.012, and the sum within `kk` of them.
                let bound = 0.012 * kk as f32 + 1e-5;
                for (g, w) in got.iter().zip(&want) {
                    assert!((g - 1.0 - w).abs() < bound, "{} vs {w}", g - 1.0);
                }
                let mut stored = vec![f32::NAN; m * n];
                gemm(&q, rows.clone(), m, &a, s, None, &mut stored, d, true);
                for (st, g) in stored.iter().zip(&got) {
                    assert_eq!((st + 1.0).to_bits(), g.to_bits());
                }
            }
        }
    }

    /// The AVX2 kernel and the portable one give the same bits, and so do
    /// the AVX2 row quantiser and the scalar one (rows of 68: the vector
    /// body and its scalar tail).
    #[test]
    fn avx2_and_portable_agree_bit_for_bit() {
        let (n, kk, m) = (40usize, 68usize, 13usize);
        let w = values(kk * n, 3);
        let q = Int8Weights::new(&w, n);
        let a = values(m * kk, 4);
        let mut via_gemm = vec![0.0f32; m * n];
        gemm(
            &q,
            0..kk,
            m,
            &a,
            Strides { row: kk, col: 1 },
            None,
            &mut via_gemm,
            Strides { row: n, col: 1 },
            true,
        );
        let mut s = Scratch::default();
        quantise_rows(m, kk, kk, &a, Strides { row: kk, col: 1 }, None, &mut s);
        // The same rows read through gathered columns: the scalar quantiser.
        let mut scalar = Scratch::default();
        let identity: Vec<usize> = (0..kk).collect();
        let gathered = Strides { row: kk, col: 0 };
        quantise_rows(m, kk, kk, &a, gathered, Some(&identity), &mut scalar);
        assert_eq!(s.a[..m * kk], scalar.a[..m * kk]);
        let bits = |v: &[f32]| v.iter().map(|x| x.to_bits()).collect::<Vec<_>>();
        assert_eq!(bits(&s.scale), bits(&scalar.scale));
        let offset: Vec<i32> = (0..n)
            .map(|j| A_OFFSET * q.prefix[(kk / GROUP) * n + j])
            .collect();
        let mut via_portable = vec![0.0f32; m * n];
        let k = Kernel {
            m,
            n,
            groups: kk / GROUP,
            a: s.a.as_ptr(),
            a_scale: s.scale.as_ptr(),
            q: q.q.as_ptr(),
            w_scale: q.scale.as_ptr(),
            offset: offset.as_ptr(),
            dst: via_portable.as_mut_ptr(),
            dst_s: Strides { row: n, col: 1 },
            store: true,
        };
        portable(&k, &mut Vec::new());
        for (x, y) in via_gemm.iter().zip(&via_portable) {
            assert_eq!(x.to_bits(), y.to_bits());
        }
    }

    /// Gathered columns and strided outputs read and write what the
    /// strided forms do.
    #[test]
    fn gathered_columns_and_strided_outputs() {
        let (n, kk, m) = (16usize, 12usize, 5usize);
        let w = values(kk * n, 5);
        let q = Int8Weights::new(&w, n);
        // Column-major `a`: column p at p·m, rows 1 apart.
        let a_cm = values(kk * m, 6);
        let columns: Vec<usize> = (0..kk).map(|p| p * m).collect();
        let mut gathered = vec![0.0f32; m * n];
        gemm(
            &q,
            0..kk,
            m,
            &a_cm,
            Strides { row: 1, col: 0 },
            Some(&columns),
            &mut gathered,
            Strides { row: n, col: 1 },
            true,
        );
        // The same matrix strided, written column-major.
        let mut strided_t = vec![0.0f32; m * n];
        gemm(
            &q,
            0..kk,
            m,
            &a_cm,
            Strides { row: 1, col: m },
            None,
            &mut strided_t,
            Strides { row: 1, col: m },
            true,
        );
        for i in 0..m {
            for j in 0..n {
                assert_eq!(
                    gathered[i * n + j].to_bits(),
                    strided_t[j * m + i].to_bits()
                );
            }
        }
    }

    /// A row of zeros gives zeros; a NaN in a row makes that row's outputs
    /// NaN, as the f32 product would, and leaves the others alone.
    #[test]
    fn zero_rows_and_non_finite_values() {
        let (n, kk, m) = (8usize, 8usize, 3usize);
        let w = values(kk * n, 9);
        let q = Int8Weights::new(&w, n);
        let mut a = values(m * kk, 10);
        a[..kk].fill(0.0);
        a[kk + 3] = f32::NAN;
        let mut out = vec![0.0f32; m * n];
        let s = Strides { row: kk, col: 1 };
        gemm(
            &q,
            0..kk,
            m,
            &a,
            s,
            None,
            &mut out,
            Strides { row: n, col: 1 },
            true,
        );
        assert!(out[..n].iter().all(|&v| v == 0.0));
        assert!(out[n..2 * n].iter().all(|v| v.is_nan()));
        assert!(out[2 * n..].iter().all(|v| v.is_finite()));
    }

    #[test]
    fn covers_whole_groups_only() {
        let q = Int8Weights::new(&values(27 * 8, 2), 8);
        assert!(q.covers(&(0..27)));
        assert!(q.covers(&(8..27)));
        assert!(q.covers(&(4..12)));
        assert!(!q.covers(&(9..18)));
        assert!(!q.covers(&(0..9)));
        assert!(!q.covers(&(0..28)));
    }
}
