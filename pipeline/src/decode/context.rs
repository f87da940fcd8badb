//! The decoding context shared by the point-cloud and image decoders: the frame id and
//! stamp of the message being decoded, which every error about the message names.

use super::error::DecodeError;
use super::{foxglove, ros2};
use superflow_schemas::Stamp;

/// Frame and stamp of the message being decoded, for error messages.
#[derive(Debug, Clone, Copy)]
pub(crate) struct Ctx<'a> {
    /// Frame of the message.
    pub(crate) frame_id: &'a str,
    /// Its sensor stamp.
    pub(crate) stamp: Stamp,
}

impl<'a> Ctx<'a> {
    /// The context of a ROS 2 message: its header's frame and stamp.
    pub(crate) fn ros2(header: &'a ros2::Header) -> Self {
        Self {
            frame_id: &header.frame_id,
            stamp: header.stamp.stamp(),
        }
    }

    /// The context of a Foxglove message; an error when it has no `timestamp`.
    pub(crate) fn foxglove<M: FoxgloveStamped>(msg: &'a M) -> Result<Self, DecodeError> {
        Ok(Self {
            frame_id: msg.frame_id(),
            stamp: foxglove::stamp(M::SCHEMA, msg.timestamp())?,
        })
    }

    /// The frame id, owned (for an error).
    pub(crate) fn id(&self) -> String {
        self.frame_id.to_string()
    }
}

/// A Foxglove sensor message: a schema name, a frame and an optional timestamp.
pub(crate) trait FoxgloveStamped {
    /// Schema name (`foxglove.PointCloud`, ...).
    const SCHEMA: &'static str;
    /// The `frame_id` field.
    fn frame_id(&self) -> &str;
    /// The `timestamp` field.
    fn timestamp(&self) -> Option<&foxglove::Timestamp>;
}

macro_rules! foxglove_stamped {
    ($($ty:ident => $schema:literal),* $(,)?) => {$(
        impl FoxgloveStamped for foxglove::$ty {
            const SCHEMA: &'static str = $schema;
            fn frame_id(&self) -> &str {
                &self.frame_id
            }
            fn timestamp(&self) -> Option<&foxglove::Timestamp> {
                self.timestamp.as_ref()
            }
        }
    )*};
}

foxglove_stamped!(
    PointCloud => "foxglove.PointCloud",
    CompressedImage => "foxglove.CompressedImage",
    RawImage => "foxglove.RawImage",
);
