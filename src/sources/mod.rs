//! Input streams, each behind one small interface (to be written).

pub mod dynamixel;
