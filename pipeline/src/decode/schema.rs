//! Which sensor a channel carries and in which dialect: [`schema_kind`] recognizes a
//! channel's schema name and message encoding as a [`SchemaKind`] of a [`Dialect`]
//! (Foxglove protobuf or ROS 2 CDR). The decoders dispatch on it, and channel discovery
//! (`drive::discover`) assigns roles from it.

use super::ros2;
use crate::source::ChannelInfo;
use serde::{Deserialize, Serialize};

/// The sensor kind a schema carries.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum SchemaKind {
    /// `foxglove.PointCloud` or `sensor_msgs/msg/PointCloud2`.
    PointCloud,
    /// `foxglove.CompressedImage` or `sensor_msgs/msg/CompressedImage`.
    CompressedImage,
    /// `foxglove.RawImage` or `sensor_msgs/msg/Image`.
    RawImage,
    /// `foxglove.CameraCalibration` or `sensor_msgs/msg/CameraInfo`.
    Calibration,
    /// `foxglove.FrameTransform`.
    FrameTransform,
    /// `foxglove.FrameTransforms`.
    FrameTransforms,
    /// `tf2_msgs/msg/TFMessage`.
    TfMessage,
}

/// The dialect of a channel's encoding.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Serialize, Deserialize)]
#[serde(rename_all = "snake_case")]
pub enum Dialect {
    /// Foxglove protobuf schemas.
    FoxgloveProtobuf,
    /// ROS 2 (`ros2msg` + CDR).
    Ros2,
}

/// Recognizes a channel's schema (name and encodings); `None` for anything else.
pub fn schema_kind(channel: &ChannelInfo) -> Option<(SchemaKind, Dialect)> {
    let name = channel.schema_name();
    let protobuf = channel.message_encoding == "protobuf";
    let cdr = channel.message_encoding == ros2::MESSAGE_ENCODING;
    let kind = match name {
        "foxglove.PointCloud" if protobuf => (SchemaKind::PointCloud, Dialect::FoxgloveProtobuf),
        "foxglove.CompressedImage" if protobuf => {
            (SchemaKind::CompressedImage, Dialect::FoxgloveProtobuf)
        }
        "foxglove.RawImage" if protobuf => (SchemaKind::RawImage, Dialect::FoxgloveProtobuf),
        "foxglove.CameraCalibration" if protobuf => {
            (SchemaKind::Calibration, Dialect::FoxgloveProtobuf)
        }
        "foxglove.FrameTransform" if protobuf => {
            (SchemaKind::FrameTransform, Dialect::FoxgloveProtobuf)
        }
        "foxglove.FrameTransforms" if protobuf => {
            (SchemaKind::FrameTransforms, Dialect::FoxgloveProtobuf)
        }
        ros2::POINT_CLOUD2 if cdr => (SchemaKind::PointCloud, Dialect::Ros2),
        ros2::COMPRESSED_IMAGE if cdr => (SchemaKind::CompressedImage, Dialect::Ros2),
        ros2::IMAGE if cdr => (SchemaKind::RawImage, Dialect::Ros2),
        ros2::CAMERA_INFO if cdr => (SchemaKind::Calibration, Dialect::Ros2),
        ros2::TF_MESSAGE if cdr => (SchemaKind::TfMessage, Dialect::Ros2),
        _ => return None,
    };
    Some(kind)
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::source::SchemaInfo;
    use std::collections::BTreeMap;
    use std::sync::Arc;

    fn channel(schema: &str, encoding: &str) -> ChannelInfo {
        ChannelInfo {
            id: 1,
            topic: "/t".into(),
            schema: Some(Arc::new(SchemaInfo {
                id: 1,
                name: schema.into(),
                encoding: String::new(),
                data: Vec::new(),
            })),
            message_encoding: encoding.into(),
            metadata: BTreeMap::new(),
        }
    }

    #[test]
    fn schemas_are_recognized_only_with_their_encoding() {
        assert_eq!(
            schema_kind(&channel("foxglove.PointCloud", "protobuf")),
            Some((SchemaKind::PointCloud, Dialect::FoxgloveProtobuf))
        );
        assert_eq!(
            schema_kind(&channel(ros2::POINT_CLOUD2, ros2::MESSAGE_ENCODING)),
            Some((SchemaKind::PointCloud, Dialect::Ros2))
        );
        assert_eq!(
            schema_kind(&channel(ros2::TF_MESSAGE, ros2::MESSAGE_ENCODING)),
            Some((SchemaKind::TfMessage, Dialect::Ros2))
        );
        assert_eq!(schema_kind(&channel("foxglove.PointCloud", "cdr")), None);
        assert_eq!(schema_kind(&channel(ros2::IMAGE, "protobuf")), None);
        assert_eq!(schema_kind(&channel("std_msgs/msg/String", "cdr")), None);
    }
}
