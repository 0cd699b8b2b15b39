//! The EMP network (to be written).
