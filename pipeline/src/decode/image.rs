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
//! | `jpeg`, `jpg`, `image/jpeg` | JPEG (jpeg-decoder, libjpeg-exact): YCbCr and grey → RGB; a grey JPEG → `Mono8` for [`Target::Mono`]; CMYK is an error |
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

use std::fmt;
use std::io::Cursor;
use std::panic::{AssertUnwindSafe, catch_unwind};

use superflow_schemas::Stamp;
use superflow_schemas::sensor::{Image, PixelFormat, SensorError};

use super::{DecodeError, foxglove, ros2};

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

/// A compression codec the decoder supports.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Hash)]
pub enum Codec {
    /// JPEG (JFIF/EXIF), baseline or progressive.
    Jpeg,
    /// PNG.
    Png,
}

impl fmt::Display for Codec {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        f.write_str(match self {
            Codec::Jpeg => "JPEG",
            Codec::Png => "PNG",
        })
    }
}

/// An image message that cannot be decoded. Every variant names the message's frame id
/// and (where the message has one) its stamp.
#[derive(Debug, thiserror::Error)]
pub enum ImageError {
    /// An image_transport `compressedDepth` payload (a quantized depth map).
    #[error(
        "image `{frame_id}` at {stamp}: format `{format}` is a compressedDepth depth map, not a camera image; not supported"
    )]
    CompressedDepth {
        /// Frame of the image.
        frame_id: String,
        /// Its stamp.
        stamp: Stamp,
        /// The `format` string.
        format: String,
    },
    /// A compression format other than JPEG and PNG (WebP, AVIF, QOI, ...), and data
    /// that does not look like JPEG or PNG either.
    #[error(
        "image `{frame_id}` at {stamp}: compressed format `{format}` is not supported (only JPEG and PNG are)"
    )]
    UnsupportedFormat {
        /// Frame of the image.
        frame_id: String,
        /// Its stamp.
        stamp: Stamp,
        /// The `format` string.
        format: String,
    },
    /// No format string and no recognizable magic bytes.
    #[error(
        "image `{frame_id}` at {stamp}: cannot tell the compression: format `{format}` names none and the data ({len} bytes, starting [{head}]) is neither JPEG (FF D8) nor PNG (89 50 4E 47)"
    )]
    UnknownFormat {
        /// Frame of the image.
        frame_id: String,
        /// Its stamp.
        stamp: Stamp,
        /// The `format` string.
        format: String,
        /// Length of the data.
        len: usize,
        /// The first bytes of the data, in hex.
        head: String,
    },
    /// The codec rejected the data (corrupt or truncated).
    #[error("image `{frame_id}` at {stamp}: invalid {codec} data: {reason}")]
    Corrupt {
        /// Frame of the image.
        frame_id: String,
        /// Its stamp.
        stamp: Stamp,
        /// The codec that failed.
        codec: Codec,
        /// What the codec reported.
        reason: String,
    },
    /// The magic bytes and the format string name different codecs, and neither decodes.
    #[error(
        "image `{frame_id}` at {stamp}: the data starts like {sniffed} but format is `{format}`, and neither decodes: as {sniffed}: {sniffed_reason}; as `{format}`: {declared_reason}"
    )]
    FormatMismatch {
        /// Frame of the image.
        frame_id: String,
        /// Its stamp.
        stamp: Stamp,
        /// The `format` string.
        format: String,
        /// The codec the magic bytes name.
        sniffed: Codec,
        /// Why decoding with that codec failed.
        sniffed_reason: String,
        /// Why decoding as the format string says failed (or why it was not tried).
        declared_reason: String,
    },
    /// A raw pixel encoding the pipeline does not decode.
    #[error("image `{frame_id}` at {stamp}: unsupported encoding `{encoding}` ({reason})")]
    UnsupportedEncoding {
        /// Frame of the image.
        frame_id: String,
        /// Its stamp.
        stamp: Stamp,
        /// The `encoding` string.
        encoding: String,
        /// Why it is not supported.
        reason: &'static str,
    },
    /// [`Target::Mono`] asked of data whose values cannot be kept exactly.
    #[error(
        "image `{frame_id}` at {stamp}: cannot decode {found} as Mono8 with its values kept (class ids / grey levels); decode it with Target::Rgb"
    )]
    NotMono {
        /// Frame of the image.
        frame_id: String,
        /// Its stamp.
        stamp: Stamp,
        /// What the data is (`raw rgb8`, `a colour JPEG`, `a 16-bit grey PNG`, ...).
        found: String,
    },
    /// Width or height is zero.
    #[error("image `{frame_id}` at {stamp}: empty image ({width}x{height})")]
    ZeroSize {
        /// Frame of the image.
        frame_id: String,
        /// Its stamp.
        stamp: Stamp,
        /// Width in pixels.
        width: u64,
        /// Height in pixels.
        height: u64,
    },
    /// The decoded image would exceed [`MAX_IMAGE_BYTES`].
    #[error(
        "image `{frame_id}` at {stamp}: {width}x{height} needs {bytes} bytes decoded, more than the {limit}-byte limit"
    )]
    TooLarge {
        /// Frame of the image.
        frame_id: String,
        /// Its stamp.
        stamp: Stamp,
        /// Width in pixels.
        width: u64,
        /// Height in pixels.
        height: u64,
        /// Bytes the decoded image (or the decoder's buffer) would take.
        bytes: u64,
        /// [`MAX_IMAGE_BYTES`].
        limit: u64,
    },
    /// A raw image whose `step` is shorter than a row of pixels.
    #[error(
        "image `{frame_id}` at {stamp}: step {step} is shorter than a row of {width} `{encoding}` pixels ({row_bytes} bytes)"
    )]
    StepTooSmall {
        /// Frame of the image.
        frame_id: String,
        /// Its stamp.
        stamp: Stamp,
        /// The `encoding` string.
        encoding: String,
        /// Width in pixels.
        width: u32,
        /// The `step` field.
        step: u32,
        /// `width × bytes per pixel`.
        row_bytes: u64,
    },
    /// A raw image whose `data` does not match `step × height`.
    #[error(
        "image `{frame_id}` at {stamp}: {got} bytes of data for {width}x{height} `{encoding}` with step {step} (expected {expected_min} to {expected_max})"
    )]
    DataLength {
        /// Frame of the image.
        frame_id: String,
        /// Its stamp.
        stamp: Stamp,
        /// The `encoding` string.
        encoding: String,
        /// Width in pixels.
        width: u32,
        /// Height in pixels.
        height: u32,
        /// Row length in bytes used for the check (`width × bytes per pixel` when the
        /// message's `step` is 0).
        step: u64,
        /// Bytes present.
        got: usize,
        /// Fewest bytes accepted (the last row without padding).
        expected_min: u64,
        /// Most bytes accepted (`step × height`).
        expected_max: u64,
    },
    /// A Foxglove message without a usable `timestamp`.
    #[error("image `{frame_id}`: {source}")]
    Timestamp {
        /// Frame of the image.
        frame_id: String,
        /// The decoder's complaint.
        source: DecodeError,
    },
    /// The sensor model rejected the decoded image (an internal inconsistency).
    #[error("image `{frame_id}` at {stamp}: {source}")]
    Sensor {
        /// Frame of the image.
        frame_id: String,
        /// Its stamp.
        stamp: Stamp,
        /// The sensor model's complaint.
        source: SensorError,
    },
}

// ---------------------------------------------------------------------------------------
// Public entry points
// ---------------------------------------------------------------------------------------

/// Decodes a ROS 2 `sensor_msgs/msg/CompressedImage` (JPEG or PNG, see the module
/// documentation for the accepted `format` strings).
pub fn decode_ros2_compressed(
    msg: &ros2::CompressedImage,
    target: Target,
) -> Result<Image, ImageError> {
    let ctx = Ctx {
        frame_id: &msg.header.frame_id,
        stamp: msg.header.stamp.stamp(),
    };
    decode_compressed(&msg.data, &msg.format, target, ctx)
}

/// Decodes a ROS 2 `sensor_msgs/msg/Image` (8-bit RGB/BGR/RGBA/BGRA/mono encodings,
/// with row padding; see the module documentation).
pub fn decode_ros2_raw(msg: &ros2::Image, target: Target) -> Result<Image, ImageError> {
    let ctx = Ctx {
        frame_id: &msg.header.frame_id,
        stamp: msg.header.stamp.stamp(),
    };
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
    let stamp = foxglove_stamp("foxglove.CompressedImage", &msg.frame_id, msg)?;
    let ctx = Ctx {
        frame_id: &msg.frame_id,
        stamp,
    };
    decode_compressed(&msg.data, &msg.format, target, ctx)
}

/// Decodes a `foxglove.RawImage` (the encodings of [`decode_ros2_raw`]).
pub fn decode_foxglove_raw(msg: &foxglove::RawImage, target: Target) -> Result<Image, ImageError> {
    let stamp = foxglove_stamp("foxglove.RawImage", &msg.frame_id, msg)?;
    let ctx = Ctx {
        frame_id: &msg.frame_id,
        stamp,
    };
    let raw = Raw {
        encoding: &msg.encoding,
        width: msg.width,
        height: msg.height,
        step: msg.step,
        data: &msg.data,
    };
    decode_raw(&raw, target, ctx)
}

/// A Foxglove message's timestamp.
trait HasTimestamp {
    fn timestamp(&self) -> Option<&foxglove::Timestamp>;
}

impl HasTimestamp for foxglove::CompressedImage {
    fn timestamp(&self) -> Option<&foxglove::Timestamp> {
        self.timestamp.as_ref()
    }
}

impl HasTimestamp for foxglove::RawImage {
    fn timestamp(&self) -> Option<&foxglove::Timestamp> {
        self.timestamp.as_ref()
    }
}

fn foxglove_stamp(
    schema: &'static str,
    frame_id: &str,
    msg: &impl HasTimestamp,
) -> Result<Stamp, ImageError> {
    foxglove::stamp(schema, msg.timestamp()).map_err(|source| ImageError::Timestamp {
        frame_id: frame_id.to_string(),
        source,
    })
}

// ---------------------------------------------------------------------------------------
// Shared helpers
// ---------------------------------------------------------------------------------------

/// Frame and stamp of the message being decoded, for error messages.
#[derive(Debug, Clone, Copy)]
struct Ctx<'a> {
    frame_id: &'a str,
    stamp: Stamp,
}

impl Ctx<'_> {
    fn id(&self) -> String {
        self.frame_id.to_string()
    }

    fn corrupt(&self, codec: Codec, reason: impl Into<String>) -> ImageError {
        ImageError::Corrupt {
            frame_id: self.id(),
            stamp: self.stamp,
            codec,
            reason: reason.into(),
        }
    }

    fn not_mono(&self, found: impl Into<String>) -> ImageError {
        ImageError::NotMono {
            frame_id: self.id(),
            stamp: self.stamp,
            found: found.into(),
        }
    }

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
    width: u32,
    height: u32,
    format: PixelFormat,
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

// ---------------------------------------------------------------------------------------
// Compressed images
// ---------------------------------------------------------------------------------------

/// The codec a format string names.
#[derive(Debug, Clone, PartialEq, Eq)]
enum Declared {
    /// Empty: only the magic bytes tell.
    Unspecified,
    /// JPEG or PNG.
    Codec(Codec),
    /// Something else (`webp`, `avif`, `qoi`, ...).
    Other,
}

/// What a `format` string says.
#[derive(Debug, Clone, PartialEq, Eq)]
struct FormatHint {
    declared: Declared,
    /// An image_transport target starting with `rgb`: the file is channel-swapped.
    swap_red_blue: bool,
    /// An image_transport `compressedDepth` payload.
    depth: bool,
}

impl FormatHint {
    /// Parses `"jpeg"`, `"png"`, `"<src>; <codec> compressed <target>"`,
    /// `"<src>; compressedDepth ..."`, ... (case-insensitive).
    fn parse(format: &str) -> Self {
        let lower = format.trim().to_ascii_lowercase();
        let depth = lower.contains("compresseddepth");
        let (codec, target) = match lower.split_once(';') {
            Some((_source_encoding, rest)) => {
                let mut words = rest.split_whitespace();
                let codec = words.next().unwrap_or("");
                let target = match words.next() {
                    Some("compressed") => words.next().unwrap_or(""),
                    _ => "",
                };
                (codec, target)
            }
            None => (lower.as_str(), ""),
        };
        let declared = match codec {
            "" => Declared::Unspecified,
            "jpeg" | "jpg" | "image/jpeg" => Declared::Codec(Codec::Jpeg),
            "png" | "image/png" => Declared::Codec(Codec::Png),
            _ => Declared::Other,
        };
        Self {
            declared,
            swap_red_blue: target.starts_with("rgb"),
            depth,
        }
    }
}

/// The codec the magic bytes name.
fn sniff(data: &[u8]) -> Option<Codec> {
    if data.starts_with(&[0xFF, 0xD8]) {
        Some(Codec::Jpeg)
    } else if data.starts_with(&[0x89, b'P', b'N', b'G']) {
        Some(Codec::Png)
    } else {
        None
    }
}

/// Decodes JPEG or PNG bytes described by `format` (see the module documentation).
fn decode_compressed(
    data: &[u8],
    format: &str,
    target: Target,
    ctx: Ctx<'_>,
) -> Result<Image, ImageError> {
    let hint = FormatHint::parse(format);
    if hint.depth {
        return Err(ImageError::CompressedDepth {
            frame_id: ctx.id(),
            stamp: ctx.stamp,
            format: format.to_string(),
        });
    }
    let mut decoded = match (sniff(data), &hint.declared) {
        (Some(sniffed), declared) => match decode_codec(sniffed, data, target, ctx) {
            Ok(decoded) => decoded,
            Err(ImageError::Corrupt {
                reason: sniffed_reason,
                ..
            }) if *declared != Declared::Codec(sniffed) && *declared != Declared::Unspecified => {
                let declared_result = match declared {
                    Declared::Codec(codec) => decode_codec(*codec, data, target, ctx),
                    _ => Err(ImageError::UnsupportedFormat {
                        frame_id: ctx.id(),
                        stamp: ctx.stamp,
                        format: format.to_string(),
                    }),
                };
                match declared_result {
                    Ok(decoded) => decoded,
                    Err(declared_error) => {
                        return Err(ImageError::FormatMismatch {
                            frame_id: ctx.id(),
                            stamp: ctx.stamp,
                            format: format.to_string(),
                            sniffed,
                            sniffed_reason,
                            declared_reason: match declared_error {
                                ImageError::Corrupt { reason, .. } => reason,
                                ImageError::UnsupportedFormat { .. } => {
                                    "not a supported codec".to_string()
                                }
                                other => other.to_string(),
                            },
                        });
                    }
                }
            }
            Err(e) => return Err(e),
        },
        (None, Declared::Codec(codec)) => decode_codec(*codec, data, target, ctx)?,
        (None, Declared::Other) => {
            return Err(ImageError::UnsupportedFormat {
                frame_id: ctx.id(),
                stamp: ctx.stamp,
                format: format.to_string(),
            });
        }
        (None, Declared::Unspecified) => {
            let head: Vec<String> = data.iter().take(8).map(|b| format!("{b:02X}")).collect();
            return Err(ImageError::UnknownFormat {
                frame_id: ctx.id(),
                stamp: ctx.stamp,
                format: format.to_string(),
                len: data.len(),
                head: head.join(" "),
            });
        }
    };
    if hint.swap_red_blue && decoded.format == PixelFormat::Rgb8 {
        for px in decoded.data.chunks_exact_mut(3) {
            px.swap(0, 2);
        }
    }
    ctx.image(decoded)
}

fn decode_codec(
    codec: Codec,
    data: &[u8],
    target: Target,
    ctx: Ctx<'_>,
) -> Result<Decoded, ImageError> {
    guarded(codec, ctx, || match codec {
        Codec::Jpeg => decode_jpeg(data, target, ctx),
        Codec::Png => decode_png(data, target, ctx),
    })
}

/// Whether an end-of-image marker (`FF D9`) follows the first start-of-scan marker
/// (`FF DA`). Inside entropy-coded data every `FF` byte is stuffed (`FF 00`) or a restart
/// marker, so a JPEG cut anywhere after its headers has no `FF D9` after the scan start.
fn jpeg_has_end(data: &[u8]) -> bool {
    let sos = data.windows(2).position(|w| w == [0xFF, 0xDA]);
    let eoi = data.windows(2).rposition(|w| w == [0xFF, 0xD9]);
    matches!((sos, eoi), (Some(sos), Some(eoi)) if eoi > sos)
}

fn decode_jpeg(data: &[u8], target: Target, ctx: Ctx<'_>) -> Result<Decoded, ImageError> {
    use jpeg_decoder::PixelFormat as Jpeg;
    let corrupt = |reason: String| ctx.corrupt(Codec::Jpeg, reason);
    let mut decoder = jpeg_decoder::Decoder::new(data);
    decoder.read_info().map_err(|e| corrupt(e.to_string()))?;
    let info = decoder
        .info()
        .ok_or_else(|| corrupt("no frame header".into()))?;
    let (width, height) = (u64::from(info.width), u64::from(info.height));
    let format = match (target, info.pixel_format) {
        (Target::Rgb, Jpeg::RGB24 | Jpeg::L8 | Jpeg::L16) => PixelFormat::Rgb8,
        (Target::Mono, Jpeg::L8) => PixelFormat::Mono8,
        (Target::Mono, Jpeg::L16) => {
            return Err(ctx.not_mono("a 16-bit grey JPEG (the ids would lose their low byte)"));
        }
        (Target::Mono, other) => return Err(ctx.not_mono(format!("a colour JPEG ({other:?})"))),
        (Target::Rgb, Jpeg::CMYK32) => {
            return Err(corrupt(
                "CMYK JPEGs are not camera images; not supported".into(),
            ));
        }
    };
    let len = ctx.checked_size(width, height, format.channels() as u64)?;
    if !jpeg_has_end(data) {
        return Err(corrupt(
            "truncated: no end-of-image marker after the scan data".into(),
        ));
    }
    decoder.set_max_decoding_buffer_size(usize::try_from(MAX_IMAGE_BYTES).unwrap_or(usize::MAX));
    let samples = decoder.decode().map_err(|e| corrupt(e.to_string()))?;
    let pixels: Vec<u8> = match (info.pixel_format, format) {
        (Jpeg::L8, PixelFormat::Rgb8) => samples.iter().flat_map(|g| [*g; 3]).collect(),
        // 16-bit grey arrives big-endian; keep the high byte for a colour image.
        (Jpeg::L16, _) => samples.chunks_exact(2).flat_map(|g| [g[0]; 3]).collect(),
        _ => samples,
    };
    if pixels.len() != len {
        return Err(corrupt(format!(
            "decoder output of {} bytes for {width}x{height} {format:?}",
            pixels.len()
        )));
    }
    let dim = |v: u64| u32::try_from(v).map_err(|_| corrupt(format!("dimension {v}")));
    Ok(Decoded {
        width: dim(width)?,
        height: dim(height)?,
        format,
        data: pixels,
    })
}

fn decode_png(data: &[u8], target: Target, ctx: Ctx<'_>) -> Result<Decoded, ImageError> {
    use png::{BitDepth, ColorType};

    let corrupt = |reason: String| ctx.corrupt(Codec::Png, reason);
    let limits = png::Limits {
        bytes: usize::try_from(MAX_IMAGE_BYTES).unwrap_or(usize::MAX),
    };
    let mut decoder = png::Decoder::new_with_limits(Cursor::new(data), limits);
    // Raw samples: bit depths, palettes and alpha are handled below, so that class ids
    // in 1/2/4-bit grey or palette PNGs are not rescaled.
    decoder.set_transformations(png::Transformations::IDENTITY);
    let png_error = |e: png::DecodingError| match e {
        png::DecodingError::LimitsExceeded => corrupt(format!(
            "the decoder needs more than {MAX_IMAGE_BYTES} bytes of buffers"
        )),
        e => corrupt(e.to_string()),
    };
    // The header alone first: the size checks come before the decoder allocates rows.
    let header = decoder.read_header_info().map_err(png_error)?;
    let (width, height) = (header.width, header.height);
    let (color, depth) = (header.color_type, header.bit_depth);
    let format = match (target, color) {
        (Target::Rgb, _) => PixelFormat::Rgb8,
        (Target::Mono, ColorType::Grayscale | ColorType::GrayscaleAlpha)
            if depth == BitDepth::Sixteen =>
        {
            return Err(ctx.not_mono("a 16-bit grey PNG (the ids would lose their low byte)"));
        }
        (Target::Mono, ColorType::Grayscale | ColorType::GrayscaleAlpha | ColorType::Indexed) => {
            PixelFormat::Mono8
        }
        (Target::Mono, ColorType::Rgb | ColorType::Rgba) => {
            return Err(ctx.not_mono(format!("a colour PNG ({color:?}, {} bit)", depth as u8)));
        }
    };
    let (w, h) = (u64::from(width), u64::from(height));
    let out_len = ctx.checked_size(w, h, format.channels() as u64)?;
    // The decoder's sample buffer: whole bytes per row, up to 8 bytes per pixel.
    let bits_per_row = w * color.samples() as u64 * u64::from(depth as u8);
    let raw_bytes = bits_per_row.div_ceil(8) * h;
    if raw_bytes > MAX_IMAGE_BYTES {
        return Err(ctx.too_large(w, h, raw_bytes));
    }
    let mut reader = decoder.read_info().map_err(png_error)?;
    let palette: Vec<u8> = reader
        .info()
        .palette
        .as_deref()
        .map(<[u8]>::to_vec)
        .unwrap_or_default();
    let raw_len = reader
        .output_buffer_size()
        .ok_or_else(|| ctx.too_large(w, h, raw_bytes))?;
    if raw_len as u64 > MAX_IMAGE_BYTES {
        return Err(ctx.too_large(w, h, raw_len as u64));
    }
    let line = reader
        .output_line_size(width)
        .ok_or_else(|| ctx.too_large(w, h, u64::MAX))?;
    let mut raw = vec![0u8; raw_len];
    reader.next_frame(&mut raw).map_err(png_error)?;

    let (width, height) = (width as usize, height as usize);
    let bits = depth as u8;
    let spp = color.samples();
    let mut out = Vec::with_capacity(out_len);
    let mut samples: Vec<u16> = Vec::with_capacity(width * spp);
    for row in raw.chunks(line).take(height) {
        match (color, bits, format) {
            // Fast paths for the common layouts.
            (ColorType::Rgb, 8, PixelFormat::Rgb8)
            | (ColorType::Grayscale, 8, PixelFormat::Mono8) => {
                let row = row
                    .get(..width * spp)
                    .ok_or_else(|| corrupt("short row".into()))?;
                out.extend_from_slice(row);
                continue;
            }
            _ => {}
        }
        unpack_samples(row, bits, width * spp, &mut samples);
        if samples.len() != width * spp {
            return Err(corrupt("short row".into()));
        }
        match color {
            ColorType::Grayscale | ColorType::GrayscaleAlpha => {
                for px in samples.chunks_exact(spp) {
                    match format {
                        // Mono8 only from depths <= 8: the value fits and is kept.
                        PixelFormat::Mono8 => out.push(px[0] as u8),
                        PixelFormat::Rgb8 => {
                            let g = to_u8(px[0], bits);
                            out.extend_from_slice(&[g, g, g]);
                        }
                    }
                }
            }
            ColorType::Rgb | ColorType::Rgba => {
                for px in samples.chunks_exact(spp) {
                    out.extend_from_slice(&[
                        to_u8(px[0], bits),
                        to_u8(px[1], bits),
                        to_u8(px[2], bits),
                    ]);
                }
            }
            ColorType::Indexed => {
                for &index in &samples {
                    match format {
                        PixelFormat::Mono8 => out.push(index as u8),
                        PixelFormat::Rgb8 => {
                            let at = usize::from(index) * 3;
                            let rgb = palette.get(at..at + 3).ok_or_else(|| {
                                corrupt(format!(
                                    "palette index {index} outside the {}-entry palette",
                                    palette.len() / 3
                                ))
                            })?;
                            out.extend_from_slice(rgb);
                        }
                    }
                }
            }
        }
    }
    if out.len() != out_len {
        return Err(corrupt(format!(
            "{} bytes decoded for {width}x{height} {format:?}",
            out.len()
        )));
    }
    Ok(Decoded {
        width: width as u32,
        height: height as u32,
        format,
        data: out,
    })
}

/// The first `count` samples of a PNG row of `bits`-bit samples (big-endian for 16 bits,
/// most significant bits first below 8), as written by the decoder without transforms.
fn unpack_samples(row: &[u8], bits: u8, count: usize, out: &mut Vec<u16>) {
    out.clear();
    match bits {
        16 => out.extend(
            row.chunks_exact(2)
                .take(count)
                .map(|b| u16::from_be_bytes([b[0], b[1]])),
        ),
        8 => out.extend(row.iter().take(count).map(|&b| u16::from(b))),
        1 | 2 | 4 => {
            let per_byte = 8 / bits;
            let mask = (1u8 << bits) - 1;
            out.extend(
                row.iter()
                    .flat_map(|&byte| {
                        (0..per_byte).map(move |k| u16::from((byte >> (8 - bits * (k + 1))) & mask))
                    })
                    .take(count),
            );
        }
        _ => {}
    }
}

/// A `bits`-bit sample as 8 bits: the high byte of 16-bit samples, low depths scaled to
/// `0..=255`.
fn to_u8(value: u16, bits: u8) -> u8 {
    match bits {
        16 => (value >> 8) as u8,
        8 => value as u8,
        _ => {
            let max = (1u32 << bits) - 1;
            (u32::from(value) * 255 / max.max(1)) as u8
        }
    }
}

// ---------------------------------------------------------------------------------------
// Raw images
// ---------------------------------------------------------------------------------------

/// The fields of a raw image message.
#[derive(Debug, Clone, Copy)]
struct Raw<'a> {
    encoding: &'a str,
    width: u32,
    height: u32,
    step: u32,
    data: &'a [u8],
}

/// Pixel layout of a supported raw encoding.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
enum RawLayout {
    Mono8,
    Rgb8,
    Bgr8,
    Rgba8,
    Bgra8,
}

impl RawLayout {
    /// The layout of `encoding`, or why it is not supported.
    fn parse(encoding: &str) -> Result<Self, &'static str> {
        let e = encoding.trim().to_ascii_lowercase();
        match e.as_str() {
            "mono8" | "8uc1" => Ok(Self::Mono8),
            "rgb8" => Ok(Self::Rgb8),
            "bgr8" | "8uc3" => Ok(Self::Bgr8),
            "rgba8" => Ok(Self::Rgba8),
            "bgra8" | "8uc4" => Ok(Self::Bgra8),
            "" => Err("no encoding given"),
            _ if e.starts_with("bayer") => {
                Err("Bayer mosaic; demosaic upstream or record the colour topic")
            }
            "mono16" | "rgb16" | "bgr16" | "rgba16" | "bgra16" => {
                Err("16 bits per channel; only 8-bit encodings are decoded")
            }
            "yuv422" | "yuv422_yuy2" | "uyvy" | "yuyv" | "nv12" | "nv21" | "i420" | "yuv420" => {
                Err("YUV data; only RGB, BGR and mono encodings are decoded")
            }
            _ if e.starts_with("16") || e.starts_with("32") || e.starts_with("64") => Err(
                "more than 8 bits per channel (depth or float data); only 8-bit encodings are decoded",
            ),
            _ if e.starts_with("8sc") => Err("signed 8-bit data"),
            _ if e.starts_with("8uc") => Err("8-bit data with 2 or more than 4 channels"),
            _ => Err("unknown encoding"),
        }
    }

    fn channels(self) -> usize {
        match self {
            Self::Mono8 => 1,
            Self::Rgb8 | Self::Bgr8 => 3,
            Self::Rgba8 | Self::Bgra8 => 4,
        }
    }
}

/// Decodes raw pixels (see the module documentation for encodings and `step`).
fn decode_raw(raw: &Raw<'_>, target: Target, ctx: Ctx<'_>) -> Result<Image, ImageError> {
    let layout =
        RawLayout::parse(raw.encoding).map_err(|reason| ImageError::UnsupportedEncoding {
            frame_id: ctx.id(),
            stamp: ctx.stamp,
            encoding: raw.encoding.to_string(),
            reason,
        })?;
    let format = match (target, layout) {
        (Target::Rgb, _) => PixelFormat::Rgb8,
        (Target::Mono, RawLayout::Mono8) => PixelFormat::Mono8,
        (Target::Mono, _) => return Err(ctx.not_mono(format!("raw `{}` data", raw.encoding))),
    };
    let (w, h) = (u64::from(raw.width), u64::from(raw.height));
    let out_len = ctx.checked_size(w, h, format.channels() as u64)?;
    let bpp = layout.channels();
    let row_bytes = w * bpp as u64;
    let step = if raw.step == 0 {
        row_bytes
    } else {
        u64::from(raw.step)
    };
    if step < row_bytes {
        return Err(ImageError::StepTooSmall {
            frame_id: ctx.id(),
            stamp: ctx.stamp,
            encoding: raw.encoding.to_string(),
            width: raw.width,
            step: raw.step,
            row_bytes,
        });
    }
    // No overflow: step < 2^35 and h < 2^32.
    let expected_min = step * (h - 1) + row_bytes;
    let expected_max = step * h;
    let got = raw.data.len();
    if (got as u64) < expected_min || got as u64 > expected_max {
        return Err(ImageError::DataLength {
            frame_id: ctx.id(),
            stamp: ctx.stamp,
            encoding: raw.encoding.to_string(),
            width: raw.width,
            height: raw.height,
            step,
            got,
            expected_min,
            expected_max,
        });
    }
    // Both fit in usize: row_bytes <= out_len·4/3 and step is at most the data length
    // unless there is a single row.
    let row_bytes = row_bytes as usize;
    let step = usize::try_from(step).unwrap_or(usize::MAX);
    let mut out = Vec::with_capacity(out_len);
    for row in raw.data.chunks(step).take(raw.height as usize) {
        let Some(row) = row.get(..row_bytes) else {
            break;
        };
        match (layout, format) {
            (RawLayout::Mono8, PixelFormat::Mono8) | (RawLayout::Rgb8, PixelFormat::Rgb8) => {
                out.extend_from_slice(row);
            }
            (RawLayout::Mono8, _) => {
                for &g in row {
                    out.extend_from_slice(&[g, g, g]);
                }
            }
            (RawLayout::Bgr8, _) => {
                for px in row.chunks_exact(3) {
                    out.extend_from_slice(&[px[2], px[1], px[0]]);
                }
            }
            (RawLayout::Rgba8, _) => {
                for px in row.chunks_exact(4) {
                    out.extend_from_slice(&px[..3]);
                }
            }
            (RawLayout::Bgra8, _) => {
                for px in row.chunks_exact(4) {
                    out.extend_from_slice(&[px[2], px[1], px[0]]);
                }
            }
            (RawLayout::Rgb8, PixelFormat::Mono8) => {
                return Err(ctx.not_mono(format!("raw `{}` data", raw.encoding)));
            }
        }
    }
    ctx.image(Decoded {
        width: raw.width,
        height: raw.height,
        format,
        data: out,
    })
}

#[cfg(test)]
mod tests {
    use super::foxglove::Timestamp;
    use super::*;
    use crate::decode::ros2::{Header, Ros2Time};

    const FRAME: &str = "cam_front_optical";
    const SEC: i32 = 1_700_000_000;
    const NSEC: u32 = 42;

    fn stamp() -> Stamp {
        Stamp::from_sec_nanosec(i64::from(SEC), NSEC)
    }

    fn header() -> Header {
        Header {
            stamp: Ros2Time {
                sec: SEC,
                nanosec: NSEC,
            },
            frame_id: FRAME.into(),
        }
    }

    fn ros2_compressed(format: &str, data: Vec<u8>) -> ros2::CompressedImage {
        ros2::CompressedImage {
            header: header(),
            format: format.into(),
            data,
        }
    }

    fn ros2_raw(encoding: &str, width: u32, height: u32, step: u32, data: Vec<u8>) -> ros2::Image {
        ros2::Image {
            header: header(),
            height,
            width,
            encoding: encoding.into(),
            is_bigendian: 0,
            step,
            data,
        }
    }

    fn fox_compressed(format: &str, data: Vec<u8>) -> foxglove::CompressedImage {
        foxglove::CompressedImage {
            timestamp: Some(Timestamp::new(SEC as u32, NSEC)),
            frame_id: FRAME.into(),
            data: data.into(),
            format: format.into(),
        }
    }

    fn fox_raw(
        encoding: &str,
        width: u32,
        height: u32,
        step: u32,
        data: Vec<u8>,
    ) -> foxglove::RawImage {
        foxglove::RawImage {
            timestamp: Some(Timestamp::new(SEC as u32, NSEC)),
            frame_id: FRAME.into(),
            width,
            height,
            encoding: encoding.into(),
            step,
            data: data.into(),
        }
    }

    /// Asserts that the error's message names the frame and the stamp, and returns it.
    fn named(err: ImageError) -> ImageError {
        let msg = err.to_string();
        assert!(msg.contains(FRAME), "no frame id in: {msg}");
        assert!(msg.contains(&stamp().to_string()), "no stamp in: {msg}");
        err
    }

    /// A smooth RGB test image (gradients, no hard edges).
    fn gradient(width: u32, height: u32) -> Vec<u8> {
        let mut v = Vec::new();
        for y in 0..height {
            for x in 0..width {
                v.push((40 + x * 160 / width) as u8);
                v.push((30 + y * 180 / height) as u8);
                v.push((200 - (x + y) * 100 / (width + height)) as u8);
            }
        }
        v
    }

    fn solid(width: u32, height: u32, px: [u8; 3]) -> Vec<u8> {
        px.repeat((width * height) as usize)
    }

    /// Camera JPEGs are chroma-subsampled (4:2:0) with optimized Huffman tables, as the
    /// sample drives' are; zune-jpeg 0.5.15 decoded those to green, which this catches.
    #[test]
    fn subsampled_camera_jpegs_keep_their_colours() {
        let (w, h) = (64usize, 48usize);
        let mut rgb = Vec::with_capacity(w * h * 3);
        for y in 0..h {
            for x in 0..w {
                let (r, g, b) = if x < w / 2 {
                    (140u8, 140u8, 145u8)
                } else {
                    (200, 40, 30)
                };
                let _ = y;
                rgb.extend_from_slice(&[r, g, b]);
            }
        }
        let mut bytes = Vec::new();
        let mut encoder = jpeg_encoder::Encoder::new(&mut bytes, 80);
        encoder.set_optimized_huffman_tables(true);
        encoder.set_sampling_factor(jpeg_encoder::SamplingFactor::F_2_2);
        encoder
            .encode(&rgb, w as u16, h as u16, jpeg_encoder::ColorType::Rgb)
            .unwrap();
        let msg = foxglove::CompressedImage {
            timestamp: Some(Timestamp::new(1, 0)),
            frame_id: "cam".into(),
            data: bytes.into(),
            format: "jpeg".into(),
        };
        let image = decode_foxglove_compressed(&msg, Target::Rgb).unwrap();
        for (x, expected) in [(8u32, [140i32, 140, 145]), (56, [200, 40, 30])] {
            let got = image.pixel(x, 20).unwrap();
            for c in 0..3 {
                assert!(
                    (i32::from(got[c]) - expected[c]).abs() <= 6,
                    "pixel {x}: {got:?} vs {expected:?}"
                );
            }
        }
    }

    fn jpeg(data: &[u8], width: u16, height: u16, color: jpeg_encoder::ColorType) -> Vec<u8> {
        let mut out = Vec::new();
        let mut encoder = jpeg_encoder::Encoder::new(&mut out, 100);
        encoder.set_sampling_factor(jpeg_encoder::SamplingFactor::F_1_1);
        encoder.encode(data, width, height, color).unwrap();
        out
    }

    fn png_bytes(
        data: &[u8],
        width: u32,
        height: u32,
        color: png::ColorType,
        depth: png::BitDepth,
        palette: Option<Vec<u8>>,
    ) -> Vec<u8> {
        let mut out = Vec::new();
        {
            let mut encoder = png::Encoder::new(&mut out, width, height);
            encoder.set_color(color);
            encoder.set_depth(depth);
            if let Some(palette) = palette {
                encoder.set_palette(palette);
            }
            let mut writer = encoder.write_header().unwrap();
            writer.write_image_data(data).unwrap();
            writer.finish().unwrap();
        }
        out
    }

    fn png8(data: &[u8], width: u32, height: u32, color: png::ColorType) -> Vec<u8> {
        png_bytes(data, width, height, color, png::BitDepth::Eight, None)
    }

    fn max_abs_diff(a: &[u8], b: &[u8]) -> u8 {
        assert_eq!(a.len(), b.len());
        a.iter()
            .zip(b)
            .map(|(x, y)| x.abs_diff(*y))
            .max()
            .unwrap_or(0)
    }

    fn assert_red(image: &Image) {
        assert_eq!(image.format, PixelFormat::Rgb8);
        for px in image.data.chunks_exact(3) {
            assert!(
                px[0] >= 245 && px[1] <= 10 && px[2] <= 10,
                "not red: {px:?}"
            );
        }
    }

    const RED: [u8; 3] = [255, 0, 0];
    const BLUE: [u8; 3] = [0, 0, 255];

    // --- JPEG -----------------------------------------------------------------------

    #[test]
    fn jpeg_decodes_to_rgb_within_tolerance() {
        let (w, h) = (64, 48);
        let rgb = gradient(w, h);
        let bytes = jpeg(&rgb, w as u16, h as u16, jpeg_encoder::ColorType::Rgb);
        for format in [
            "jpeg",
            "JPEG",
            "jpg",
            "rgb8; jpeg compressed bgr8",
            "bgr8; jpeg compressed bgr8",
            "",
        ] {
            let image =
                decode_ros2_compressed(&ros2_compressed(format, bytes.clone()), Target::Rgb)
                    .unwrap_or_else(|e| panic!("{format}: {e}"));
            assert_eq!(
                (image.width, image.height, image.format),
                (w, h, PixelFormat::Rgb8)
            );
            assert_eq!(image.frame_id, FRAME);
            assert_eq!(image.stamp, stamp());
            let diff = max_abs_diff(&image.data, &rgb);
            assert!(diff <= 8, "{format}: max abs diff {diff}");
        }
    }

    #[test]
    fn red_stays_red_in_every_jpeg_path() {
        let (w, h) = (16, 16);
        let bytes = jpeg(
            &solid(w, h, RED),
            w as u16,
            h as u16,
            jpeg_encoder::ColorType::Rgb,
        );
        for format in [
            "jpeg",
            "rgb8; jpeg compressed bgr8",
            "bgr8; jpeg compressed bgr8",
            "png",
        ] {
            assert_red(
                &decode_ros2_compressed(&ros2_compressed(format, bytes.clone()), Target::Rgb)
                    .unwrap(),
            );
        }
        assert_red(
            &decode_foxglove_compressed(&fox_compressed("jpeg", bytes.clone()), Target::Rgb)
                .unwrap(),
        );
        // A JPEG written from BGR samples (as cv::imencode does with a bgr8 Mat) is a
        // standard JPEG: still red.
        let bgr = jpeg(
            &solid(w, h, [0, 0, 255]),
            w as u16,
            h as u16,
            jpeg_encoder::ColorType::Bgr,
        );
        assert_red(
            &decode_ros2_compressed(
                &ros2_compressed("rgb8; jpeg compressed bgr8", bgr),
                Target::Rgb,
            )
            .unwrap(),
        );
        // An `rgb8` target: an RGB Mat handed to cv::imencode, stored channel-swapped
        // (the file holds blue where the image is red) and swapped back on decode.
        let swapped = jpeg(
            &solid(w, h, BLUE),
            w as u16,
            h as u16,
            jpeg_encoder::ColorType::Rgb,
        );
        assert_red(
            &decode_ros2_compressed(
                &ros2_compressed("rgb8; jpeg compressed rgb8", swapped),
                Target::Rgb,
            )
            .unwrap(),
        );
    }

    #[test]
    fn grey_jpeg_decodes_to_mono_and_to_replicated_rgb() {
        let (w, h) = (32, 24);
        let grey: Vec<u8> = (0..w * h).map(|i| (50 + (i % w) * 4) as u8).collect();
        let bytes = jpeg(&grey, w as u16, h as u16, jpeg_encoder::ColorType::Luma);
        let mono = decode_ros2_compressed(
            &ros2_compressed("mono8; jpeg compressed ", bytes.clone()),
            Target::Mono,
        )
        .unwrap();
        assert_eq!(mono.format, PixelFormat::Mono8);
        assert!(max_abs_diff(&mono.data, &grey) <= 8);
        let rgb = decode_ros2_compressed(&ros2_compressed("jpeg", bytes), Target::Rgb).unwrap();
        assert_eq!(rgb.format, PixelFormat::Rgb8);
        for (px, g) in rgb.data.chunks_exact(3).zip(&grey) {
            assert!(px[0] == px[1] && px[1] == px[2], "{px:?}");
            assert!(px[0].abs_diff(*g) <= 8);
        }
    }

    #[test]
    fn colour_jpeg_to_mono_is_an_error() {
        let bytes = jpeg(&gradient(8, 8), 8, 8, jpeg_encoder::ColorType::Rgb);
        let err = named(
            decode_ros2_compressed(&ros2_compressed("jpeg", bytes), Target::Mono).unwrap_err(),
        );
        assert!(matches!(err, ImageError::NotMono { .. }), "{err}");
    }

    #[test]
    fn truncated_and_garbage_jpeg_are_errors() {
        let bytes = jpeg(&gradient(64, 64), 64, 64, jpeg_encoder::ColorType::Rgb);
        for len in [2, 20, bytes.len() / 2, bytes.len() - 10, bytes.len() - 2] {
            let err = decode_ros2_compressed(
                &ros2_compressed("jpeg", bytes[..len].to_vec()),
                Target::Rgb,
            )
            .expect_err(&format!("truncated to {len}"));
            let err = named(err);
            assert!(
                matches!(
                    err,
                    ImageError::Corrupt {
                        codec: Codec::Jpeg,
                        ..
                    }
                ),
                "{len}: {err}"
            );
        }
        let mut garbage = vec![0xFF, 0xD8];
        garbage.extend((0..500u32).map(|i| (i.wrapping_mul(2_654_435_761) >> 13) as u8));
        let err = named(
            decode_ros2_compressed(&ros2_compressed("jpeg", garbage), Target::Rgb).unwrap_err(),
        );
        assert!(matches!(err, ImageError::Corrupt { .. }), "{err}");
    }

    #[test]
    fn absurd_jpeg_dimensions_are_rejected_before_allocating() {
        let mut bytes = jpeg(&gradient(8, 8), 8, 8, jpeg_encoder::ColorType::Rgb);
        let sof = bytes.windows(2).position(|w| w == [0xFF, 0xC0]).unwrap();
        // SOF0: FF C0, length (2), precision (1), height (2), width (2).
        bytes[sof + 5..sof + 9].copy_from_slice(&[0xFF, 0xFF, 0xFF, 0xFF]);
        let err = named(
            decode_ros2_compressed(&ros2_compressed("jpeg", bytes), Target::Rgb).unwrap_err(),
        );
        assert!(matches!(err, ImageError::TooLarge { .. }), "{err}");
    }

    // --- PNG ------------------------------------------------------------------------

    #[test]
    fn png_rgb_and_rgba_decode_exactly() {
        let (w, h) = (7, 5);
        let rgb = gradient(w, h);
        let bytes = png8(&rgb, w, h, png::ColorType::Rgb);
        for format in [
            "png",
            "PNG",
            "",
            "jpeg",
            "rgb8; png compressed bgr8",
            "bgr8; png compressed bgr8",
        ] {
            let image =
                decode_ros2_compressed(&ros2_compressed(format, bytes.clone()), Target::Rgb)
                    .unwrap_or_else(|e| panic!("{format}: {e}"));
            assert_eq!((image.width, image.height), (w, h));
            assert_eq!(image.data, rgb, "{format}");
        }
        let rgba: Vec<u8> = rgb
            .chunks_exact(3)
            .flat_map(|p| [p[0], p[1], p[2], 17])
            .collect();
        let bytes = png8(&rgba, w, h, png::ColorType::Rgba);
        for format in ["png", "bgra8; png compressed bgra8"] {
            let image =
                decode_foxglove_compressed(&fox_compressed(format, bytes.clone()), Target::Rgb)
                    .unwrap();
            assert_eq!(image.data, rgb, "{format}");
        }
    }

    #[test]
    fn red_stays_red_in_every_png_path() {
        let (w, h) = (3, 2);
        // image_transport's bgr8/bgra8 targets: cv::imencode writes a standard RGB(A) PNG
        // (OpenCV's PNG encoder calls png_set_bgr), so the file holds red as red.
        let red = png8(&solid(w, h, RED), w, h, png::ColorType::Rgb);
        for format in [
            "png",
            "rgb8; png compressed bgr8",
            "bgr8; png compressed bgr8",
            "8UC3; png compressed bgr8",
            "",
        ] {
            assert_red(
                &decode_ros2_compressed(&ros2_compressed(format, red.clone()), Target::Rgb)
                    .unwrap(),
            );
        }
        let red16: Vec<u8> = RED
            .iter()
            .flat_map(|&c| [c, c])
            .collect::<Vec<u8>>()
            .repeat((w * h) as usize);
        let red16 = png_bytes(
            &red16,
            w,
            h,
            png::ColorType::Rgb,
            png::BitDepth::Sixteen,
            None,
        );
        assert_red(
            &decode_ros2_compressed(
                &ros2_compressed("rgb16; png compressed bgr16", red16),
                Target::Rgb,
            )
            .unwrap(),
        );
        let red_rgba = png8(
            &[255, 0, 0, 255].repeat((w * h) as usize),
            w,
            h,
            png::ColorType::Rgba,
        );
        assert_red(
            &decode_ros2_compressed(
                &ros2_compressed("rgba8; png compressed bgra8", red_rgba),
                Target::Rgb,
            )
            .unwrap(),
        );
        // An `rgb8` target: an RGB Mat through cv::imencode is stored channel-swapped.
        let swapped = png8(&solid(w, h, BLUE), w, h, png::ColorType::Rgb);
        assert_red(
            &decode_ros2_compressed(
                &ros2_compressed("rgb8; png compressed rgb8", swapped),
                Target::Rgb,
            )
            .unwrap(),
        );
        assert_red(&decode_foxglove_compressed(&fox_compressed("png", red), Target::Rgb).unwrap());
    }

    #[test]
    fn mono_png_class_map_is_kept_exact() {
        let (w, h) = (16, 16);
        let ids: Vec<u8> = (0..=255).collect();
        let bytes = png8(&ids, w, h, png::ColorType::Grayscale);
        for format in ["png", "mono8; png compressed ", "8UC1; png compressed "] {
            let image =
                decode_ros2_compressed(&ros2_compressed(format, bytes.clone()), Target::Mono)
                    .unwrap();
            assert_eq!(image.format, PixelFormat::Mono8);
            assert_eq!(image.data, ids);
        }
        let image = decode_foxglove_compressed(&fox_compressed("png", bytes.clone()), Target::Mono)
            .unwrap();
        assert_eq!(image.data, ids);
        // Mono to RGB replicates the channel.
        let rgb = decode_ros2_compressed(&ros2_compressed("png", bytes), Target::Rgb).unwrap();
        let expected: Vec<u8> = ids.iter().flat_map(|&g| [g, g, g]).collect();
        assert_eq!(rgb.data, expected);
        // Grey + alpha: alpha dropped, grey kept.
        let ga: Vec<u8> = ids.iter().flat_map(|&g| [g, 99]).collect();
        let bytes = png8(&ga, w, h, png::ColorType::GrayscaleAlpha);
        let image =
            decode_ros2_compressed(&ros2_compressed("png", bytes.clone()), Target::Mono).unwrap();
        assert_eq!(image.data, ids);
        let rgb = decode_ros2_compressed(&ros2_compressed("png", bytes), Target::Rgb).unwrap();
        assert_eq!(rgb.data, expected);
    }

    #[test]
    fn low_bit_grey_png_keeps_ids_for_mono_and_scales_for_rgb() {
        // 2-bit grey, width 5: rows are packed and padded to a byte.
        let (w, h) = (5, 2);
        let values: [u8; 10] = [0, 1, 2, 3, 1, 3, 2, 1, 0, 2];
        let pack = |row: &[u8]| -> Vec<u8> {
            let mut bytes = vec![0u8; 2];
            for (i, v) in row.iter().enumerate() {
                bytes[i / 4] |= v << (6 - 2 * (i % 4));
            }
            bytes
        };
        let data: Vec<u8> = values.chunks(5).flat_map(pack).collect();
        let bytes = png_bytes(
            &data,
            w,
            h,
            png::ColorType::Grayscale,
            png::BitDepth::Two,
            None,
        );
        let mono =
            decode_ros2_compressed(&ros2_compressed("png", bytes.clone()), Target::Mono).unwrap();
        assert_eq!(mono.data, values);
        let rgb = decode_ros2_compressed(&ros2_compressed("png", bytes), Target::Rgb).unwrap();
        let expected: Vec<u8> = values.iter().flat_map(|&v| [v * 85; 3]).collect();
        assert_eq!(rgb.data, expected);
    }

    #[test]
    fn palette_png_expands_for_rgb_and_gives_indices_for_mono() {
        let (w, h) = (4, 3);
        let palette = vec![0, 0, 0, 255, 0, 0, 0, 255, 0, 10, 20, 30];
        let indices: Vec<u8> = (0..w * h).map(|i| (i % 4) as u8).collect();
        let bytes = png_bytes(
            &indices,
            w,
            h,
            png::ColorType::Indexed,
            png::BitDepth::Eight,
            Some(palette.clone()),
        );
        let rgb =
            decode_ros2_compressed(&ros2_compressed("png", bytes.clone()), Target::Rgb).unwrap();
        let expected: Vec<u8> = indices
            .iter()
            .flat_map(|&i| palette[usize::from(i) * 3..usize::from(i) * 3 + 3].to_vec())
            .collect();
        assert_eq!(rgb.data, expected);
        assert_eq!(rgb.pixel(1, 0), Some(&RED[..]));
        let mono = decode_ros2_compressed(&ros2_compressed("png", bytes), Target::Mono).unwrap();
        assert_eq!(mono.data, indices);
        // 4-bit palette, odd width.
        let (w, h) = (3, 2);
        let indices = [1u8, 2, 3, 0, 1, 2];
        let data: Vec<u8> = indices
            .chunks(3)
            .flat_map(|r| [(r[0] << 4) | r[1], r[2] << 4])
            .collect();
        let bytes = png_bytes(
            &data,
            w,
            h,
            png::ColorType::Indexed,
            png::BitDepth::Four,
            Some(palette.clone()),
        );
        let mono =
            decode_ros2_compressed(&ros2_compressed("png", bytes.clone()), Target::Mono).unwrap();
        assert_eq!(mono.data, indices);
        let rgb = decode_ros2_compressed(&ros2_compressed("png", bytes), Target::Rgb).unwrap();
        assert_eq!(rgb.pixel(0, 0), Some(&RED[..]));
        assert_eq!(rgb.pixel(2, 0), Some(&[10u8, 20, 30][..]));
    }

    #[test]
    fn sixteen_bit_png_converts_for_rgb_and_is_an_error_for_mono() {
        let (w, h) = (4, 2);
        let values: Vec<u16> = vec![0, 255, 256, 0x1234, 0x7FFF, 0x8000, 0xFF00, 0xFFFF];
        let data: Vec<u8> = values.iter().flat_map(|v| v.to_be_bytes()).collect();
        let bytes = png_bytes(
            &data,
            w,
            h,
            png::ColorType::Grayscale,
            png::BitDepth::Sixteen,
            None,
        );
        let rgb =
            decode_ros2_compressed(&ros2_compressed("png", bytes.clone()), Target::Rgb).unwrap();
        let expected: Vec<u8> = values.iter().flat_map(|v| [(v >> 8) as u8; 3]).collect();
        assert_eq!(rgb.data, expected);
        let err = named(
            decode_ros2_compressed(&ros2_compressed("png", bytes), Target::Mono).unwrap_err(),
        );
        assert!(matches!(err, ImageError::NotMono { .. }), "{err}");
        assert!(err.to_string().contains("16-bit"), "{err}");
        // 16-bit RGB.
        let rgb16: Vec<u8> = [0xABCDu16, 0x0102, 0xFFFF]
            .iter()
            .flat_map(|v| v.to_be_bytes())
            .collect();
        let bytes = png_bytes(
            &rgb16,
            1,
            1,
            png::ColorType::Rgb,
            png::BitDepth::Sixteen,
            None,
        );
        let image = decode_foxglove_compressed(&fox_compressed("png", bytes), Target::Rgb).unwrap();
        assert_eq!(image.data, [0xAB, 0x01, 0xFF]);
    }

    #[test]
    fn colour_png_to_mono_is_an_error() {
        let bytes = png8(&gradient(2, 2), 2, 2, png::ColorType::Rgb);
        let err = named(
            decode_ros2_compressed(&ros2_compressed("png", bytes), Target::Mono).unwrap_err(),
        );
        assert!(matches!(err, ImageError::NotMono { .. }), "{err}");
    }

    /// CRC-32 (PNG chunks), for hand-made files.
    fn crc32(bytes: &[u8]) -> u32 {
        let mut crc = 0xFFFF_FFFFu32;
        for &b in bytes {
            crc ^= u32::from(b);
            for _ in 0..8 {
                crc = if crc & 1 == 1 {
                    (crc >> 1) ^ 0xEDB8_8320
                } else {
                    crc >> 1
                };
            }
        }
        !crc
    }

    fn chunk(kind: &[u8; 4], body: &[u8]) -> Vec<u8> {
        let mut out = (body.len() as u32).to_be_bytes().to_vec();
        let mut typed = kind.to_vec();
        typed.extend_from_slice(body);
        out.extend_from_slice(&typed);
        out.extend_from_slice(&crc32(&typed).to_be_bytes());
        out
    }

    #[test]
    fn absurd_png_dimensions_are_rejected_before_allocating() {
        for (width, height) in [(100_000u32, 100_000u32), (0x7FFF_FFFF, 0x7FFF_FFFF)] {
            let mut ihdr = width.to_be_bytes().to_vec();
            ihdr.extend_from_slice(&height.to_be_bytes());
            ihdr.extend_from_slice(&[8, 2, 0, 0, 0]); // 8-bit RGB
            let mut bytes = vec![0x89, b'P', b'N', b'G', 0x0D, 0x0A, 0x1A, 0x0A];
            bytes.extend(chunk(b"IHDR", &ihdr));
            bytes.extend(chunk(
                b"IDAT",
                &[0x78, 0x9C, 0x03, 0x00, 0x00, 0x00, 0x00, 0x01],
            ));
            bytes.extend(chunk(b"IEND", &[]));
            let err = named(
                decode_ros2_compressed(&ros2_compressed("png", bytes), Target::Rgb).unwrap_err(),
            );
            assert!(matches!(err, ImageError::TooLarge { .. }), "{err}");
        }
    }

    #[test]
    fn truncated_png_is_an_error() {
        let bytes = png8(&gradient(32, 32), 32, 32, png::ColorType::Rgb);
        for len in [0, 4, 8, 20, 40, bytes.len() / 2, bytes.len() - 20] {
            let err =
                decode_ros2_compressed(&ros2_compressed("png", bytes[..len].to_vec()), Target::Rgb)
                    .expect_err(&format!("truncated to {len}"));
            named(err);
        }
    }

    // --- Format strings and magic bytes --------------------------------------------

    #[test]
    fn format_strings_parse() {
        let p = FormatHint::parse;
        assert_eq!(p("jpeg").declared, Declared::Codec(Codec::Jpeg));
        assert_eq!(p(" PNG ").declared, Declared::Codec(Codec::Png));
        assert_eq!(p("").declared, Declared::Unspecified);
        assert_eq!(p("webp").declared, Declared::Other);
        let it = p("rgb8; jpeg compressed bgr8");
        assert_eq!(
            (it.declared, it.swap_red_blue, it.depth),
            (Declared::Codec(Codec::Jpeg), false, false)
        );
        let it = p("bgr8; png compressed rgb8");
        assert_eq!(
            (it.declared, it.swap_red_blue),
            (Declared::Codec(Codec::Png), true)
        );
        let it = p("mono8; png compressed ");
        assert_eq!(
            (it.declared, it.swap_red_blue),
            (Declared::Codec(Codec::Png), false)
        );
        assert!(p("16UC1; compressedDepth").depth);
        assert!(p("32FC1; compressedDepth png").depth);
        assert_eq!(p("rgb8; qoi compressed bgr8").declared, Declared::Other);
    }

    #[test]
    fn compressed_depth_is_rejected_even_with_png_bytes() {
        let bytes = png8(&[1, 2, 3, 4], 2, 2, png::ColorType::Grayscale);
        for format in [
            "16UC1; compressedDepth",
            "32FC1; compressedDepth png",
            "16UC1; compressedDepth rvl",
        ] {
            let err = named(
                decode_ros2_compressed(&ros2_compressed(format, bytes.clone()), Target::Mono)
                    .unwrap_err(),
            );
            assert!(matches!(err, ImageError::CompressedDepth { .. }), "{err}");
            assert!(err.to_string().contains("compressedDepth"));
        }
    }

    #[test]
    fn webp_and_avif_are_unsupported() {
        let webp = b"RIFF\x10\x00\x00\x00WEBPVP8 ".to_vec();
        for format in ["webp", "avif", "rgb8; qoi compressed bgr8"] {
            let err = named(
                decode_foxglove_compressed(&fox_compressed(format, webp.clone()), Target::Rgb)
                    .unwrap_err(),
            );
            assert!(matches!(err, ImageError::UnsupportedFormat { .. }), "{err}");
            assert!(err.to_string().contains(format), "{err}");
        }
        // A mislabelled JPEG is still decoded.
        let bytes = jpeg(&solid(8, 8, RED), 8, 8, jpeg_encoder::ColorType::Rgb);
        assert_red(
            &decode_foxglove_compressed(&fox_compressed("webp", bytes), Target::Rgb).unwrap(),
        );
    }

    #[test]
    fn unknown_format_names_the_bytes() {
        let err = named(
            decode_ros2_compressed(&ros2_compressed("", b"hello world".to_vec()), Target::Rgb)
                .unwrap_err(),
        );
        assert!(matches!(err, ImageError::UnknownFormat { .. }), "{err}");
        assert!(err.to_string().contains("68 65 6C 6C"), "{err}");
        let err = named(
            decode_ros2_compressed(&ros2_compressed("", Vec::new()), Target::Rgb).unwrap_err(),
        );
        assert!(
            matches!(err, ImageError::UnknownFormat { len: 0, .. }),
            "{err}"
        );
        // Declared JPEG, not JPEG bytes: the JPEG decoder's error.
        let err = named(
            decode_ros2_compressed(
                &ros2_compressed("jpeg", b"hello world".to_vec()),
                Target::Rgb,
            )
            .unwrap_err(),
        );
        assert!(
            matches!(
                err,
                ImageError::Corrupt {
                    codec: Codec::Jpeg,
                    ..
                }
            ),
            "{err}"
        );
        let err = named(
            decode_ros2_compressed(&ros2_compressed("png", Vec::new()), Target::Rgb).unwrap_err(),
        );
        assert!(
            matches!(
                err,
                ImageError::Corrupt {
                    codec: Codec::Png,
                    ..
                }
            ),
            "{err}"
        );
    }

    #[test]
    fn disagreement_is_reported_when_neither_codec_works() {
        let bytes = jpeg(&gradient(32, 32), 32, 32, jpeg_encoder::ColorType::Rgb);
        let truncated = bytes[..bytes.len() / 2].to_vec();
        let err = named(
            decode_ros2_compressed(&ros2_compressed("png", truncated.clone()), Target::Rgb)
                .unwrap_err(),
        );
        assert!(
            matches!(
                err,
                ImageError::FormatMismatch {
                    sniffed: Codec::Jpeg,
                    ..
                }
            ),
            "{err}"
        );
        let msg = err.to_string();
        assert!(msg.contains("JPEG") && msg.contains("`png`"), "{msg}");
        // Same codec declared: plain decoder error, no disagreement to report.
        let err = decode_ros2_compressed(&ros2_compressed("jpeg", truncated.clone()), Target::Rgb)
            .unwrap_err();
        assert!(matches!(err, ImageError::Corrupt { .. }), "{err}");
        let err = decode_ros2_compressed(&ros2_compressed("", truncated), Target::Rgb).unwrap_err();
        assert!(matches!(err, ImageError::Corrupt { .. }), "{err}");
    }

    // --- Raw images -----------------------------------------------------------------

    #[test]
    fn raw_colour_encodings_come_out_rgb() {
        let (w, h) = (3, 2);
        let rgb = gradient(w, h);
        let bgr: Vec<u8> = rgb
            .chunks_exact(3)
            .flat_map(|p| [p[2], p[1], p[0]])
            .collect();
        let rgba: Vec<u8> = rgb
            .chunks_exact(3)
            .flat_map(|p| [p[0], p[1], p[2], 7])
            .collect();
        let bgra: Vec<u8> = rgb
            .chunks_exact(3)
            .flat_map(|p| [p[2], p[1], p[0], 7])
            .collect();
        let cases: [(&str, &Vec<u8>, u32); 7] = [
            ("rgb8", &rgb, 3),
            ("bgr8", &bgr, 3),
            ("8UC3", &bgr, 3),
            ("rgba8", &rgba, 4),
            ("bgra8", &bgra, 4),
            ("8UC4", &bgra, 4),
            ("BGR8", &bgr, 3),
        ];
        for (encoding, data, bpp) in cases {
            let image = decode_ros2_raw(
                &ros2_raw(encoding, w, h, w * bpp, data.clone()),
                Target::Rgb,
            )
            .unwrap_or_else(|e| panic!("{encoding}: {e}"));
            assert_eq!(image.format, PixelFormat::Rgb8);
            assert_eq!(image.data, rgb, "{encoding}");
            let image =
                decode_foxglove_raw(&fox_raw(encoding, w, h, w * bpp, data.clone()), Target::Rgb)
                    .unwrap();
            assert_eq!(image.data, rgb, "{encoding}");
        }
        // A pure red pixel in each layout.
        for (encoding, px) in [
            ("rgb8", vec![255, 0, 0]),
            ("bgr8", vec![0, 0, 255]),
            ("8UC3", vec![0, 0, 255]),
            ("rgba8", vec![255, 0, 0, 0]),
            ("bgra8", vec![0, 0, 255, 0]),
        ] {
            let image =
                decode_ros2_raw(&ros2_raw(encoding, 1, 1, px.len() as u32, px), Target::Rgb)
                    .unwrap();
            assert_red(&image);
        }
    }

    #[test]
    fn raw_rows_with_padding_are_unpadded() {
        let (w, h) = (3, 3);
        let rgb = gradient(w, h);
        let step = w * 3 + 5;
        let mut padded = Vec::new();
        for row in rgb.chunks(9) {
            padded.extend_from_slice(row);
            padded.extend_from_slice(&[0xEE; 5]);
        }
        let image =
            decode_ros2_raw(&ros2_raw("rgb8", w, h, step, padded.clone()), Target::Rgb).unwrap();
        assert_eq!(image.data, rgb);
        // The last row's padding may be missing.
        padded.truncate(padded.len() - 5);
        let image = decode_foxglove_raw(&fox_raw("rgb8", w, h, step, padded), Target::Rgb).unwrap();
        assert_eq!(image.data, rgb);
        // step 0: tightly packed.
        let image =
            decode_foxglove_raw(&fox_raw("rgb8", w, h, 0, rgb.clone()), Target::Rgb).unwrap();
        assert_eq!(image.data, rgb);
    }

    #[test]
    fn raw_mono_class_map_is_kept_exact() {
        let (w, h) = (16u32, 16u32);
        let ids: Vec<u8> = (0..=255).collect();
        let step = w + 3;
        let padded: Vec<u8> = ids
            .chunks(16)
            .flat_map(|r| [r, &[9, 9, 9][..]].concat())
            .collect();
        for encoding in ["mono8", "8UC1"] {
            let image = decode_ros2_raw(
                &ros2_raw(encoding, w, h, step, padded.clone()),
                Target::Mono,
            )
            .unwrap();
            assert_eq!(image.format, PixelFormat::Mono8);
            assert_eq!(image.data, ids);
            let image = decode_foxglove_raw(&fox_raw(encoding, w, h, w, ids.clone()), Target::Mono)
                .unwrap();
            assert_eq!(image.data, ids);
        }
        let rgb = decode_ros2_raw(&ros2_raw("mono8", w, h, w, ids.clone()), Target::Rgb).unwrap();
        assert_eq!(
            rgb.data,
            ids.iter().flat_map(|&g| [g, g, g]).collect::<Vec<u8>>()
        );
        // Colour to a class map is an error.
        for encoding in ["rgb8", "bgr8", "8UC3", "rgba8"] {
            let err = named(
                decode_ros2_raw(
                    &ros2_raw(
                        encoding,
                        1,
                        1,
                        4,
                        vec![1, 2, 3, 4][..if encoding == "rgba8" { 4 } else { 3 }].to_vec(),
                    ),
                    Target::Mono,
                )
                .unwrap_err(),
            );
            assert!(matches!(err, ImageError::NotMono { .. }), "{err}");
        }
    }

    #[test]
    fn unsupported_raw_encodings_are_clear_errors() {
        for (encoding, expect) in [
            ("mono16", "16 bits"),
            ("16UC1", "more than 8 bits"),
            ("32FC1", "more than 8 bits"),
            ("rgb16", "16 bits"),
            ("bayer_rggb8", "Bayer"),
            ("bayer_grbg16", "Bayer"),
            ("yuv422", "YUV"),
            ("uyvy", "YUV"),
            ("8UC2", "channels"),
            ("", "no encoding"),
            ("hsv8", "unknown"),
        ] {
            for target in [Target::Rgb, Target::Mono] {
                let err = named(
                    decode_ros2_raw(&ros2_raw(encoding, 2, 2, 4, vec![0; 8]), target).unwrap_err(),
                );
                assert!(
                    matches!(err, ImageError::UnsupportedEncoding { .. }),
                    "{err}"
                );
                let msg = err.to_string();
                assert!(
                    msg.contains("unsupported encoding") && msg.contains(expect),
                    "{msg}"
                );
                assert!(msg.contains(&format!("`{encoding}`")), "{msg}");
            }
        }
    }

    #[test]
    fn raw_size_errors() {
        // Zero size.
        let err = named(
            decode_ros2_raw(&ros2_raw("rgb8", 0, 4, 0, Vec::new()), Target::Rgb).unwrap_err(),
        );
        assert!(matches!(err, ImageError::ZeroSize { .. }), "{err}");
        let err = named(
            decode_foxglove_raw(&fox_raw("mono8", 4, 0, 4, Vec::new()), Target::Mono).unwrap_err(),
        );
        assert!(matches!(err, ImageError::ZeroSize { .. }), "{err}");
        // Step too small.
        let err = named(
            decode_ros2_raw(&ros2_raw("rgb8", 4, 2, 11, vec![0; 22]), Target::Rgb).unwrap_err(),
        );
        assert!(
            matches!(
                err,
                ImageError::StepTooSmall {
                    step: 11,
                    row_bytes: 12,
                    ..
                }
            ),
            "{err}"
        );
        // Data too short, and too long.
        let err = named(
            decode_ros2_raw(&ros2_raw("rgb8", 4, 2, 12, vec![0; 23]), Target::Rgb).unwrap_err(),
        );
        assert!(
            matches!(err, ImageError::DataLength { got: 23, .. }),
            "{err}"
        );
        let err = named(
            decode_ros2_raw(&ros2_raw("bgr8", 4, 2, 12, vec![0; 25]), Target::Rgb).unwrap_err(),
        );
        assert!(
            matches!(err, ImageError::DataLength { got: 25, .. }),
            "{err}"
        );
        let err = named(
            decode_foxglove_raw(&fox_raw("mono8", 4, 2, 0, vec![0; 7]), Target::Mono).unwrap_err(),
        );
        assert!(matches!(err, ImageError::DataLength { .. }), "{err}");
        // Absurd sizes: rejected before anything is allocated.
        for (w, h, step) in [
            (u32::MAX, u32::MAX, u32::MAX),
            (100_000, 100_000, 0),
            (1 << 20, 1 << 10, 0),
        ] {
            let err = named(
                decode_ros2_raw(&ros2_raw("rgb8", w, h, step, vec![0; 16]), Target::Rgb)
                    .unwrap_err(),
            );
            assert!(matches!(err, ImageError::TooLarge { .. }), "{err}");
        }
        // Huge step with a single row is a length error, not an overflow.
        let err = decode_ros2_raw(&ros2_raw("mono8", 2, 1, u32::MAX, vec![0; 2]), Target::Mono);
        assert_eq!(err.unwrap().data, [0, 0]);
        let err = decode_ros2_raw(&ros2_raw("mono8", 2, 3, u32::MAX, vec![0; 6]), Target::Mono)
            .unwrap_err();
        assert!(matches!(err, ImageError::DataLength { .. }), "{err}");
    }

    #[test]
    fn foxglove_without_timestamp_is_an_error() {
        let mut msg = fox_raw("mono8", 1, 1, 1, vec![0]);
        msg.timestamp = None;
        let err = decode_foxglove_raw(&msg, Target::Mono).unwrap_err();
        assert!(matches!(err, ImageError::Timestamp { .. }), "{err}");
        assert!(err.to_string().contains(FRAME), "{err}");
        let mut msg = fox_compressed("png", Vec::new());
        msg.timestamp = None;
        assert!(decode_foxglove_compressed(&msg, Target::Rgb).is_err());
    }

    // --- Robustness -----------------------------------------------------------------

    #[test]
    fn every_truncation_of_a_png_and_a_jpeg_fails_cleanly() {
        let rgb = gradient(24, 16);
        let png_rgb = png8(&rgb, 24, 16, png::ColorType::Rgb);
        let png_grey = png8(&rgb[..24 * 16], 24, 16, png::ColorType::Grayscale);
        let jpg = jpeg(&rgb, 24, 16, jpeg_encoder::ColorType::Rgb);
        let mut progressive = Vec::new();
        {
            let mut encoder = jpeg_encoder::Encoder::new(&mut progressive, 90);
            encoder.set_progressive(true);
            encoder
                .encode(&rgb, 24, 16, jpeg_encoder::ColorType::Rgb)
                .unwrap();
        }
        for (name, bytes, grey) in [
            ("png", &png_rgb, false),
            ("png", &png_grey, true),
            ("jpeg", &jpg, false),
            ("jpeg", &progressive, false),
        ] {
            for len in 0..bytes.len() {
                for format in [name, "", "webp"] {
                    for target in [Target::Rgb, Target::Mono] {
                        // Must not panic; a result is allowed only when all the image data is there.
                        let result = decode_ros2_compressed(
                            &ros2_compressed(format, bytes[..len].to_vec()),
                            target,
                        );
                        if len < bytes.len() - 12 {
                            assert!(
                                result.is_err(),
                                "{name} truncated to {len} of {} decoded",
                                bytes.len()
                            );
                        }
                    }
                }
            }
            for target in [Target::Rgb, Target::Mono] {
                let full = decode_ros2_compressed(&ros2_compressed(name, bytes.to_vec()), target);
                if grey || target == Target::Rgb {
                    assert!(full.is_ok(), "{name}: {:?}", full.err());
                }
            }
        }
    }

    #[test]
    fn garbage_never_panics() {
        let mut state = 0x1234_5678_u32;
        let mut next = move || {
            state ^= state << 13;
            state ^= state >> 17;
            state ^= state << 5;
            state
        };
        let png_ok = png8(&gradient(8, 8), 8, 8, png::ColorType::Rgb);
        let jpg_ok = jpeg(&gradient(16, 16), 16, 16, jpeg_encoder::ColorType::Rgb);
        for round in 0..400 {
            let mut bytes = match round % 3 {
                0 => png_ok.clone(),
                1 => jpg_ok.clone(),
                _ => (0..(next() % 300)).map(|_| next() as u8).collect(),
            };
            // Flip a few bytes past the magic.
            if bytes.len() > 8 {
                for _ in 0..(1 + next() % 4) {
                    let at = 4 + (next() as usize) % (bytes.len() - 4);
                    bytes[at] = next() as u8;
                }
            }
            for format in ["png", "jpeg", "", "rgb8; png compressed rgb8"] {
                let _ =
                    decode_ros2_compressed(&ros2_compressed(format, bytes.clone()), Target::Rgb);
                let _ = decode_foxglove_compressed(
                    &fox_compressed(format, bytes.clone()),
                    Target::Mono,
                );
            }
            let w = next() % 64;
            let h = next() % 64;
            let _ = decode_ros2_raw(
                &ros2_raw("bgra8", w, h, next() % 300, bytes.clone()),
                Target::Rgb,
            );
            let _ = decode_foxglove_raw(&fox_raw("mono8", w, h, next() % 70, bytes), Target::Mono);
        }
    }
}
