//! Training and evaluation of the EMP network.
//!
//! Windows come from the data plane (`dataset`, `sampler`, owned by the data
//! engineer); `fit` trains, `metrics` and `eval` score, `bench` measures speed.

pub mod bench;
pub mod eval;
pub mod fit;
pub mod logreg;
pub mod metrics;
pub mod plots;

pub use fit::{fit, EncoderRates, EpochSource, FitOptions, LabeledWindow, TrainError};

#[cfg(test)]
mod tests;
