//! Per-point semantic labels of a drive's LiDAR sweeps — what a linear probe or a
//! segmentation head is trained and scored on (nuScenes-lidarseg, SemanticKITTI converted
//! to MCAP).
//!
//! # Where labels come from ([`LabelForm`])
//!
//! * **A field of the LiDAR cloud** (`foxglove.PointCloud` or `sensor_msgs/msg/PointCloud2`):
//!   `[labels] field`, else the first of `label`, `class`, `semantic`, `semantic_label`,
//!   `lidarseg` (regardless of case) that the first readable sweep has. Any integer type,
//!   or a float holding integers ([`crate::decode::points::LabelFieldSpec`]).
//! * **A sidecar** `<drive>.labels.mcap` next to `<drive>.mcap` (grouped with the drive
//!   like the other sidecars, [`super::files`]): a point cloud per sweep with the sweep's
//!   stamp, its point order and count, and the label field (the configured or a default
//!   name, else its only field). The sidecar's point clouds are never taken for the LiDAR.
//!   Which of them labels the LiDAR: the only one; else the one whose channel metadata
//!   [`LABELS_LIDAR_TOPIC_KEY`](super::discover::LABELS_LIDAR_TOPIC_KEY) names the LiDAR
//!   topic; else the one whose topic starts with the LiDAR topic
//!   (`/lidar_top/points_raw/labels` for `/lidar_top/points_raw`); else it is an error
//!   ([`LabelError::AmbiguousSidecar`]). A sweep is matched with the label cloud of the
//!   same stamp; none, or one with another point count, is an error naming the sidecar,
//!   its topic and the stamp.
//!
//! The field wins when a drive has both.
//!
//! # What a sweep's labels are aligned with
//!
//! [`DriveLabels::read`] gives the labels of sweep `i` of
//! [`Drive::lidar`](super::Drive::lidar) — the index the sample builder and
//! [`crate::sample::KeyframeRef::sweep`] use — aligned point for point with what
//! [`Drive::read_sweep`](super::Drive::read_sweep) decodes for that sweep: the points left
//! after the pipeline drops those with a non-finite coordinate (the only points it drops;
//! de-skew moves points without reordering them). A sidecar's labels, which cover every
//! point of the message, are carried through the same dropping
//! ([`crate::decode::points::CloudOptions::kept_indices`]).
//!
//! # Raw ids and training classes ([`LabelConfig`], `[labels]`)
//!
//! A stored value, masked by `label_mask` if set (SemanticKITTI: `0xFFFF`), is the **raw
//! id** ([`PointCloud::label`](superflow_schemas::sensor::PointCloud::label)). The
//! **training class** is a `u8`: `mapping[raw]`, `ignore_index` (255) for a raw id the
//! mapping does not list; without a mapping the raw id itself, and a raw id that is not
//! below the number of `classes` (when given) or 256 is an error
//! ([`LabelError::UnknownId`]).
//!
//! Nothing here runs unless asked: the sample builder never reads labels.
//!
//! ```no_run
//! use superflow_pipeline::drive::labels::{DriveLabels, LabelConfig};
//! use superflow_pipeline::drive::{Dataset, IngestConfig};
//! use superflow_pipeline::source::ChunkCache;
//!
//! let dataset = Dataset::open(&["drive.mcap".into()], &IngestConfig::default())?;
//! let drive = &dataset.drives[0];
//! if let Some(labels) = DriveLabels::open(drive, &LabelConfig::default())? {
//!     let mut cache = ChunkCache::new(2);
//!     let sweep = labels.read(0, &mut cache)?;
//!     assert_eq!(sweep.labels.len(), sweep.decoded.cloud.len());
//! }
//! # Ok::<(), Box<dyn std::error::Error>>(())
//! ```

mod config;
mod error;
mod form;
mod map;
mod read;

pub use config::LabelConfig;
pub use error::LabelError;
pub use form::LabelForm;
pub use map::LabelMap;
pub use read::{DriveLabels, LabelledSweep};

#[cfg(test)]
mod tests;
