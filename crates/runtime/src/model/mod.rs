//! The EMP network (`docs/network.md`) in burn: encoders, classifier, the
//! model file, fused inference and the per-tick streaming forecaster.
//!
//! Training builds an [`Emp`] on an autodiff device; the daemon loads a
//! [`LoadedModel`] from one file and drives a [`StreamingForecaster`] tick by tick.

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
