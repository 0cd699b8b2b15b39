//! From the streams to the forecast: the tick loop (`tick`), the networks
//! of the configuration (`models`), the choice of network by the streams
//! available (`choice`) and the inference on its own thread (`inference`).
//! The resampling onto the tick grid and the ring of the last N ticks are
//! the layer below (`crate::window`), which the sources, the model and the
//! lab build on too.

pub mod choice;
pub mod inference;
pub mod models;
pub mod tick;
