//! Fixed linear maps of the EMP network, precomputed as real matrices.
//!
//! Three maps, each a plain `Vec<f32>` in row-major order that the encoders turn
//! into constant tensors (so they work on every backend, for any length, and
//! differentiate):
//! - [`dct_matrix`]: the orthonormal DCT-II used by the motion encoder.
//! - [`lowpass_matrix`]: the square-mask low-pass of the vision encoder fused
//!   with the decimation to `2a x 2a` (`Y = P · X · Pᵀ` per channel).
//! - [`dft_matrices`]: the cos/sin rows of the real DFT whose amplitudes pick
//!   the TimesNet periods of the trajectory encoder.

use std::f64::consts::PI;
use std::sync::{Arc, Mutex, OnceLock, PoisonError};

/// Orthonormal DCT-II matrix `D` (`n x n`, row-major):
/// `D[i, j] = sqrt(2/n) / sqrt(1 + [i == 0]) · cos(pi/n · (j + 1/2) · i)`.
pub fn dct_matrix(n: usize) -> Vec<f32> {
    let mut d = vec![0.0f32; n * n];
    let nf = n as f64;
    for i in 0..n {
        let scale = (2.0 / nf).sqrt() / if i == 0 { 2f64.sqrt() } else { 1.0 };
        for j in 0..n {
            d[i * n + j] = (scale * (PI / nf * (j as f64 + 0.5) * i as f64).cos()) as f32;
        }
    }
    d
}

/// Low-pass with decimation as one real matrix `P` (`2a x s`, row-major).
///
/// The low-pass keeps the DFT frequencies `|f| < a` (both signs, counted from DC)
/// of a length-`s` signal. The result is band-limited, so it is exactly
/// described by its samples on a `2a` grid: `y[m] = x̃(m · s / 2a)` where `x̃` is
/// the full-size filtered signal, i.e.
/// `P[m, n] = 1/s · Σ_{|f| < a} cos(2π f (m/2a − n/s))`.
/// Separable: the 2-D square mask is `Y = P · X · Pᵀ`.
pub fn lowpass_matrix(a: usize, s: usize) -> Vec<f32> {
    assert!(a >= 1 && 2 * a <= s, "low-pass needs 1 <= a and 2a <= s");
    let out = 2 * a;
    let mut p = vec![0.0f32; out * s];
    for m in 0..out {
        for n in 0..s {
            let t = m as f64 / out as f64 - n as f64 / s as f64;
            let mut acc = 1.0; // f = 0
            for f in 1..a {
                acc += 2.0 * (2.0 * PI * f as f64 * t).cos();
            }
            p[m * s + n] = (acc / s as f64) as f32;
        }
    }
    p
}

/// A fixed matrix of this module made once per process and kept: `make`
/// runs the first time `(kind, a, b)` is asked for.
fn shared_matrix(
    kind: &'static str,
    a: usize,
    b: usize,
    make: impl FnOnce() -> Vec<f32>,
) -> Arc<[f32]> {
    type Cache = Mutex<Vec<((&'static str, usize, usize), Arc<[f32]>)>>;
    static CACHE: OnceLock<Cache> = OnceLock::new();
    let mut cache = CACHE
        .get_or_init(Cache::default)
        .lock()
        .unwrap_or_else(PoisonError::into_inner);
    if let Some((_, m)) = cache.iter().find(|(key, _)| *key == (kind, a, b)) {
        return Arc::clone(m);
    }
    let m: Arc<[f32]> = make().into();
    cache.push(((kind, a, b), Arc::clone(&m)));
    m
}

/// [`lowpass_matrix`], computed once per `(a, s)` for the whole process:
/// 30,720 cosines in f64 for `a = 16, s = 64`, which were 0.3-0.4 ms of
/// every streaming tick when made per frame.
pub fn lowpass_matrix_shared(a: usize, s: usize) -> Arc<[f32]> {
    shared_matrix("lowpass", a, s, || lowpass_matrix(a, s))
}

/// [`dct_matrix`], computed once per `n` for the whole process (3,600
/// cosines in f64 for `N = 60`, once per forecast before).
pub fn dct_matrix_shared(n: usize) -> Arc<[f32]> {
    shared_matrix("dct", n, 0, || dct_matrix(n))
}

/// Real-DFT rows for a length-`l` signal: `(cos, sin)`, each `(l/2 + 1) x l`
/// row-major, so that `Re X_f = Σ cos[f, n] x_n` and `Im X_f = −Σ sin[f, n] x_n`.
pub fn dft_matrices(l: usize) -> (Vec<f32>, Vec<f32>) {
    let nf = l / 2 + 1;
    let mut c = vec![0.0f32; nf * l];
    let mut s = vec![0.0f32; nf * l];
    for f in 0..nf {
        for n in 0..l {
            let ang = 2.0 * PI * (f * n % l) as f64 / l as f64;
            c[f * l + n] = ang.cos() as f32;
            s[f * l + n] = ang.sin() as f32;
        }
    }
    (c, s)
}

/// Apply the low-pass + decimation to one `s x s` image plane (row-major)
/// on the host: `P · x · Pᵀ`, `2a x 2a` out. `p` is [`lowpass_matrix`].
pub fn lowpass_plane(p: &[f32], a: usize, s: usize, x: &[f32], out: &mut [f32]) {
    let o = 2 * a;
    debug_assert_eq!(x.len(), s * s);
    debug_assert_eq!(out.len(), o * o);
    // tmp = x · Pᵀ : [s, o]
    let mut tmp = vec![0.0f32; s * o];
    for r in 0..s {
        let row = &x[r * s..(r + 1) * s];
        for m in 0..o {
            let prow = &p[m * s..(m + 1) * s];
            tmp[r * o + m] = dot(row, prow);
        }
    }
    // out = P · tmp : [o, o]
    for m in 0..o {
        let prow = &p[m * s..(m + 1) * s];
        let orow = &mut out[m * o..(m + 1) * o];
        orow.iter_mut().for_each(|v| *v = 0.0);
        for (r, &pv) in prow.iter().enumerate() {
            let trow = &tmp[r * o..(r + 1) * o];
            for (ov, tv) in orow.iter_mut().zip(trow) {
                *ov += pv * tv;
            }
        }
    }
}

fn dot(a: &[f32], b: &[f32]) -> f32 {
    // Four partial sums: lets the compiler vectorise without reassociating floats.
    let mut acc = [0.0f32; 8];
    let chunks = a.len() / 8;
    for i in 0..chunks {
        for k in 0..8 {
            acc[k] += a[i * 8 + k] * b[i * 8 + k];
        }
    }
    let mut sum: f32 = acc.iter().sum();
    for i in chunks * 8..a.len() {
        sum += a[i] * b[i];
    }
    sum
}

#[cfg(test)]
mod tests {
    use super::*;
    use rustfft::{num_complex::Complex, FftPlanner};

    #[test]
    fn shared_matrices_are_made_once_and_equal_fresh_ones() {
        let a = lowpass_matrix_shared(5, 16);
        assert_eq!(&a[..], &lowpass_matrix(5, 16)[..]);
        assert!(Arc::ptr_eq(&a, &lowpass_matrix_shared(5, 16)), "made once");
        let other = lowpass_matrix_shared(4, 16);
        assert_eq!(&other[..], &lowpass_matrix(4, 16)[..], "keyed by (a, s)");
        let dct = dct_matrix_shared(16);
        assert_eq!(&dct[..], &dct_matrix(16)[..], "keyed by kind too");
        assert!(Arc::ptr_eq(&dct, &dct_matrix_shared(16)));
    }

    #[test]
    fn dct_is_orthonormal() {
        for n in [24usize, 60] {
            let d = dct_matrix(n);
            for i in 0..n {
                for k in 0..n {
                    let v: f64 = (0..n)
                        .map(|j| d[i * n + j] as f64 * d[k * n + j] as f64)
                        .sum();
                    let want = if i == k { 1.0 } else { 0.0 };
                    assert!((v - want).abs() < 1e-5, "D·Dᵀ[{i},{k}] = {v}");
                }
            }
        }
    }

    /// The definition: fft2, zero every frequency with |f_y| >= a or |f_x| >= a,
    /// ifft2 at full size.
    fn lowpass_by_fft(x: &[f32], a: usize, s: usize) -> Vec<f32> {
        let mut planner = FftPlanner::<f64>::new();
        let fwd = planner.plan_fft_forward(s);
        let inv = planner.plan_fft_inverse(s);
        let mut g: Vec<Complex<f64>> = x.iter().map(|&v| Complex::new(v as f64, 0.0)).collect();
        let transform = |g: &mut Vec<Complex<f64>>,
                         plan: &std::sync::Arc<dyn rustfft::Fft<f64>>| {
            for r in 0..s {
                plan.process(&mut g[r * s..(r + 1) * s]);
            }
            let mut col = vec![Complex::new(0.0, 0.0); s];
            for c in 0..s {
                for r in 0..s {
                    col[r] = g[r * s + c];
                }
                plan.process(&mut col);
                for r in 0..s {
                    g[r * s + c] = col[r];
                }
            }
        };
        transform(&mut g, &fwd);
        let freq = |i: usize| {
            if i <= s / 2 {
                i as i64
            } else {
                i as i64 - s as i64
            }
        };
        for r in 0..s {
            for c in 0..s {
                if freq(r).unsigned_abs() as usize >= a || freq(c).unsigned_abs() as usize >= a {
                    g[r * s + c] = Complex::new(0.0, 0.0);
                }
            }
        }
        transform(&mut g, &inv);
        g.iter().map(|v| (v.re / (s * s) as f64) as f32).collect()
    }

    fn pseudo_random_image(s: usize, seed: u64) -> Vec<f32> {
        let mut state = seed.wrapping_mul(6364136223846793005).wrapping_add(1);
        (0..s * s)
            .map(|_| {
                state = state
                    .wrapping_mul(6364136223846793005)
                    .wrapping_add(1442695040888963407);
                ((state >> 33) as f32) / (1u64 << 31) as f32
            })
            .collect()
    }

    #[test]
    fn lowpass_equals_fft_definition() {
        let (a, s) = (16usize, 64usize);
        let p = lowpass_matrix(a, s);
        for seed in 0..3 {
            let x = pseudo_random_image(s, seed);
            let full = lowpass_by_fft(&x, a, s);
            let mut y = vec![0.0f32; 4 * a * a];
            lowpass_plane(&p, a, s, &x, &mut y);
            // The decimated result is the full-size low-pass sampled every s/2a pixels.
            let step = s / (2 * a);
            for m in 0..2 * a {
                for n in 0..2 * a {
                    let want = full[(m * step) * s + n * step];
                    let got = y[m * 2 * a + n];
                    assert!(
                        (want - got).abs() < 1e-5,
                        "({m},{n}): fft {want} matrix {got}"
                    );
                }
            }
        }
    }

    #[test]
    fn lowpass_keeps_constant_and_removes_checkerboard() {
        let (a, s) = (16usize, 64usize);
        let p = lowpass_matrix(a, s);
        let mut y = vec![0.0f32; 4 * a * a];
        lowpass_plane(&p, a, s, &vec![0.37; s * s], &mut y);
        assert!(y.iter().all(|v| (v - 0.37).abs() < 1e-5));
        let checker: Vec<f32> = (0..s * s)
            .map(|i| if (i / s + i % s) % 2 == 0 { 1.0 } else { 0.0 })
            .collect();
        lowpass_plane(&p, a, s, &checker, &mut y);
        // Mean 0.5 survives (DC); the checkerboard itself (Nyquist) is gone.
        assert!(y.iter().all(|v| (v - 0.5).abs() < 1e-5), "{:?}", &y[..4]);
    }

    #[test]
    fn dft_rows_match_fft_amplitude() {
        let l = 75;
        let (c, s) = dft_matrices(l);
        let x: Vec<f32> = (0..l).map(|i| ((i * 7 % 11) as f32).sin()).collect();
        let mut buf: Vec<Complex<f64>> = x.iter().map(|&v| Complex::new(v as f64, 0.0)).collect();
        FftPlanner::<f64>::new()
            .plan_fft_forward(l)
            .process(&mut buf);
        for f in 0..l / 2 + 1 {
            let re: f64 = (0..l).map(|n| c[f * l + n] as f64 * x[n] as f64).sum();
            let im: f64 = -(0..l)
                .map(|n| s[f * l + n] as f64 * x[n] as f64)
                .sum::<f64>();
            assert!((re - buf[f].re).abs() < 1e-4 && (im - buf[f].im).abs() < 1e-4);
        }
    }
}
