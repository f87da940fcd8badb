//! Looking at what superflow makes, in Foxglove: MCAP files of Foxglove's own protobuf
//! schemas, which Foxglove opens with no plugin.
//!
//! * [`writer`]: [`ViewWriter`], the MCAP writer of every view file, and [`ViewError`];
//! * [`cloud`]: point clouds with [`Column`]s of per-point values to colour by;
//! * [`image`]: camera images as PNG on `/superflow/<camera>/…`;
//! * [`sample`]: [`SampleMcap`], samples (clouds, images as the model sees them with their
//!   calibrations, superpixels, pairings, transforms) one after the other
//!   (`superflow-pipeline sample --out-mcap`, `--drive-mcap`).

pub mod cloud;
pub mod image;
pub mod sample;
pub mod writer;

pub use cloud::{Column, point_cloud};
pub use image::camera_topic;
pub use sample::{POINT_FIELDS, SampleMcap, ViewSummary, resized_calibration};
pub use writer::{ViewError, ViewWriter, frame_transform};
