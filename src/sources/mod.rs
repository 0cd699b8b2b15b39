//! Input streams, each behind one small interface.

pub mod dynamixel;
