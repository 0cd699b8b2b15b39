//! fall-guard: forecasts falls of a walking Poppy Humanoid before they happen.
//!
//! Data flows one way (`docs/architecture.md`): sources -> streams (the
//! feeds, each with its input boundary) -> pipeline (resampling onto the
//! tick grid, the window ring, the model choice and the inference) ->
//! outputs (ROS 2, safety latch, diagnostics, recorder). The daemon wires
//! them per command; training (`train`) builds its windows with the same
//! `pipeline::window` code the daemon uses. Layers import only downwards
//! (`scripts/check-layers.py`).

pub mod clock;
pub mod config;
pub mod daemon;
pub mod frame;
pub mod model;
pub mod msgs;
pub mod outputs;
pub mod pipeline;
pub mod recording;
pub mod robot;
pub mod ros;
pub mod shutdown;
pub mod sources;
pub mod streams;
pub mod train;
