//! A fused convolution run on the host as im2col + GEMM (inference): its
//! weights laid out once as the GEMM's right-hand side, one scratch
//! buffer per thread for the im2col matrix, and one safe entry to the
//! `gemm` crate (the kernels Flex itself uses). Two shapes of input use it:
//! the trajectory encoder's folded sequences (`grid_conv`) and the vision
//! encoder's single time slices (`slice_conv`).

use std::cell::RefCell;
use std::sync::Arc;

use super::inception::FusedConv;

thread_local! {
    /// The im2col matrix, reused between calls (no allocation per tick).
    static SCRATCH: RefCell<Vec<f32>> = const { RefCell::new(Vec::new()) };
}

/// One fused convolution (odd square or cubic kernel) for the host paths.
#[derive(Debug, Clone)]
pub struct HostConv {
    k: usize,
    c_in: usize,
    c_out: usize,
    /// `[taps·C_in, C_out]` row-major, row `tap·C_in + ci`, the kernel
    /// offsets (`(kt,) ky, kx`) numbered row-major.
    weight: Arc<[f32]>,
    /// 2-D kernels only: the same rows with the offsets numbered
    /// column-major (`kx·k + ky`), so that the taps of a range of kernel
    /// columns are contiguous ([`HostConv::accumulate_kernel_columns`]).
    weight_by_column: Option<Arc<[f32]>>,
    /// 2-D kernels, made on request ([`HostConv::with_tap_products`]): the
    /// weights as `[C_in, taps·C_out]`, element `(ci, tap·C_out + co)`, so
    /// that one GEMM gives every tap's product with every input position
    /// ([`HostConv::tap_products`]).
    weight_by_input: Option<Arc<[f32]>>,
    /// `[C_out]`.
    bias: Arc<[f32]>,
}

/// Where element `(i, j)` of a matrix is: `i·row + j·col`.
#[derive(Debug, Clone, Copy)]
pub struct Strides {
    pub row: usize,
    pub col: usize,
}

impl HostConv {
    /// From a fused 2-D (`[C_out, C_in, k, k]`) or 3-D
    /// (`[C_out, C_in, k, k, k]`) convolution.
    pub fn from_fused<const D: usize>(conv: &FusedConv<D>) -> HostConv {
        let dims = conv.weight.dims();
        let (c_out, c_in, k) = (dims[0], dims[1], dims[2]);
        assert!(dims[2..].iter().all(|&d| d == k), "square or cubic kernel");
        let taps = k.pow(D as u32 - 2);
        let host = |d: burn::tensor::TensorData, what: &str| -> Vec<f32> {
            d.convert::<f32>()
                .try_into_vec()
                .unwrap_or_else(|e| panic!("f32 {what}: {e:?}"))
        };
        let w = host(conv.weight.clone().into_data(), "weights");
        let bias = host(conv.bias.clone().into_data(), "bias");
        let mut weight = vec![0.0f32; taps * c_in * c_out];
        for co in 0..c_out {
            for ci in 0..c_in {
                for tap in 0..taps {
                    weight[(tap * c_in + ci) * c_out + co] = w[(co * c_in + ci) * taps + tap];
                }
            }
        }
        let weight_by_column = (D == 4).then(|| {
            let mut by_col = vec![0.0f32; weight.len()];
            for ky in 0..k {
                for kx in 0..k {
                    let (from, to) = ((ky * k + kx) * c_in, (kx * k + ky) * c_in);
                    by_col[to * c_out..(to + c_in) * c_out]
                        .copy_from_slice(&weight[from * c_out..(from + c_in) * c_out]);
                }
            }
            by_col.into()
        });
        HostConv {
            k,
            c_in,
            c_out,
            weight: weight.into(),
            weight_by_column,
            weight_by_input: None,
            bias: bias.into(),
        }
    }

    /// This convolution with the layout [`HostConv::tap_products`] reads
    /// (`taps·C_in·C_out` more floats; 2-D kernels only).
    pub fn with_tap_products(mut self) -> HostConv {
        assert!(self.weight_by_column.is_some(), "a 2-D convolution");
        let (taps, c_in, c_out) = (self.k * self.k, self.c_in, self.c_out);
        let mut by_input = vec![0.0f32; self.weight.len()];
        for tap in 0..taps {
            for ci in 0..c_in {
                let from = (tap * c_in + ci) * c_out;
                let to = (ci * taps + tap) * c_out;
                by_input[to..to + c_out].copy_from_slice(&self.weight[from..from + c_out]);
            }
        }
        self.weight_by_input = Some(by_input.into());
        self
    }

    /// Whether [`HostConv::tap_products`] can be used.
    pub fn has_tap_products(&self) -> bool {
        self.weight_by_input.is_some()
    }

    /// Kernel side.
    pub fn k(&self) -> usize {
        self.k
    }

    pub fn c_in(&self) -> usize {
        self.c_in
    }

    pub fn c_out(&self) -> usize {
        self.c_out
    }

    pub fn bias(&self) -> &[f32] {
        &self.bias
    }

    /// Runs `f` with this thread's im2col scratch, at least `len` long.
    pub fn with_scratch<R>(len: usize, f: impl FnOnce(&mut [f32]) -> R) -> R {
        SCRATCH.with(|s| {
            let mut a = s.borrow_mut();
            if a.len() < len {
                a.resize(len, 0.0);
            }
            f(&mut a[..len])
        })
    }

    /// `dst += a · weight[taps]`, one thread: `a` is the
    /// `m x taps.len()·C_in` im2col matrix of the kernel taps `taps` (the
    /// others read only zero padding, whose products are all zero), `dst`
    /// the `m x C_out` output, each stored with its strides.
    pub fn accumulate_taps(&self, taps: std::ops::Range<usize>, product: Product<'_>) {
        self.gemm(&self.weight, taps, product);
    }

    /// [`accumulate_taps`](Self::accumulate_taps) over the kernel columns
    /// `cols` of a 2-D kernel, every kernel row: `a` is
    /// `m x cols.len()·k·C_in`, its columns ordered `(kx, ky, ci)`.
    pub fn accumulate_kernel_columns(&self, cols: std::ops::Range<usize>, product: Product<'_>) {
        let weight = self
            .weight_by_column
            .as_ref()
            .expect("kernel columns of a 2-D convolution");
        let k = self.k;
        self.gemm(weight, cols.start * k..cols.end * k, product);
    }

    /// `dst += a · weight[taps]`, `weight` one of this convolution's layouts.
    fn gemm(&self, weight: &[f32], taps: std::ops::Range<usize>, product: Product<'_>) {
        let n = self.c_out;
        assert!(
            taps.start < taps.end && taps.end * self.c_in * n <= weight.len(),
            "taps inside the kernel"
        );
        let weight = &weight[taps.start * self.c_in * n..taps.end * self.c_in * n];
        gemm_rows(weight, n, product);
    }

    /// Every kernel tap's product with every input position: `x`
    /// `[len, C_in]` position-major -> `[len, taps·C_out]`, row `n` holding
    /// `x[n] · W_tap` for each tap in turn (no bias). A 2-D convolution at
    /// any folding of `x` is then a sum of these rows
    /// ([`HostConv::forward_grid_from_taps`]): one GEMM shared by all the
    /// periods a block folds the same input at.
    pub fn tap_products(&self, x: &[f32]) -> Vec<f32> {
        let weight = self
            .weight_by_input
            .as_ref()
            .expect("HostConv::with_tap_products");
        let c_in = self.c_in;
        assert_eq!(x.len() % c_in, 0, "input width");
        let (len, n) = (x.len() / c_in, self.k * self.k * self.c_out);
        let mut y = vec![0.0f32; len * n];
        let row_major = |cols| Strides { row: cols, col: 1 };
        gemm_rows(
            weight,
            n,
            Product {
                m: len,
                dst: &mut y,
                dst_s: row_major(n),
                a: x,
                a_s: row_major(c_in),
            },
        );
        y
    }
}

/// The operands of `dst += a · weight`: `a` (`m` rows) and `dst`, each
/// stored with its strides.
pub struct Product<'a> {
    pub m: usize,
    pub dst: &'a mut [f32],
    pub dst_s: Strides,
    pub a: &'a [f32],
    pub a_s: Strides,
}

/// `dst += a · weight`: `weight` `kk x n` row-major (`kk = weight.len() / n`),
/// `a` `m x kk` and `dst` `m x n` with their strides, on this thread.
fn gemm_rows(weight: &[f32], n: usize, product: Product<'_>) {
    let Product {
        m,
        dst,
        dst_s,
        a,
        a_s,
    } = product;
    assert!(n > 0 && weight.len().is_multiple_of(n), "weight rows");
    let kk = weight.len() / n;
    if m == 0 || kk == 0 {
        return;
    }
    let last = |s: Strides, cols: usize| (m - 1) * s.row + (cols - 1) * s.col;
    assert!(last(dst_s, n) < dst.len(), "output inside its buffer");
    assert!(last(a_s, kk) < a.len(), "im2col inside its buffer");
    // SAFETY: the largest index each matrix is read or written at was
    // checked above against its slice; `weight` is `kk x n` row-major,
    // sliced so; `dst` is borrowed mutably, so no input overlaps it.
    unsafe {
        gemm::gemm(
            m,
            n,
            kk,
            dst.as_mut_ptr(),
            dst_s.col as isize,
            dst_s.row as isize,
            true,
            a.as_ptr(),
            a_s.col as isize,
            a_s.row as isize,
            weight.as_ptr(),
            1,
            n as isize,
            1.0f32,
            1.0f32,
            false,
            false,
            false,
            gemm::Parallelism::None,
        );
    }
}
