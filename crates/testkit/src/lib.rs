//! Test doubles for fall-guard, kept out of the shipped crates: the tests
//! and benches of the robot binary, the runtime and the lab use them (a
//! dev-dependency), nothing else does.
//!
//! - [`emulator`]: a Dynamixel bus behind a USB2AX on a pseudo-terminal,
//!   with faults on demand, for the servo reader and the daemon;
//! - [`recordings`]: synthetic MCAP recordings and data sets, in the
//!   recording format the simulator writes, with learnable falls.
//!
//! The synthetic training windows are the lab's own test support
//! (`crates/lab/tests/support/windows.rs`): the kit depends on the runtime
//! only.

pub mod emulator;
pub mod recordings;
