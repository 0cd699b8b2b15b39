//! A fused convolution run on the host as im2col + GEMM (inference): its
//! weights laid out once as the GEMM's right-hand side, one scratch
//! buffer per thread for the im2col matrix, and one safe entry to the
//! `gemm` crate (the kernels Flex itself uses). Two shapes of input use it:
//! the trajectory encoder's folded sequences (`grid_conv`) and the vision
//! encoder's single time slices (`slice_conv`).

use std::cell::RefCell;
use std::sync::Arc;

use super::inception::FusedConv;
use super::int8_gemm::{self, Int8Weights};

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
    /// The layouts above in int8 ([`HostConv::to_int8`]): when present,
    /// every product whose weight rows are whole int8 groups runs in
    /// integers (`int8_gemm`).
    int8: Option<Int8Layouts>,
}

/// [`HostConv`]'s weight layouts in int8.
#[derive(Debug, Clone)]
struct Int8Layouts {
    rows: Int8Weights,
    by_column: Option<Int8Weights>,
    by_input: Option<Int8Weights>,
}

/// Which of [`HostConv`]'s weight layouts a product reads.
#[derive(Debug, Clone, Copy)]
enum Layout {
    Rows,
    ByColumn,
    ByInput,
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
            int8: None,
        }
    }

    /// This convolution with its products in integers: every weight layout
    /// it holds also in int8, one scale per output column, and each im2col
    /// row quantised to 7 bits as it is multiplied (`int8_gemm`). Not
    /// lossless: what it changes in the forecasts is measured in the model
    /// card. A product over rows that are not whole int8 groups of four
    /// (three input channels a tap) stays f32. Call after
    /// [`HostConv::with_tap_products`].
    pub fn to_int8(mut self) -> HostConv {
        let n = self.c_out;
        let taps_n = self.k * self.k * n;
        self.int8 = Some(Int8Layouts {
            rows: Int8Weights::new(&self.weight, n),
            by_column: self
                .weight_by_column
                .as_ref()
                .map(|w| Int8Weights::new(w, n)),
            by_input: self
                .weight_by_input
                .as_ref()
                .map(|w| Int8Weights::new(w, taps_n)),
        });
        self
    }

    /// A layout's f32 weights and its int8 twin, if any.
    fn layout(&self, layout: Layout) -> (&[f32], Option<&Int8Weights>) {
        let int8 = self.int8.as_ref();
        match layout {
            Layout::Rows => (&self.weight, int8.map(|q| &q.rows)),
            Layout::ByColumn => (
                self.weight_by_column
                    .as_deref()
                    .expect("kernel columns of a 2-D convolution"),
                int8.and_then(|q| q.by_column.as_ref()),
            ),
            Layout::ByInput => (
                self.weight_by_input
                    .as_deref()
                    .expect("HostConv::with_tap_products"),
                int8.and_then(|q| q.by_input.as_ref()),
            ),
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
        self.gemm(Layout::Rows, taps, product, None, Write::Add);
    }

    /// [`accumulate_taps`](Self::accumulate_taps) over the kernel columns
    /// `cols` of a 2-D kernel, every kernel row: `a` is
    /// `m x cols.len()·k·C_in`, its columns ordered `(kx, ky, ci)`.
    pub fn accumulate_kernel_columns(&self, cols: std::ops::Range<usize>, product: Product<'_>) {
        let k = self.k;
        self.gemm(
            Layout::ByColumn,
            cols.start * k..cols.end * k,
            product,
            None,
            Write::Add,
        );
    }

    /// `dst = a · weight[taps]` (what `dst` held is not read, so a reused
    /// buffer needs no zeroing) with `a`'s columns read in place: column
    /// `q` of the im2col matrix is `a` from `columns[q]` on (rows
    /// `product.a_s.row` apart; `product.a_s.col` is not read), so a
    /// matrix whose columns are runs of one buffer is not copied.
    pub fn store_taps_gathered(
        &self,
        taps: std::ops::Range<usize>,
        product: Product<'_>,
        columns: &[usize],
    ) {
        assert_eq!(
            columns.len(),
            taps.len() * self.c_in,
            "one offset per im2col column"
        );
        self.gemm(Layout::Rows, taps, product, Some(columns), Write::Store);
    }

    /// `dst += a · weight[taps]` with one of this convolution's layouts
    /// (`C_out` columns, `C_in` rows a tap), in integers when the layout
    /// is held in int8 and the rows are whole groups.
    fn gemm(
        &self,
        layout: Layout,
        taps: std::ops::Range<usize>,
        product: Product<'_>,
        columns: Option<&[usize]>,
        write: Write,
    ) {
        let (weight, int8) = self.layout(layout);
        let n = self.c_out;
        assert!(
            taps.start < taps.end && taps.end * self.c_in * n <= weight.len(),
            "taps inside the kernel"
        );
        let rows = taps.start * self.c_in..taps.end * self.c_in;
        let weight = &weight[rows.start * n..rows.end * n];
        gemm_rows(weight, n, product, write, columns, int8.map(|q| (q, rows)));
    }

    /// Every kernel tap's product with every input position: `x`
    /// `[len, C_in]` position-major -> `[len, taps·C_out]`, row `n` holding
    /// `x[n] · W_tap` for each tap in turn (no bias). A 2-D convolution at
    /// any folding of `x` is then a sum of these rows
    /// ([`HostConv::forward_grid_from_taps`]): one GEMM shared by all the
    /// periods a block folds the same input at.
    pub fn tap_products(&self, x: &[f32]) -> Vec<f32> {
        let mut y = vec![0.0; x.len() / self.c_in * self.k * self.k * self.c_out];
        self.tap_products_of_rows(x, &mut y);
        y
    }

    /// [`tap_products`](Self::tap_products) into `y`, exactly
    /// `[len, taps·C_out]` long: every element is written (the GEMM stores
    /// its sums, it does not add them to what `y` held), so a kept buffer
    /// needs no zeroing. Each row of `y` depends on its row of `x` alone,
    /// and is the same bits whichever rows are computed with it.
    pub fn tap_products_of_rows(&self, x: &[f32], y: &mut [f32]) {
        let (weight, int8) = self.layout(Layout::ByInput);
        let c_in = self.c_in;
        assert_eq!(x.len() % c_in, 0, "input width");
        let (len, n) = (x.len() / c_in, self.k * self.k * self.c_out);
        assert_eq!(y.len(), len * n, "tap products size");
        let row_major = |cols| Strides { row: cols, col: 1 };
        gemm_rows(
            weight,
            n,
            Product {
                m: len,
                dst: y,
                dst_s: row_major(n),
                a: x,
                a_s: row_major(c_in),
            },
            Write::Store,
            None,
            int8.map(|q| (q, 0..c_in)),
        );
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

/// How [`gemm_rows`] writes its sums.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
enum Write {
    /// `dst += a · weight`.
    Add,
    /// `dst = a · weight` (what `dst` held is not read).
    Store,
}

/// `dst += a · weight` ([`Write::Add`]) or `dst = a · weight`
/// ([`Write::Store`]): `weight` `kk x n` row-major (`kk = weight.len() / n`),
/// `a` `m x kk` and `dst` `m x n` with their strides, on this thread.
///
/// A direct kernel for the small, fixed shapes of these layers (`n` up
/// to a few hundred, `kk` up to about a thousand, `m` a few dozen to a
/// few hundred): the weights are read in place (row-major with the
/// output channels contiguous is already the layout a register block
/// wants), `a` is read by broadcasting its elements, so nothing is
/// packed or copied per call. A general GEMM (the `gemm` crate, used
/// before) packed both operands and set up its thread-local buffers on
/// every call, which cost more than the multiply-adds at these shapes.
/// Each output is `dst + Σ_p a[p]·w[p]`, the sum in the order of `p`
/// with fused multiply-adds where the CPU has them: the same bits on
/// every x86-64 CPU with AVX2 and FMA (with or without AVX-512).
///
/// `int8`: the same weights in int8 and the rows of that layout `weight`
/// is; when the rows are whole int8 groups the product runs in integers
/// there (`int8_gemm`), after the same bounds checks.
fn gemm_rows(
    weight: &[f32],
    n: usize,
    product: Product<'_>,
    write: Write,
    columns: Option<&[usize]>,
    int8: Option<(&Int8Weights, std::ops::Range<usize>)>,
) {
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
    match columns {
        None => assert!(last(a_s, kk) < a.len(), "im2col inside its buffer"),
        Some(cols) => {
            assert_eq!(cols.len(), kk, "one offset per column");
            let far = cols.iter().max().copied().unwrap_or(0) + (m - 1) * a_s.row;
            assert!(far < a.len(), "gathered columns inside their buffer");
        }
    }
    if let Some((q, rows)) = int8.filter(|(q, rows)| q.covers(rows)) {
        assert_eq!(rows.len(), kk, "the int8 rows are the product's");
        int8_gemm::gemm(
            q,
            rows,
            m,
            a,
            a_s,
            columns,
            dst,
            dst_s,
            write == Write::Store,
        );
        return;
    }
    let ops = Operands {
        m,
        n,
        kk,
        weight: weight.as_ptr(),
        a: a.as_ptr(),
        a_s,
        a_cols: columns.map_or(std::ptr::null(), <[usize]>::as_ptr),
        dst: dst.as_mut_ptr(),
        dst_s,
        store: write == Write::Store,
    };
    #[cfg(target_arch = "x86_64")]
    {
        if std::arch::is_x86_feature_detected!("avx2") && std::arch::is_x86_feature_detected!("fma")
        {
            // SAFETY: the CPU has AVX2 and FMA (checked just above); every
            // index the kernel reads or writes is inside the slices (the
            // largest of each was checked above); `dst` is borrowed
            // mutably, so no input overlaps it.
            unsafe { kernel::gemm_avx2(&ops) };
            return;
        }
    }
    // SAFETY: as above.
    #[cfg(target_arch = "aarch64")]
    unsafe {
        kernel::gemm_neon(&ops)
    };
    // SAFETY: as above.
    #[cfg(not(target_arch = "aarch64"))]
    unsafe {
        kernel::gemm_portable(&ops)
    };
}

/// The raw operands of [`gemm_rows`], bounds already checked.
struct Operands {
    m: usize,
    n: usize,
    kk: usize,
    weight: *const f32,
    a: *const f32,
    a_s: Strides,
    /// Null, or `kk` offsets: column `p` of `a` starts at `a_cols[p]`
    /// (then `a_s.col` is not read).
    a_cols: *const usize,
    dst: *mut f32,
    dst_s: Strides,
    /// Store the sums (`Write::Store`) instead of adding them.
    store: bool,
}

mod kernel {
    use super::Operands;

    /// `acc[r][j] = Σ_p a[i0 + r, p] · w[p, j0 + j]`, `r < R`, `j < W`, then
    /// added to `dst`. `fma(a, b, c)` is `a·b + c`.
    ///
    /// # Safety
    /// `i0 + R <= m`, `j0 + W <= n`, the operands as [`Operands`] says.
    #[inline(always)]
    unsafe fn block<const R: usize, const W: usize>(
        o: &Operands,
        i0: usize,
        j0: usize,
        fma: impl Fn(f32, f32, f32) -> f32,
    ) {
        let mut acc = [[0.0f32; W]; R];
        for p in 0..o.kk {
            // SAFETY: `p < kk`, `j0 + W <= n`: inside the weight matrix.
            let w: [f32; W] = unsafe { std::array::from_fn(|j| *o.weight.add(p * o.n + j0 + j)) };
            for (r, row) in acc.iter_mut().enumerate() {
                // SAFETY: row `i0 + r < m`, column `p < kk` of `a`.
                let x = unsafe {
                    let col = if o.a_cols.is_null() {
                        p * o.a_s.col
                    } else {
                        *o.a_cols.add(p)
                    };
                    *o.a.add((i0 + r) * o.a_s.row + col)
                };
                for (s, &wj) in row.iter_mut().zip(&w) {
                    *s = fma(x, wj, *s);
                }
            }
        }
        for (r, row) in acc.iter().enumerate() {
            for (j, &s) in row.iter().enumerate() {
                // SAFETY: element `(i0 + r, j0 + j)` of `dst`.
                unsafe {
                    let d = o.dst.add((i0 + r) * o.dst_s.row + (j0 + j) * o.dst_s.col);
                    *d = if o.store { s } else { *d + s };
                }
            }
        }
    }

    /// Every block of rows for columns `j0..j0 + W`.
    #[inline(always)]
    unsafe fn columns<const W: usize>(
        o: &Operands,
        j0: usize,
        fma: impl Fn(f32, f32, f32) -> f32 + Copy,
    ) {
        // SAFETY (all calls): `i0 + R <= m`, `j0 + W <= n`.
        unsafe { row_blocks!(o.m, |R, i0| block::<R, W>(o, i0, j0, fma)) }
    }

    /// All of `dst`: columns in blocks of 16 (two AVX2 registers), then 8,
    /// then one at a time.
    #[cfg(not(target_arch = "aarch64"))]
    #[inline(always)]
    unsafe fn gemm(o: &Operands, fma: impl Fn(f32, f32, f32) -> f32 + Copy) {
        // SAFETY (all calls): `j0 + width <= n`.
        unsafe {
            column_blocks!(
                o.n,
                |j0| columns::<16>(o, j0, fma),
                columns::<8>(o, j0, fma),
                last_columns(o, j0, fma)
            )
        }
    }

    /// Columns `j0..n` (fewer than 8, after the register blocks) one at a
    /// time.
    ///
    /// # Safety
    /// `j0 <= n`, the operands as [`Operands`] says.
    #[inline(always)]
    unsafe fn last_columns(o: &Operands, j0: usize, fma: impl Fn(f32, f32, f32) -> f32 + Copy) {
        for j in j0..o.n {
            // SAFETY: `j + 1 <= n`.
            unsafe { columns::<1>(o, j, fma) }
        }
    }

    /// All of `dst` with AVX2 registers: columns in blocks of 16 (two
    /// registers) and 8, rows in blocks of six (twelve accumulators),
    /// the last columns (fewer than 8) one at a time.
    ///
    /// # Safety
    /// The CPU has AVX2 and FMA; the operands as [`Operands`] says.
    #[cfg(target_arch = "x86_64")]
    #[target_feature(enable = "avx2,fma")]
    pub(super) unsafe fn gemm_avx2(o: &Operands) {
        // SAFETY (all calls): `j0 + width <= n`, `i0 + rows <= m`.
        unsafe {
            column_blocks!(
                o.n,
                |j0| columns_avx2::<2>(o, j0),
                columns_avx2::<1>(o, j0),
                last_columns(o, j0, f32::mul_add)
            )
        }
    }

    /// Every block of rows for columns `j0..j0 + 8·V`.
    #[cfg(target_arch = "x86_64")]
    #[target_feature(enable = "avx2,fma")]
    #[inline]
    unsafe fn columns_avx2<const V: usize>(o: &Operands, j0: usize) {
        // SAFETY (all calls): `i0 + rows <= m`, `j0 + 8·V <= n`.
        unsafe {
            if o.a_cols.is_null() {
                rows_avx2::<V, false>(o, j0);
            } else {
                rows_avx2::<V, true>(o, j0);
            }
        }
    }

    /// [`columns_avx2`] with `a`'s columns strided (`G` false) or
    /// gathered (`G` true).
    #[cfg(target_arch = "x86_64")]
    #[target_feature(enable = "avx2,fma")]
    #[inline]
    unsafe fn rows_avx2<const V: usize, const G: bool>(o: &Operands, j0: usize) {
        // SAFETY (all calls): `i0 + R <= m`, `j0 + 8·V <= n`.
        unsafe { row_blocks!(o.m, |R, i0| block_avx2::<R, V, G>(o, i0, j0)) }
    }

    /// [`block`] in AVX2 registers: `R x 8·V` sums, each `a` element
    /// broadcast once per `p`, each weight row loaded once per `p`.
    ///
    /// # Safety
    /// The CPU has AVX2 and FMA; `i0 + R <= m`, `j0 + 8·V <= n`.
    #[cfg(target_arch = "x86_64")]
    #[target_feature(enable = "avx2,fma")]
    #[inline]
    unsafe fn block_avx2<const R: usize, const V: usize, const G: bool>(
        o: &Operands,
        i0: usize,
        j0: usize,
    ) {
        use std::arch::x86_64::{
            __m256, _mm256_add_ps, _mm256_broadcast_ss, _mm256_fmadd_ps, _mm256_loadu_ps,
            _mm256_setzero_ps, _mm256_storeu_ps,
        };
        let mut acc: [[__m256; V]; R] = [[_mm256_setzero_ps(); V]; R];
        // SAFETY: every pointer below stays inside its matrix: weight row
        // `p < kk` columns `j0..j0 + 8·V`, `a` rows `i0..i0 + R` column `p`,
        // `dst` rows `i0..i0 + R` columns `j0..j0 + 8·V`.
        unsafe {
            let mut w = o.weight.add(j0);
            let mut a = o.a.add(i0 * o.a_s.row);
            for p in 0..o.kk {
                let wv: [__m256; V] = std::array::from_fn(|v| _mm256_loadu_ps(w.add(8 * v)));
                if G {
                    a = o.a.add(i0 * o.a_s.row + *o.a_cols.add(p));
                }
                for (r, row) in acc.iter_mut().enumerate() {
                    let x = _mm256_broadcast_ss(&*a.add(r * o.a_s.row));
                    for (s, &wj) in row.iter_mut().zip(&wv) {
                        *s = _mm256_fmadd_ps(x, wj, *s);
                    }
                }
                w = w.add(o.n);
                if !G {
                    a = a.add(o.a_s.col);
                }
            }
            for (r, row) in acc.iter().enumerate() {
                let d = o.dst.add((i0 + r) * o.dst_s.row + j0 * o.dst_s.col);
                for (v, &s) in row.iter().enumerate() {
                    if o.dst_s.col == 1 {
                        let at = d.add(8 * v);
                        let sum = if o.store {
                            s
                        } else {
                            _mm256_add_ps(_mm256_loadu_ps(at), s)
                        };
                        _mm256_storeu_ps(at, sum);
                    } else {
                        let mut lanes = [0.0f32; 8];
                        _mm256_storeu_ps(lanes.as_mut_ptr(), s);
                        for (j, &l) in lanes.iter().enumerate() {
                            let at = d.add((8 * v + j) * o.dst_s.col);
                            *at = if o.store { l } else { *at + l };
                        }
                    }
                }
            }
        }
    }

    /// All of `dst` with NEON registers (aarch64): columns in blocks of 16
    /// (four registers) and 8, rows in blocks of six (twenty-four
    /// accumulators), the last columns (fewer than 8) one at a time. Each
    /// output the same fused multiply-adds in the same order as the AVX2
    /// path: the same bits.
    ///
    /// # Safety
    /// The operands as [`Operands`] says.
    #[cfg(target_arch = "aarch64")]
    pub(super) unsafe fn gemm_neon(o: &Operands) {
        // SAFETY (all calls): `j0 + width <= n`.
        unsafe {
            column_blocks!(
                o.n,
                |j0| columns_neon::<4>(o, j0),
                columns_neon::<2>(o, j0),
                last_columns(o, j0, f32::mul_add)
            )
        }
    }

    /// Every block of rows for columns `j0..j0 + 4·V`.
    #[cfg(target_arch = "aarch64")]
    #[inline]
    unsafe fn columns_neon<const V: usize>(o: &Operands, j0: usize) {
        // SAFETY (all calls): `i0 + rows <= m`, `j0 + 4·V <= n`.
        unsafe {
            if o.a_cols.is_null() {
                rows_neon::<V, false>(o, j0);
            } else {
                rows_neon::<V, true>(o, j0);
            }
        }
    }

    /// [`columns_neon`] with `a`'s columns strided (`G` false) or
    /// gathered (`G` true).
    #[cfg(target_arch = "aarch64")]
    #[inline]
    unsafe fn rows_neon<const V: usize, const G: bool>(o: &Operands, j0: usize) {
        // SAFETY (all calls): `i0 + R <= m`, `j0 + 4·V <= n`.
        unsafe { row_blocks!(o.m, |R, i0| block_neon::<R, V, G>(o, i0, j0)) }
    }

    /// [`block`] in NEON registers: `R x 4·V` sums ([`sums_neon`]), then
    /// stored or added into `dst`.
    ///
    /// # Safety
    /// `i0 + R <= m`, `j0 + 4·V <= n`, the operands as [`Operands`] says.
    #[cfg(target_arch = "aarch64")]
    #[inline]
    unsafe fn block_neon<const R: usize, const V: usize, const G: bool>(
        o: &Operands,
        i0: usize,
        j0: usize,
    ) {
        use std::arch::aarch64::{vaddq_f32, vld1q_f32, vst1q_f32};
        // SAFETY: NEON is part of aarch64; `dst` rows `i0..i0 + R`, columns
        // `j0..j0 + 4·V` are inside it.
        unsafe {
            let acc = sums_neon::<R, V, G>(o, i0, j0);
            if o.dst_s.col != 1 {
                store_strided(o, i0, j0, &acc);
                return;
            }
            for (r, row) in acc.iter().enumerate() {
                let d = o.dst.add((i0 + r) * o.dst_s.row + j0);
                for (v, &s) in row.iter().enumerate() {
                    let at = d.add(4 * v);
                    let sum = if o.store {
                        s
                    } else {
                        vaddq_f32(vld1q_f32(at), s)
                    };
                    vst1q_f32(at, sum);
                }
            }
        }
    }

    /// `R x 4·V` sums `Σ_p a[i0 + r, p] · w[p, j0..]`, each `a` element
    /// multiplied by lane, each weight row loaded once per `p`: the fused
    /// multiply-adds of [`block`] in the same order. A function of its own,
    /// not inlined: where the sums were used in the same function as the
    /// strided store, LLVM kept them in memory and stored all of them at
    /// every `p` (twelve 32-byte stores for twenty-four multiply-adds).
    ///
    /// # Safety
    /// `i0 + R <= m`, `j0 + 4·V <= n`, the operands as [`Operands`] says.
    #[cfg(target_arch = "aarch64")]
    #[inline(never)]
    unsafe fn sums_neon<const R: usize, const V: usize, const G: bool>(
        o: &Operands,
        i0: usize,
        j0: usize,
    ) -> [[std::arch::aarch64::float32x4_t; V]; R] {
        use std::arch::aarch64::{float32x4_t, vdupq_n_f32, vfmaq_n_f32, vld1q_f32};
        // SAFETY: NEON is part of aarch64; weight row `p < kk` columns
        // `j0..j0 + 4·V` and `a` rows `i0..i0 + R` column `p` are inside
        // their matrices.
        unsafe {
            let mut acc: [[float32x4_t; V]; R] = [[vdupq_n_f32(0.0); V]; R];
            let mut w = o.weight.add(j0);
            let mut a = o.a.add(i0 * o.a_s.row);
            for p in 0..o.kk {
                let wv: [float32x4_t; V] = std::array::from_fn(|v| vld1q_f32(w.add(4 * v)));
                if G {
                    a = o.a.add(i0 * o.a_s.row + *o.a_cols.add(p));
                }
                for (r, row) in acc.iter_mut().enumerate() {
                    let x = *a.add(r * o.a_s.row);
                    for (s, &wj) in row.iter_mut().zip(&wv) {
                        *s = vfmaq_n_f32(*s, wj, x);
                    }
                }
                w = w.add(o.n);
                if !G {
                    a = a.add(o.a_s.col);
                }
            }
            acc
        }
    }

    /// [`block_neon`]'s sums into a `dst` whose columns are strided.
    ///
    /// # Safety
    /// `i0 + R <= m`, `j0 + 4·V <= n`, the operands as [`Operands`] says.
    #[cfg(target_arch = "aarch64")]
    unsafe fn store_strided<const R: usize, const V: usize>(
        o: &Operands,
        i0: usize,
        j0: usize,
        acc: &[[std::arch::aarch64::float32x4_t; V]; R],
    ) {
        for (r, row) in acc.iter().enumerate() {
            for (v, &s) in row.iter().enumerate() {
                let mut lanes = [0.0f32; 4];
                // SAFETY: NEON is part of aarch64; element
                // `(i0 + r, j0 + 4·v + j)` is inside `dst`.
                unsafe {
                    std::arch::aarch64::vst1q_f32(lanes.as_mut_ptr(), s);
                    for (j, &l) in lanes.iter().enumerate() {
                        let at = o
                            .dst
                            .add((i0 + r) * o.dst_s.row + (j0 + 4 * v + j) * o.dst_s.col);
                        *at = if o.store { l } else { *at + l };
                    }
                }
            }
        }
    }

    /// Elsewhere than x86-64 with AVX2 and aarch64: a product and a sum.
    ///
    /// # Safety
    /// The operands as [`Operands`] says.
    #[cfg(not(target_arch = "aarch64"))]
    pub(super) unsafe fn gemm_portable(o: &Operands) {
        // SAFETY: passed on.
        unsafe { gemm(o, |a: f32, b: f32, c: f32| a * b + c) }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    /// Values with every bit of the mantissa in use, so that another order
    /// of the sums, or a product rounded before its sum, shows.
    fn values(len: usize, seed: u32) -> Vec<f32> {
        let mut state = seed.wrapping_mul(0x9e37_79b9) | 1;
        (0..len)
            .map(|_| {
                state ^= state << 13;
                state ^= state >> 17;
                state ^= state << 5;
                (state >> 8) as f32 / (1u32 << 23) as f32 - 1.0
            })
            .collect()
    }

    /// Whether this build's kernel sums with fused multiply-adds (AVX2 +
    /// FMA on x86-64, NEON on aarch64); elsewhere a product and a sum.
    fn fused() -> bool {
        #[cfg(target_arch = "x86_64")]
        {
            std::arch::is_x86_feature_detected!("avx2")
                && std::arch::is_x86_feature_detected!("fma")
        }
        #[cfg(not(target_arch = "x86_64"))]
        {
            cfg!(target_arch = "aarch64")
        }
    }

    /// Every register block shape (rows 1-13: whole blocks of six and
    /// every remainder; columns 1-37: blocks of 16, of 8 and single
    /// columns), `a` strided and gathered, `dst` contiguous and strided,
    /// stored and added: each output is `dst + Σ_p a[i, p] · w[p, j]`
    /// summed in the order of `p` from zero, with fused multiply-adds
    /// where the kernel has them, to the bit.
    #[test]
    fn every_block_shape_sums_in_the_order_of_p() {
        let fused = fused();
        for m in 1..=13 {
            for n in [1, 3, 8, 11, 16, 24, 37] {
                for kk in [1, 7, 33] {
                    let weight = values(kk * n, (m * 1000 + n * 10 + kk) as u32);
                    // `a` stored column-major with a gap, so that the
                    // strided and the gathered reads both leave a row.
                    let a = values((kk + 1) * (m + 2), (m + n + kk) as u32);
                    let a_s = Strides { row: 1, col: m + 2 };
                    let columns: Vec<usize> = (0..kk).map(|p| p * (m + 2)).collect();
                    for gathered in [false, true] {
                        for transposed in [false, true] {
                            for write in [Write::Store, Write::Add] {
                                let dst_s = if transposed {
                                    Strides { row: 1, col: m }
                                } else {
                                    Strides { row: n, col: 1 }
                                };
                                let start = values(m * n, 7);
                                let mut dst = start.clone();
                                gemm_rows(
                                    &weight,
                                    n,
                                    Product {
                                        m,
                                        dst: &mut dst,
                                        dst_s,
                                        a: &a,
                                        a_s,
                                    },
                                    write,
                                    gathered.then_some(&columns[..]),
                                    None,
                                );
                                for i in 0..m {
                                    for j in 0..n {
                                        let mut s = 0.0f32;
                                        for p in 0..kk {
                                            let x = a[i * a_s.row + p * a_s.col];
                                            let w = weight[p * n + j];
                                            s = if fused { x.mul_add(w, s) } else { x * w + s };
                                        }
                                        let at = i * dst_s.row + j * dst_s.col;
                                        let want = match write {
                                            Write::Store => s,
                                            Write::Add => start[at] + s,
                                        };
                                        assert_eq!(
                                            dst[at].to_bits(),
                                            want.to_bits(),
                                            "m {m} n {n} kk {kk} gathered {gathered} \
                                             transposed {transposed} {write:?} ({i}, {j}): \
                                             {} against {want}",
                                            dst[at]
                                        );
                                    }
                                }
                            }
                        }
                    }
                }
            }
        }
    }
}
