//! From the streams to the forecast: the resampling of every stream onto
//! the tick grid and the ring of the last N ticks (`window`, the one place
//! the network's arrays are cut), the tick loop (`tick`), and the choice of
//! network by the streams available and the inference on its own thread
//! (`forecast`).

pub mod forecast;
pub mod tick;
pub mod window;
