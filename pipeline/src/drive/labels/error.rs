//! [`LabelError`]: why labels cannot be read.

use crate::decode::points::PointsError;
use crate::drive::read::{FrameAt, ReadError};
use superflow_common::InvalidSetting;
use superflow_schemas::Stamp;

/// Why labels cannot be read.
#[derive(Debug, thiserror::Error)]
pub enum LabelError {
    /// The `[labels]` settings are out of range.
    #[error(transparent)]
    Config(#[from] InvalidSetting),
    /// The sweep (or, for a field, its labels) could not be read or decoded.
    #[error(transparent)]
    Read(#[from] ReadError),
    /// A sweep index past the LiDAR's sweeps.
    #[error("{files}: sweep {sweep} requested; the LiDAR has {sweeps} sweeps")]
    NoSweep {
        /// The drive's files.
        files: String,
        /// The index asked for.
        sweep: usize,
        /// Sweeps of the LiDAR.
        sweeps: usize,
    },
    /// A sidecar label cloud did not decode.
    #[error("{at}: {source}")]
    LabelCloud {
        /// Where it is.
        at: FrameAt,
        /// Why (boxed: the error stays small).
        #[source]
        source: Box<PointsError>,
    },
    /// A sweep without a label cloud of its stamp in the sidecar.
    #[error(
        "{file}: {topic} has no label cloud at {stamp}, the stamp of sweep {sweep} of {lidar_topic}"
    )]
    MissingLabelCloud {
        /// The sidecar file.
        file: String,
        /// Its label-cloud topic.
        topic: String,
        /// The sweep's stamp.
        stamp: Stamp,
        /// The sweep's index.
        sweep: usize,
        /// The LiDAR topic.
        lidar_topic: String,
    },
    /// A label cloud whose point count differs from its sweep's.
    #[error(
        "{file}: {topic} at {stamp}: {labels} labels for the {points} points of the sweep on {lidar_topic}"
    )]
    PointCount {
        /// The sidecar file.
        file: String,
        /// Its label-cloud topic.
        topic: String,
        /// The stamp of both.
        stamp: Stamp,
        /// Labels in the label cloud.
        labels: usize,
        /// Points in the sweep's message (dropped ones included).
        points: usize,
        /// The LiDAR topic.
        lidar_topic: String,
    },
    /// A raw id without a training class and no mapping to give it one.
    #[error("{at}: unknown raw id {id} without a mapping ({limit}; set [labels] mapping)")]
    UnknownId {
        /// The labelled message (LiDAR cloud or sidecar label cloud).
        at: FrameAt,
        /// The raw id.
        id: u32,
        /// The limit it breaks, in words.
        limit: String,
    },
    /// Several label clouds in the sidecar and nothing tells which labels the LiDAR.
    #[error(
        "{files}: the labels sidecar has several point clouds ({topics}) and none is named for the LiDAR {lidar_topic} (channel metadata `{key}`) or has a topic starting with it"
    )]
    AmbiguousSidecar {
        /// The drive's files.
        files: String,
        /// The candidates, comma-separated.
        topics: String,
        /// The LiDAR topic.
        lidar_topic: String,
        /// The metadata key that would decide.
        key: &'static str,
    },
}
