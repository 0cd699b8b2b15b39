//! Training and evaluation (to be written).
