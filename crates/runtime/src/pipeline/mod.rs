//! From the streams to the forecast: the tick loop (`tick`) and the choice
//! of network by the streams available and the inference on its own thread
//! (`forecast`). The resampling onto the tick grid and the ring of the last
//! N ticks are the layer below (`crate::window`), which the sources, the
//! model and the lab build on too.

pub mod forecast;
pub mod tick;
