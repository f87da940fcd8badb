//! Tests of the per-point loops: the plain loop keeps, converts and rejects what the
//! general loop does, and both find the ring index of a FLOAT32 as the round trip
//! through `f64` does.

mod plain;
mod ring;
