//! Training and evaluation: data sets of recordings, the i.i.d. window
//! sampler, and (network side) the training loop, metrics and plots.

pub mod dataset;
pub mod sampler;
