//! fall-guard's lab: everything that makes and judges the networks the
//! robot runs, on a workstation, never on the robot (the robot's binary
//! does not depend on this crate). On top of the runtime
//! (`fall_guard_runtime`): its window builder, network and model file.
//!
//! - the data plane: data sets of recordings (`dataset`) and the i.i.d.
//!   window sampler (`sampler`);
//! - training: the loop (`fit`), the optimizer (`adam`), checkpoints of a
//!   run (`checkpoint`), the training device (`device`), the logistic
//!   baseline (`logreg`);
//! - judging: metrics, evaluation (`eval`), plots, `calibrate` (Platt or
//!   beta calibration per horizon, shortest first, on held-out windows),
//!   the latch's `warning` figures (lead time, false alarms, thresholds),
//!   the training benchmark (`bench`);
//! - `commands`: the `train`, `eval` and `half` commands' options and run
//!   functions (the binary, `src/main.rs` and `src/cli.rs`, parses the
//!   command line into them and prints what they return);
//! - `error`: the commands' error and the training error.

pub mod adam;
pub mod bench;
pub mod calibrate;
pub mod checkpoint;
pub mod commands;
pub mod dataset;
pub mod device;
pub mod error;
pub mod eval;
pub mod finetune;
pub mod fit;
pub mod logreg;
pub mod metrics;
pub mod plots;
pub mod ranges;
pub mod sampler;
pub mod warning;

pub use device::TrainDevice;
pub use error::TrainError;
pub use fit::{fit, EncoderRates, EpochSource, FitOptions, LabeledWindow, WindowSet, WindowTruth};

#[cfg(test)]
mod tests;
