//! Why a sample (or a plan) cannot be built: [`SampleError`].

use crate::decode::DecodeError;
use crate::drive::TfError;
use crate::drive::{IngestError, ReadError};
use crate::source::SourceError;
use superflow_common::InvalidSetting;
use superflow_schemas::Stamp;

/// Why a sample (or a plan) cannot be built. Each names the file, channel and time.
#[derive(Debug, thiserror::Error)]
pub enum SampleError {
    /// A message could not be read or decoded.
    #[error(transparent)]
    Read(#[from] ReadError),
    /// A transform is missing at the instant a sensor needs it.
    #[error("{files}: {what} at {stamp}: {source}")]
    Transform {
        /// The drive's files.
        files: String,
        /// Which sensor needed it.
        what: String,
        /// The instant.
        stamp: Stamp,
        /// The lookup error.
        source: Box<TfError>,
    },
    /// A class map (or a sidecar's SLIC labels) that cannot serve as superpixels.
    #[error("{files}: {topic} at {stamp}: {reason}")]
    Superpixels {
        /// The drive's files.
        files: String,
        /// The class-map topic.
        topic: String,
        /// The image stamp.
        stamp: Stamp,
        /// What is wrong (boxed: the error stays small).
        #[source]
        reason: Box<SuperpixelsFault>,
    },
    /// An image that does not match its calibration.
    #[error("{files}: {topic} at {stamp}: {reason}")]
    Image {
        /// The drive's files.
        files: String,
        /// The image topic.
        topic: String,
        /// The image stamp.
        stamp: Stamp,
        /// What is wrong.
        reason: String,
    },
    /// A setting of the recipe is out of range.
    #[error(transparent)]
    Setting(#[from] InvalidSetting),
    /// The dataset lacks sensors that training needs.
    #[error(transparent)]
    Sensors(#[from] IngestError),
    /// `superpixels = "channel"` but some cameras have no class-map channel.
    #[error("{files}: superpixels = \"channel\" but cameras {cameras} have no class-map channel")]
    NoClassMaps {
        /// The drive's files.
        files: String,
        /// The cameras without one, `, `-separated.
        cameras: String,
    },
    /// A drive without a LiDAR (a plan never holds one; only a misuse gets here).
    #[error("{files}: no LiDAR")]
    NoLidar {
        /// The drive's files.
        files: String,
    },
    /// An index past the plan.
    #[error("keyframe {index} requested, the plan has {len}")]
    OutOfRange {
        /// The index asked for.
        index: usize,
        /// Keyframes in the plan.
        len: usize,
    },
}

/// Why a class map or a sidecar's SLIC labels cannot serve as superpixels
/// ([`SampleError::Superpixels`]).
#[derive(Debug, thiserror::Error)]
pub enum SuperpixelsFault {
    /// The sidecar's message could not be read.
    #[error("{0}")]
    Read(#[source] SourceError),
    /// The sidecar's message did not decode.
    #[error("{0}")]
    Decode(#[source] DecodeError),
    /// The stored labels' PNG did not decode.
    #[error("{0}")]
    Png(#[source] png::DecodingError),
    /// What is wrong with the labels, in words.
    #[error("{0}")]
    Invalid(String),
}

impl From<String> for SuperpixelsFault {
    fn from(reason: String) -> Self {
        Self::Invalid(reason)
    }
}
