//! The limit and checks every image decoder applies: [`MAX_IMAGE_BYTES`], the errors
//! about the message being decoded (its frame and stamp, from [`Ctx`]), and [`guarded`],
//! which turns a third-party decoder's panic into an error.

use std::panic::{AssertUnwindSafe, catch_unwind};

use superflow_schemas::sensor::Image;

use super::codec::Codec;
use super::decoded::Decoded;
use super::error::{ImageError, Rejection};
use crate::decode::context::Ctx;

/// Largest decoded image accepted, in bytes (512 MiB). Checked before allocating, on the
/// output and on the PNG decoder's sample buffer.
pub const MAX_IMAGE_BYTES: u64 = 512 * 1024 * 1024;

/// The image decoders' errors and checks about the message being decoded.
impl Ctx<'_> {
    /// [`ImageError::Corrupt`]: `codec` rejected the data.
    pub(super) fn corrupt(&self, codec: Codec, reason: impl Into<Rejection>) -> ImageError {
        ImageError::Corrupt {
            frame_id: self.id(),
            stamp: self.stamp,
            codec,
            reason: reason.into(),
        }
    }

    /// [`ImageError::NotMono`]: `found` cannot be kept as `Mono8`.
    pub(super) fn not_mono(&self, found: impl Into<String>) -> ImageError {
        ImageError::NotMono {
            frame_id: self.id(),
            stamp: self.stamp,
            found: found.into(),
        }
    }

    /// [`ImageError::TooLarge`]: `bytes` exceed [`MAX_IMAGE_BYTES`].
    pub(super) fn too_large(&self, width: u64, height: u64, bytes: u64) -> ImageError {
        ImageError::TooLarge {
            frame_id: self.id(),
            stamp: self.stamp,
            width,
            height,
            bytes,
            limit: MAX_IMAGE_BYTES,
        }
    }

    /// Checks that a `width × height` image of `channels` bytes per pixel is non-empty
    /// and within [`MAX_IMAGE_BYTES`]; returns its size in bytes.
    pub(super) fn checked_size(
        &self,
        width: u64,
        height: u64,
        channels: u64,
    ) -> Result<usize, ImageError> {
        if width == 0 || height == 0 {
            return Err(ImageError::ZeroSize {
                frame_id: self.id(),
                stamp: self.stamp,
                width,
                height,
            });
        }
        let bytes = width
            .checked_mul(height)
            .and_then(|n| n.checked_mul(channels))
            .unwrap_or(u64::MAX);
        if bytes > MAX_IMAGE_BYTES {
            return Err(self.too_large(width, height, bytes));
        }
        usize::try_from(bytes).map_err(|_| self.too_large(width, height, bytes))
    }

    /// The sensor-model image, checked.
    pub(super) fn image(&self, decoded: Decoded) -> Result<Image, ImageError> {
        Image::new(
            self.stamp,
            self.frame_id,
            decoded.width,
            decoded.height,
            decoded.format,
            decoded.data,
        )
        .map_err(|source| ImageError::Sensor {
            frame_id: self.id(),
            stamp: self.stamp,
            source,
        })
    }
}

/// Runs a third-party decoder, turning a panic into [`ImageError::Corrupt`].
pub(super) fn guarded<T>(
    codec: Codec,
    ctx: Ctx<'_>,
    decode: impl FnOnce() -> Result<T, ImageError>,
) -> Result<T, ImageError> {
    catch_unwind(AssertUnwindSafe(decode))
        .unwrap_or_else(|_| Err(ctx.corrupt(codec, "the decoder panicked on this input")))
}
