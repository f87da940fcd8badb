//! The per-dialect entry points: ROS 2 and Foxglove compressed and raw images, each
//! decoded with the frame and stamp of its message.

use superflow_schemas::sensor::Image;

use super::error::ImageError;
use super::format::decode_compressed;
use super::raw::{Raw, decode_raw};
use super::scale::{Scale, ScaledImage};
use super::target::Target;
use crate::decode::context::{Ctx, FoxgloveStamped};
use crate::decode::{foxglove, ros2};

/// Decodes a ROS 2 `sensor_msgs/msg/CompressedImage` (JPEG or PNG, see the module
/// documentation for the accepted `format` strings).
pub fn decode_ros2_compressed(
    msg: &ros2::CompressedImage,
    target: Target,
) -> Result<Image, ImageError> {
    decode_ros2_compressed_scaled(msg, target, Scale::Full).map(|s| s.image)
}

/// [`decode_ros2_compressed`] at a reduced [`Scale`] where the JPEG allows it.
pub fn decode_ros2_compressed_scaled(
    msg: &ros2::CompressedImage,
    target: Target,
    scale: Scale,
) -> Result<ScaledImage, ImageError> {
    let ctx = Ctx::ros2(&msg.header);
    decode_compressed(&msg.data, &msg.format, target, scale, ctx)
}

/// Decodes a ROS 2 `sensor_msgs/msg/Image` (8-bit RGB/BGR/RGBA/BGRA/mono encodings,
/// with row padding; see the module documentation).
pub fn decode_ros2_raw(msg: &ros2::Image, target: Target) -> Result<Image, ImageError> {
    let ctx = Ctx::ros2(&msg.header);
    let raw = Raw {
        encoding: &msg.encoding,
        width: msg.width,
        height: msg.height,
        step: msg.step,
        data: &msg.data,
    };
    decode_raw(&raw, target, ctx)
}

/// Decodes a `foxglove.CompressedImage` (`format` `jpeg` or `png`; `webp` and `avif` are
/// reported as unsupported).
pub fn decode_foxglove_compressed(
    msg: &foxglove::CompressedImage,
    target: Target,
) -> Result<Image, ImageError> {
    decode_foxglove_compressed_scaled(msg, target, Scale::Full).map(|s| s.image)
}

/// [`decode_foxglove_compressed`] at a reduced [`Scale`] where the JPEG allows it.
pub fn decode_foxglove_compressed_scaled(
    msg: &foxglove::CompressedImage,
    target: Target,
    scale: Scale,
) -> Result<ScaledImage, ImageError> {
    let ctx = foxglove_ctx(msg)?;
    decode_compressed(&msg.data, &msg.format, target, scale, ctx)
}

/// Decodes a `foxglove.RawImage` (the encodings of [`decode_ros2_raw`]).
pub fn decode_foxglove_raw(msg: &foxglove::RawImage, target: Target) -> Result<Image, ImageError> {
    let ctx = foxglove_ctx(msg)?;
    let raw = Raw {
        encoding: &msg.encoding,
        width: msg.width,
        height: msg.height,
        step: msg.step,
        data: &msg.data,
    };
    decode_raw(&raw, target, ctx)
}

/// The context of a Foxglove image: its frame and stamp (an error without a timestamp).
fn foxglove_ctx<M: FoxgloveStamped>(msg: &M) -> Result<Ctx<'_>, ImageError> {
    Ctx::foxglove(msg).map_err(|source| ImageError::Timestamp {
        frame_id: msg.frame_id().to_string(),
        source,
    })
}
