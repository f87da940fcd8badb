//! [`ImageError`]: why an image message cannot be decoded. Every variant names the
//! message's frame id and (where the message has one) its stamp.

use super::codec::Codec;
use crate::decode::error::DecodeError;
use superflow_schemas::Stamp;
use superflow_schemas::sensor::SensorError;

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
        #[source]
        reason: Rejection,
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
    /// [`Target::Mono`](super::Target::Mono) asked of data whose values cannot be kept exactly.
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
    /// The decoded image would exceed [`MAX_IMAGE_BYTES`](super::MAX_IMAGE_BYTES).
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
        /// [`MAX_IMAGE_BYTES`](super::MAX_IMAGE_BYTES).
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

/// Why a codec rejected an image's data ([`ImageError::Corrupt`]): the decoder's own
/// error, or what the data gets wrong where no decoder error stands behind it.
#[derive(Debug, thiserror::Error)]
pub enum Rejection {
    /// libjpeg-turbo's error.
    #[error("libjpeg-turbo: {0}")]
    Jpeg(#[source] turbojpeg::Error),
    /// The png crate's error.
    #[error("{0}")]
    Png(#[source] png::DecodingError),
    /// What is wrong with the data, in words.
    #[error("{0}")]
    Invalid(String),
}

impl From<String> for Rejection {
    fn from(reason: String) -> Self {
        Self::Invalid(reason)
    }
}

impl From<&str> for Rejection {
    fn from(reason: &str) -> Self {
        Self::Invalid(reason.to_string())
    }
}
