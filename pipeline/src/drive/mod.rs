//! A drive in time: channel discovery, the index of every LiDAR sweep and camera frame
//! over one or more files, and the transform tree.

pub mod dataset;
pub mod discover;
pub mod tf;

pub use dataset::{CameraStream, Dataset, Drive, FrameRef, IngestError, LidarStream, SkipReport};
pub use discover::{IngestConfig, Role};
pub use tf::{TfError, TransformTree};
