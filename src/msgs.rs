//! (to be written: see docs/contracts.md)
