//! Test doubles for fall-guard, kept out of the shipped crate: fall-guard's
//! tests and benches use them (a dev-dependency), nothing else does.
//!
//! - [`emulator`]: a Dynamixel bus behind a USB2AX on a pseudo-terminal,
//!   with faults on demand, for the servo reader and the daemon;
//! - [`recordings`]: synthetic MCAP recordings and data sets, in the
//!   recording format the simulator writes, with learnable falls;
//! - [`windows`]: synthetic labelled windows with learnable falls, for the
//!   training loop.

pub mod emulator;
pub mod recordings;
pub mod windows;
