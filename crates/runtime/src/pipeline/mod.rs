//! From the streams to the forecast: the tick loop (`tick`), the networks
//! of the configuration (`models`), the choice of network by the streams
//! available (`choice`), the inference on its own thread (`inference`) and
//! the out-of-range guard on its input (`guard`), and what happens when
//! inference runs late (`overload`).
//! The resampling onto the tick grid and the ring of the last N ticks are
//! the layer below (`crate::window`), which the sources, the model and the
//! lab build on too.

pub mod choice;
pub mod guard;
pub mod inference;
pub mod models;
pub mod overload;
pub mod tick;
