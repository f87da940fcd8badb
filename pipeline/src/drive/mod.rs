//! A drive in time: the transform tree (and, with the ingest work, the index of sweeps
//! and camera frames).

pub mod tf;

pub use tf::{TfError, TransformTree};
