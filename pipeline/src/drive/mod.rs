//! A drive in time: channel discovery, the index of every LiDAR sweep and camera frame
//! over one or more files, and the transform tree.
//!
//! `files` finds the files of each drive, `groups` names groups of drives with their
//! repeats (`[[dataset]]`), `dataset` opens a dataset of drives, `index`
//! holds a [`Drive`] and joins the indexes of its files (made by `file_index`, with
//! `heads` reading just the stamp of a sensor message, and kept between runs by
//! `index_cache`; `streams` turns the indexed topics into the drive's streams),
//! `read` reads one sensor message of a drive, `rig` tells drives' sensor sets apart (a
//! fleet's rigs), `skips` reports what was skipped, `error`
//! says why a dataset cannot be trained on, and `labels` reads the per-point semantic
//! labels of a sweep (a field of the LiDAR cloud or a `<drive>.labels.mcap` sidecar).

pub mod dataset;
pub mod discover;
mod error;
mod file_index;
pub mod files;
pub mod groups;
mod heads;
mod index;
pub mod index_cache;
pub mod labels;
mod read;
pub mod rig;
pub mod skips;
mod streams;
pub mod tf;

pub use dataset::{Dataset, IndexProgress};
pub use discover::{IngestConfig, Role};
pub use error::IngestError;
pub use groups::{DatasetGroup, DriveGroup};
pub use index::{Drive, IndexedBy};
pub use index_cache::IndexCache;
pub use labels::{DriveLabels, LabelConfig, LabelError, LabelForm, LabelledSweep};
pub use read::{FrameAt, ImageReadError, ReadError};
pub use rig::{LidarFacts, Rig, RigShare};
pub use skips::SkipReport;
pub use streams::{
    CameraStream, ChannelSummary, FrameRef, LabelCloudStream, LidarStream, SlicStream, nearest,
};
pub use tf::{TfError, TransformTree};
