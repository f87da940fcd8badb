//! Reading one sensor message of a drive: the raw message of a frame, and its decoding
//! into a point cloud or an image, with where it is ([`FrameAt`]) in every error.

use super::index::Drive;
use super::streams::{CameraStream, FrameRef};
use crate::decode::image::{self, ImageError, Scale, ScaledImage, Target};
use crate::decode::points::{DecodedCloud, PointsError};
use crate::decode::{DecodeError, foxglove, ros2};
use crate::decode::{Dialect, SchemaKind, schema_kind};
use crate::source::{ChunkCache, MessageRef, SourceError};
use std::path::PathBuf;
use superflow_schemas::Stamp;
use superflow_schemas::sensor::Image;

/// Where a frame is: shown as `file: topic at stamp`.
#[derive(Debug, Clone, PartialEq, Eq)]
pub struct FrameAt {
    /// The file.
    pub file: String,
    /// The topic.
    pub topic: String,
    /// The frame's stamp.
    pub stamp: Stamp,
}

impl std::fmt::Display for FrameAt {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        write!(f, "{}: {} at {}", self.file, self.topic, self.stamp)
    }
}

/// A sensor message that could not be read or decoded, with where it is.
#[derive(Debug, thiserror::Error)]
pub enum ReadError {
    /// The file could not deliver the message.
    #[error(transparent)]
    Source(#[from] SourceError),
    /// An image (or class map) of a camera did not decode.
    #[error("{at}: {camera} ({source})")]
    Image {
        /// Where the image is.
        at: FrameAt,
        /// The camera.
        camera: String,
        /// What failed (boxed: a read error stays small).
        #[source]
        source: Box<ImageReadError>,
    },
    /// A LiDAR sweep did not decode.
    #[error("{at}: {source}")]
    Sweep {
        /// Where the sweep is.
        at: FrameAt,
        /// What failed (boxed: a read error stays small).
        #[source]
        source: Box<PointsError>,
    },
    /// A message decoded but cannot be used.
    #[error("{at}: {reason}")]
    Decode {
        /// Where the message is.
        at: FrameAt,
        /// What is wrong, in words.
        reason: String,
    },
}

/// Why an image message did not decode.
#[derive(Debug, thiserror::Error)]
pub enum ImageReadError {
    /// The message itself did not decode (CDR or protobuf).
    #[error(transparent)]
    Message(#[from] DecodeError),
    /// Its image data did not decode.
    #[error(transparent)]
    Image(#[from] ImageError),
    /// The channel's schema is not an image.
    #[error("schema `{0}` is not an image")]
    NotAnImage(String),
}

impl Drive {
    /// The raw message of a sensor frame (through `cache`, which holds a few
    /// decompressed chunks: memory stays bounded whatever the file size).
    pub fn read_raw<'c>(
        &'c self,
        frame: &FrameRef,
        cache: &'c mut crate::source::ChunkCache,
    ) -> Result<MessageRef<'c>, SourceError> {
        let file =
            self.files
                .get(frame.file as usize)
                .ok_or_else(|| SourceError::NoSuchMessage {
                    path: PathBuf::from(self.file_list()),
                    loc: frame.loc,
                })?;
        file.read_message(frame.loc, cache)
    }

    /// Where `frame` of `topic` is: its file, the topic and its stamp.
    pub fn frame_at(&self, frame: &FrameRef, topic: &str) -> FrameAt {
        FrameAt {
            file: self
                .files
                .get(frame.file as usize)
                .map_or_else(|| self.file_list(), |f| f.path().display().to_string()),
            topic: topic.to_string(),
            stamp: frame.stamp,
        }
    }

    /// A [`ReadError::Decode`] naming the file, topic and stamp of `frame`.
    pub(crate) fn decode_error(
        &self,
        frame: &FrameRef,
        topic: &str,
        reason: impl std::fmt::Display,
    ) -> ReadError {
        ReadError::Decode {
            at: self.frame_at(frame, topic),
            reason: reason.to_string(),
        }
    }

    /// Decodes image `frame` of `camera` (its colour image with `Target::Rgb`; pass a
    /// frame of `camera.superpixels` with `Target::Mono` for its class map).
    pub fn read_image(
        &self,
        camera: &CameraStream,
        frame: &FrameRef,
        target: Target,
        cache: &mut ChunkCache,
    ) -> Result<Image, ReadError> {
        self.read_image_scaled(camera, frame, target, Scale::Full, cache)
            .map(|s| s.image)
    }

    /// [`Drive::read_image`] at a reduced [`Scale`] where the image allows it (a JPEG
    /// colour image), with the stored image's size.
    pub fn read_image_scaled(
        &self,
        camera: &CameraStream,
        frame: &FrameRef,
        target: Target,
        scale: Scale,
        cache: &mut ChunkCache,
    ) -> Result<ScaledImage, ReadError> {
        let message = self.read_raw(frame, cache)?;
        decode_image(&message, target, scale).map_err(|source| ReadError::Image {
            at: self.frame_at(frame, &message.channel.topic),
            camera: camera.name.clone(),
            source: Box::new(source),
        })
    }

    /// Decodes LiDAR sweep `frame` (non-finite points are dropped and counted in the
    /// result).
    pub fn read_sweep(
        &self,
        frame: &FrameRef,
        cache: &mut ChunkCache,
    ) -> Result<DecodedCloud, ReadError> {
        let message = self.read_raw(frame, cache)?;
        crate::decode::points::decode_message(&message, None).map_err(|source| ReadError::Sweep {
            at: self.frame_at(frame, &message.channel.topic),
            source: Box::new(source),
        })
    }
}

/// Decodes an image message of either dialect, compressed or raw.
fn decode_image(
    message: &MessageRef<'_>,
    target: Target,
    scale: Scale,
) -> Result<ScaledImage, ImageReadError> {
    let data = message.data;
    let full = |image: Image| ScaledImage {
        native: (image.width, image.height),
        image,
    };
    Ok(match schema_kind(message.channel) {
        Some((SchemaKind::CompressedImage, Dialect::Ros2)) => {
            let m = ros2::decode(data).map_err(DecodeError::from)?;
            image::decode_ros2_compressed_scaled(&m, target, scale)?
        }
        Some((SchemaKind::RawImage, Dialect::Ros2)) => {
            let m = ros2::decode(data).map_err(DecodeError::from)?;
            full(image::decode_ros2_raw(&m, target)?)
        }
        Some((SchemaKind::CompressedImage, Dialect::FoxgloveProtobuf)) => {
            let m = foxglove::decode("foxglove.CompressedImage", data)?;
            image::decode_foxglove_compressed_scaled(&m, target, scale)?
        }
        Some((SchemaKind::RawImage, Dialect::FoxgloveProtobuf)) => {
            let m = foxglove::decode("foxglove.RawImage", data)?;
            full(image::decode_foxglove_raw(&m, target)?)
        }
        _ => {
            let schema = message.channel.schema_name().to_string();
            return Err(ImageReadError::NotAnImage(schema));
        }
    })
}
