//! Camera images (and per-pixel class maps) as recorders write them, decoded into the
//! sensor model's [`Image`] (`Rgb8` or `Mono8`, tightly packed, row-major).
//!
//! # Messages
//!
//! | message | entry point | fields read |
//! |---|---|---|
//! | ROS 2 `sensor_msgs/msg/CompressedImage` | [`decode_ros2_compressed`] | `header`, `format`, `data` |
//! | ROS 2 `sensor_msgs/msg/Image` | [`decode_ros2_raw`] | `header`, `width`, `height`, `encoding`, `step`, `data` |
//! | `foxglove.CompressedImage` | [`decode_foxglove_compressed`] | `timestamp`, `frame_id`, `format`, `data` |
//! | `foxglove.RawImage` | [`decode_foxglove_raw`] | `timestamp`, `frame_id`, `width`, `height`, `encoding`, `step`, `data` |
//!
//! # Compressed formats (`format`)
//!
//! | `format` | decoded as |
//! |---|---|
//! | `jpeg`, `jpg`, `image/jpeg` | JPEG (libjpeg-turbo; bit-exact with Pillow and `djpeg`, also at a reduced [`Scale`]): YCbCr and grey → RGB; a grey JPEG → `Mono8` for [`Target::Mono`]; CMYK is an error |
//! | `png`, `image/png` | PNG (`png` crate): grey 1/2/4/8/16-bit, grey+alpha, RGB, RGBA (8/16-bit), palette 1/2/4/8-bit; alpha and `tRNS` are dropped |
//! | `<src>; jpeg compressed bgr8`, `<src>; png compressed bgr8` / `bgr16` / `bgra8` / `bgra16` (image_transport) | as JPEG/PNG, channel order as stored (see below) |
//! | `<src>; jpeg compressed rgb8`, `<src>; png compressed rgb8` (any target starting with `rgb`) | as JPEG/PNG, then red and blue swapped (see below) |
//! | `<src>; jpeg compressed ` / `<src>; png compressed ` (mono sources: no target) | as JPEG/PNG |
//! | `<src>; compressedDepth …` | error [`ImageError::CompressedDepth`] (a quantized depth map, not a camera image) |
//! | `webp`, `avif`, `qoi`, anything else | error [`ImageError::UnsupportedFormat`] |
//! | `""` | by magic bytes |
//!
//! The magic bytes win over the format string: data starting with `FF D8` is decoded as
//! JPEG and data starting with `89 50 4E 47` as PNG whatever `format` says (empty and
//! wrong format strings occur in real recordings). Only when that decode fails and
//! `format` names the other codec is the other codec tried; when both fail the error
//! ([`ImageError::FormatMismatch`]) reports the disagreement and both failures.
//!
//! ## image_transport channel order
//!
//! `compressed_image_transport` converts a colour image to a `bgr8` (`bgr16`, `bgra8`)
//! OpenCV `Mat` and passes it to `cv::imencode`. OpenCV's encoders treat a 3-channel
//! `Mat` as BGR and write **standard** files: the JPEG encoder converts BGR to YCbCr, and
//! the PNG encoder calls `png_set_bgr`, so the PNG's samples are in RGB order (OpenCV
//! `modules/imgcodecs/src/grfmt_png.cpp`, `PngEncoder::write`). A normal decoder therefore
//! returns correct colours for a `… compressed bgr8` payload and no swap is applied, for
//! JPEG and PNG alike. A target starting with `rgb` (`… compressed rgb8`, written by
//! older publishers) means an RGB `Mat` was handed to `cv::imencode`, which stored it
//! channel-swapped; red and blue are swapped back. This is exactly what
//! image_transport's own `CompressedSubscriber` does (it reverts only `compressed bgr`
//! payloads to BGR and treats every other payload as RGB).
//!
//! # Raw encodings (`encoding`, as ROS 2 and `foxglove.RawImage` write them)
//!
//! | `encoding` | read as |
//! |---|---|
//! | `rgb8` | 3 bytes, red first |
//! | `bgr8`, `8UC3` | 3 bytes, blue first (`8UC3` follows cv_bridge/OpenCV, whose 3-channel `Mat`s are BGR) |
//! | `rgba8` | 4 bytes, red first, alpha dropped |
//! | `bgra8`, `8UC4` | 4 bytes, blue first, alpha dropped (`8UC4` as OpenCV's BGRA) |
//! | `mono8`, `8UC1` | 1 byte (`8UC1` is a single-channel 8-bit `Mat`: grey levels or ids) |
//! | `mono16`, `16UC1`, `16SC1`, `32FC1`, `rgb16`, … | error [`ImageError::UnsupportedEncoding`] (more than 8 bits per channel) |
//! | `bayer_*` | error [`ImageError::UnsupportedEncoding`] (mosaic; debayer upstream) |
//! | `yuv422`, `uyvy`, `yuyv`, `nv21`, … | error [`ImageError::UnsupportedEncoding`] |
//!
//! Encodings are matched case-insensitively. `step` is the byte length of a row and may
//! exceed `width × channels` (row padding, skipped); `step = 0` (an unset protobuf field)
//! means tightly packed rows. `data` must hold `step × height` bytes; the padding of the
//! last row may be omitted. `is_bigendian` does not matter for 8-bit samples.
//!
//! # Targets
//!
//! [`Target::Rgb`] (the default, for camera images) gives `Rgb8`: colour is converted to
//! RGB order, single-channel data is replicated to three channels, 16-bit PNG samples
//! keep their high byte and 1/2/4-bit grey is scaled to `0..=255`.
//!
//! [`Target::Mono`] ("keep ids", for class maps and grey cameras) gives `Mono8` with the
//! stored values untouched: `mono8`/`8UC1` raw data, 8-bit grey (or grey+alpha) PNGs,
//! 1/2/4-bit grey PNGs (raw values, not scaled), palette PNGs (the palette **indices**,
//! as in Pascal VOC style class maps) and grey JPEGs. Anything that would need a colour
//! conversion or a bit-depth reduction (RGB/BGR data, colour JPEGs, 16-bit PNGs) is an
//! error ([`ImageError::NotMono`]) rather than a silent corruption of the ids.
//!
//! # Errors and limits
//!
//! Every error names the frame id and stamp of the message (the caller adds file and
//! topic). Decoding never panics on malformed input: sizes are checked before anything is
//! allocated, images whose decoded size (or PNG sample buffer) would exceed
//! [`MAX_IMAGE_BYTES`] are rejected, truncated JPEG and PNG data are errors (a JPEG
//! without an end-of-image marker after its scan data counts as truncated), and a panic
//! inside a third-party codec is caught and reported as [`ImageError::Corrupt`].

pub mod buffers;
mod error;
mod format;
mod jpeg;
mod png;
mod png_grey;
mod raw;
#[cfg(test)]
mod tests;

use std::panic::{AssertUnwindSafe, catch_unwind};

use superflow_schemas::sensor::{Image, PixelFormat};

use super::context::{Ctx, FoxgloveStamped};
use super::{foxglove, ros2};
pub use error::ImageError;
pub use format::Codec;
use format::decode_compressed;
use raw::{Raw, decode_raw};

/// Largest decoded image accepted, in bytes (512 MiB). Checked before allocating, on the
/// output and on the PNG decoder's sample buffer.
pub const MAX_IMAGE_BYTES: u64 = 512 * 1024 * 1024;

/// What the caller wants out of an image.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Hash, Default)]
pub enum Target {
    /// A camera image as `Rgb8`; single-channel sources are replicated to three channels.
    #[default]
    Rgb,
    /// `Mono8` with the stored values kept exactly (class ids of a semantic map, or grey
    /// levels); colour or 16-bit sources are an error, never converted.
    Mono,
}

/// How small a decoded colour image may be. A JPEG can decode at 1/2 or 1/4 of its size
/// in the DCT domain, which costs a fraction of a full decode; a sample that resizes to
/// 448×224 anyway asks for [`Scale::AtLeast`] that size. PNG, raw images and class maps
/// ([`Target::Mono`]) always decode at full size.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Hash, Default)]
pub enum Scale {
    /// Every pixel.
    #[default]
    Full,
    /// The smallest of 1/4, 1/2 and full size that is at least `width × height`.
    AtLeast {
        /// Smallest acceptable width.
        width: u32,
        /// Smallest acceptable height.
        height: u32,
    },
}

/// A decoded image and the size of the image it was decoded from (different from the
/// image's own size when a JPEG decoded at a reduced [`Scale`]).
#[derive(Debug, Clone, PartialEq)]
pub struct ScaledImage {
    /// The pixels.
    pub image: Image,
    /// Width and height of the stored image.
    pub native: (u32, u32),
}

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

/// The image decoders' errors and checks about the message being decoded.
impl Ctx<'_> {
    /// [`ImageError::Corrupt`]: `codec` rejected the data.
    fn corrupt(&self, codec: Codec, reason: impl Into<String>) -> ImageError {
        ImageError::Corrupt {
            frame_id: self.id(),
            stamp: self.stamp,
            codec,
            reason: reason.into(),
        }
    }

    /// [`ImageError::NotMono`]: `found` cannot be kept as `Mono8`.
    fn not_mono(&self, found: impl Into<String>) -> ImageError {
        ImageError::NotMono {
            frame_id: self.id(),
            stamp: self.stamp,
            found: found.into(),
        }
    }

    /// [`ImageError::TooLarge`]: `bytes` exceed [`MAX_IMAGE_BYTES`].
    fn too_large(&self, width: u64, height: u64, bytes: u64) -> ImageError {
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
    fn checked_size(&self, width: u64, height: u64, channels: u64) -> Result<usize, ImageError> {
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
    fn image(&self, decoded: Decoded) -> Result<Image, ImageError> {
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

/// Decoded pixels before they become an [`Image`].
#[derive(Debug)]
struct Decoded {
    /// Width in pixels.
    width: u32,
    /// Height in pixels.
    height: u32,
    /// Size of the stored image (`(width, height)` unless a JPEG decoded at a reduced
    /// scale).
    native: (u32, u32),
    /// `Rgb8` or `Mono8`.
    format: PixelFormat,
    /// Tightly packed rows.
    data: Vec<u8>,
}

/// Runs a third-party decoder, turning a panic into [`ImageError::Corrupt`].
fn guarded<T>(
    codec: Codec,
    ctx: Ctx<'_>,
    decode: impl FnOnce() -> Result<T, ImageError>,
) -> Result<T, ImageError> {
    catch_unwind(AssertUnwindSafe(decode))
        .unwrap_or_else(|_| Err(ctx.corrupt(codec, "the decoder panicked on this input")))
}
