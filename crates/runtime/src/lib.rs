//! fall-guard's runtime: what runs on the robot, from the clock to the
//! daemon. It forecasts falls of a walking Poppy Humanoid before they
//! happen.
//!
//! Data flows one way (`docs/architecture.md`): sources -> streams (the
//! feeds, each with its input boundary) -> window (resampling onto the tick
//! grid, the ring of the last N ticks) -> pipeline (the tick loop, the model
//! choice and the inference) -> outputs (ROS 2, safety latch, diagnostics,
//! recorder). The daemon wires them per command. Training is another crate
//! (`fall-guard-lab`), built on this one: it cuts its windows with the same
//! `window` code the daemon uses, and this crate never depends on it.
//! Modules import only downwards (`scripts/checks/check-layers.py`).

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
pub mod window;
