//! [`GenerateError`]: why a drive, its ground truth or a damaged recording could not be
//! generated or written. The generator's own output is always well formed, so these are
//! mostly limits (a stamp out of a format's range, an image too large for JPEG) and I/O.

use std::path::PathBuf;
use superflow_schemas::Stamp;
use superflow_schemas::ros2::CdrError;

/// Why a recording could not be generated or written.
#[derive(Debug, thiserror::Error)]
pub enum GenerateError {
    /// The MCAP writer (or, when damaging a drive, the reader) failed.
    #[error("writing MCAP: {0}")]
    Mcap(#[from] mcap::McapError),
    /// A camera image could not be encoded as JPEG.
    #[error("encoding JPEG for {frame_id}: {source}")]
    Jpeg {
        /// Frame id of the image.
        frame_id: String,
        /// What the encoder reported.
        source: jpeg_encoder::EncodingError,
    },
    /// A class map could not be encoded as PNG.
    #[error("encoding PNG for {frame_id}: {source}")]
    Png {
        /// Frame id of the class map.
        frame_id: String,
        /// What the encoder reported.
        source: png::EncodingError,
    },
    /// A class map to encode as 8-bit grey PNG is not Mono8.
    #[error("class map of {frame_id} is not Mono8")]
    NotMono8 {
        /// Frame id of the class map.
        frame_id: String,
    },
    /// A camera image is larger than JPEG allows (65535 pixels a side).
    #[error("image of {frame_id} is {width}x{height}: too large for JPEG (65535 a side)")]
    ImageTooLarge {
        /// Frame id of the image.
        frame_id: String,
        /// Width, pixels.
        width: u32,
        /// Height, pixels.
        height: u32,
    },
    /// A stamp cannot be written in the message format's time type.
    #[error("stamp {stamp} out of {format} range")]
    StampOutOfRange {
        /// The format (`ROS 2`, `Foxglove`).
        format: &'static str,
        /// The stamp.
        stamp: Stamp,
    },
    /// A Foxglove message type came without its protobuf schema.
    #[error("foxglove type {type_name} without schema")]
    MissingSchema {
        /// The Rust type.
        type_name: &'static str,
    },
    /// A sweep has more points than a `PointCloud2` row can count.
    #[error("sweep {sweep} has {points} points: too many for a PointCloud2")]
    TooManyPoints {
        /// Index of the sweep.
        sweep: usize,
        /// Its number of points.
        points: usize,
    },
    /// A ROS 2 message could not be encoded (or, when damaging a drive, decoded) as CDR.
    #[error(transparent)]
    Cdr(#[from] CdrError),
    /// A Foxglove protobuf message could not be decoded when damaging a drive.
    #[error("decoding protobuf: {0}")]
    ProtobufDecode(#[from] prost::DecodeError),
    /// The ground truth could not be serialised.
    #[error("ground truth JSON: {0}")]
    Json(#[from] serde_json::Error),
    /// A file or directory could not be written.
    #[error("{action} {}: {source}", path.display())]
    Io {
        /// What was being done (`creating`, `writing`).
        action: &'static str,
        /// The file or directory.
        path: PathBuf,
        /// The error.
        source: std::io::Error,
    },
    /// The drive read back to be damaged is not what the generator writes.
    #[error("reading the drive to damage: {what} (id {id})")]
    Malformed {
        /// What is wrong (`channel before its schema`, `message without channel`).
        what: &'static str,
        /// The schema or channel id concerned.
        id: u16,
    },
    /// Editing a message of the drive being damaged failed.
    #[error("{doing} on {topic}: {source}")]
    Damaging {
        /// What was being done (`poisoning a sweep`, `restamping a message`).
        doing: &'static str,
        /// Topic of the message.
        topic: String,
        /// Why it failed.
        source: Box<GenerateError>,
    },
}

impl GenerateError {
    /// An I/O error while `action` (`creating`, `writing`) `path`.
    pub fn io(action: &'static str, path: impl Into<PathBuf>, source: std::io::Error) -> Self {
        Self::Io {
            action,
            path: path.into(),
            source,
        }
    }
}

/// The result of the generator's functions.
pub type Result<T, E = GenerateError> = std::result::Result<T, E>;
