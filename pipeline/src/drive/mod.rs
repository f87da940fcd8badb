//! A drive in time: channel discovery, the index of every LiDAR sweep and camera frame
//! over one or more files, and the transform tree.
//!
//! `inputs` finds the files of each drive, `index` builds a drive's index (with `heads`
//! reading just the stamp of a sensor message and `streams` turning the indexed topics
//! into streams), `skips` reports what was skipped, `dataset` holds the dataset and
//! drive types and reads one sensor message, and `labels` reads the per-point semantic
//! labels of a sweep (a field of the LiDAR cloud or a `<drive>.labels.mcap` sidecar).

pub mod dataset;
pub mod discover;
mod heads;
mod index;
pub mod inputs;
pub mod labels;
pub mod skips;
mod streams;
pub mod tf;

pub use dataset::{
    CameraStream, Dataset, Drive, FrameRef, IngestError, LabelCloudStream, LidarStream, ReadError,
};
pub use discover::{IngestConfig, Role};
pub use labels::{DriveLabels, LabelConfig, LabelError, LabelForm, LabelledSweep};
pub use skips::SkipReport;
pub use tf::{TfError, TransformTree};
