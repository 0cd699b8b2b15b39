//! fall-guard: forecasts falls of a walking Poppy Humanoid before they happen.
//!
//! Data flows one way (see `docs/contracts.md`, "The flow"): sources ->
//! tick grid (`window`) -> inference (`model`, `forecast`) -> outputs
//! (ROS 2, safety latch, diagnostics, recorder). Training (`train`) builds
//! its windows with the same `window` code the daemon uses.

pub mod config;
pub mod daemon_bench;
pub mod forecast;
pub mod frame;
pub mod model;
pub mod msgs;
pub mod outputs;
pub mod recording;
pub mod robot;
pub mod ros;
pub mod service;
pub mod shutdown;
pub mod sources;
pub mod tick;
pub mod train;
pub mod window;
