//! The EMP network (`docs/network.md`) in burn: encoders, classifier, the
//! model file, fused inference and the per-tick streaming forecaster.
//!
//! Training builds an [`Emp`] on an autodiff device; the daemon loads a
//! [`LoadedModel`] from one file and drives a [`StreamingForecaster`] tick by tick.

// The loops the register kernels (`host_conv`, `int8_gemm`) share. Macros,
// not functions taking the block: each block is then called from the
// kernel's own `#[target_feature]` function, where it is inlined.

/// `$block` for every register block of `$m` rows: blocks of six from row
/// 0, then one block of the 1-5 rows left. `$block` sees the block's row
/// count as the `const` `$r` (a const generic argument) and its first row
/// as `$i0`.
macro_rules! row_blocks {
    // `$block` with `$r` the `const` `$rows`.
    (@rows $r:ident = $rows:literal, $block:expr) => {{
        const $r: usize = $rows;
        $block
    }};
    ($m:expr, |$r:ident, $i0:ident| $block:expr) => {{
        let m: usize = $m;
        let mut $i0: usize = 0;
        while $i0 + 6 <= m {
            row_blocks!(@rows $r = 6, $block);
            $i0 += 6;
        }
        match m - $i0 {
            0 => {}
            1 => row_blocks!(@rows $r = 1, $block),
            2 => row_blocks!(@rows $r = 2, $block),
            3 => row_blocks!(@rows $r = 3, $block),
            4 => row_blocks!(@rows $r = 4, $block),
            _ => row_blocks!(@rows $r = 5, $block),
        }
    }};
}

/// `$n` columns from 0: `$sixteen` for each block of 16, `$eight` for one
/// block of 8 if 8 are left, then `$rest` once if any are left (fewer than
/// 8), each with `$j0` its first column.
macro_rules! column_blocks {
    ($n:expr, |$j0:ident| $sixteen:expr, $eight:expr, $rest:expr) => {{
        let n: usize = $n;
        let mut $j0: usize = 0;
        while $j0 + 16 <= n {
            $sixteen;
            $j0 += 16;
        }
        if $j0 + 8 <= n {
            $eight;
            $j0 += 8;
        }
        if $j0 < n {
            $rest;
        }
    }};
}

pub mod bench;
pub mod config;
pub mod emp;
pub mod file;
pub mod grid_conv;
pub mod host_conv;
pub mod host_linear;
pub mod inception;
pub mod int8_gemm;
pub mod motion;
pub mod plan;
pub mod ranges;
pub mod slice_conv;
pub mod spectral;
pub mod streaming;
pub mod tick_input;
pub mod vision;

pub use config::{Ablation, ModelConfig, TrajectoryInput};
pub use emp::{Emp, EmpInference, EmpInput};
pub use file::{
    save_model, save_model_as, Calibration, Convolutions, EpochRecord, LoadedModel, ModelError,
    ModelMeta, ProjectionWeights, WeightPrecision,
};
pub use streaming::StreamingForecaster;

use burn::prelude::Device;

/// The CPU device inference and training run on: Flex by default, NdArray
/// with `--no-default-features --features ndarray`.
pub fn cpu_device() -> Device {
    #[cfg(feature = "flex")]
    {
        Device::flex()
    }
    // Deprecated upstream; kept selectable as the design asks (12x slower
    // per tick than Flex here, see the model card).
    #[cfg(all(not(feature = "flex"), feature = "ndarray"))]
    #[allow(deprecated)]
    {
        Device::ndarray()
    }
    #[cfg(not(any(feature = "flex", feature = "ndarray")))]
    {
        Device::default()
    }
}

#[cfg(test)]
mod tests;
