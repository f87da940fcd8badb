//! Just the stamp and frame of a sensor message, for the index: the point or pixel data
//! is skipped without being copied (prost skips unknown fields; CDR decoding stops after
//! the header).

use crate::decode::{DecodeError, foxglove, ros2};
use crate::decode::{Dialect, SchemaKind};
use serde::Deserialize;
use superflow_schemas::Stamp;

/// Why the stamp and frame of a message could not be read.
#[derive(Debug, thiserror::Error)]
pub(super) enum HeadError {
    /// The message did not decode.
    #[error(transparent)]
    Decode(#[from] DecodeError),
    /// The schema is not a LiDAR or camera message.
    #[error("not a sensor message")]
    NotSensor,
}

// Just the stamp and frame of Foxglove sensor messages: prost skips the other fields
// (the point or pixel data) without copying them.
macro_rules! stamp_and_frame {
    ($name:ident, $frame_tag:literal) => {
        #[derive(Clone, PartialEq, prost::Message)]
        struct $name {
            #[prost(message, optional, tag = "1")]
            timestamp: Option<foxglove::Timestamp>,
            #[prost(string, tag = $frame_tag)]
            frame_id: String,
        }
    };
}
stamp_and_frame!(PointCloudHead, "2");
stamp_and_frame!(CompressedImageHead, "4");
stamp_and_frame!(RawImageHead, "7");

/// Just the header of a ROS 2 sensor message (CDR decoding stops after it).
#[derive(Debug, Deserialize)]
struct Ros2Head {
    header: ros2::Header,
}

/// The sensor stamp and frame id of a LiDAR or camera message of `kind`.
pub(super) fn stamp_and_frame(
    kind: SchemaKind,
    dialect: Dialect,
    data: &[u8],
) -> Result<(Stamp, String), HeadError> {
    match dialect {
        Dialect::Ros2 => {
            let head: Ros2Head = ros2::decode(data).map_err(DecodeError::from)?;
            Ok((head.header.stamp.stamp(), head.header.frame_id))
        }
        Dialect::FoxgloveProtobuf => {
            let (schema, timestamp, frame_id) = match kind {
                SchemaKind::PointCloud => {
                    let m: PointCloudHead = foxglove::decode("foxglove.PointCloud", data)?;
                    ("foxglove.PointCloud", m.timestamp, m.frame_id)
                }
                SchemaKind::CompressedImage => {
                    let m: CompressedImageHead =
                        foxglove::decode("foxglove.CompressedImage", data)?;
                    ("foxglove.CompressedImage", m.timestamp, m.frame_id)
                }
                SchemaKind::RawImage => {
                    let m: RawImageHead = foxglove::decode("foxglove.RawImage", data)?;
                    ("foxglove.RawImage", m.timestamp, m.frame_id)
                }
                _ => return Err(HeadError::NotSensor),
            };
            let stamp = foxglove::stamp(schema, timestamp.as_ref())?;
            Ok((stamp, frame_id))
        }
    }
}
