//! Training and evaluation: data sets of recordings and the i.i.d. window
//! sampler (data plane: `dataset`, `sampler`), and the network side: the
//! training loop (`fit`), metrics, evaluation, plots, the logistic baseline,
//! the optimizer (`adam`), checkpoints of a training run (`checkpoint`), the
//! `train`/`eval` commands (`cli`), `calibrate` (Platt scaling, shortest horizon first, on
//! held-out windows), `bench`, and the safety figures of
//! `warnings` (lead time, false alarms, thresholds).

pub mod adam;
pub mod bench;
pub mod calibrate;
pub mod checkpoint;
pub mod cli;
pub mod dataset;
pub mod device;
pub mod error;
pub mod eval;
pub mod fit;
pub mod logreg;
pub mod metrics;
pub mod plots;
pub mod sampler;
pub mod warning;

pub use device::TrainDevice;
pub use fit::{
    fit, EncoderRates, EpochSource, FitOptions, LabeledWindow, TrainError, WindowSet, WindowTruth,
};

#[cfg(test)]
mod tests;
