//! Compressed images: what a `format` string says (codec, image_transport channel
//! order, `compressedDepth`), what the magic bytes say, and the choice of codec when the
//! two disagree (see the module documentation of [`super`]).

use superflow_schemas::sensor::PixelFormat;

use super::checks::guarded;
use super::codec::Codec;
use super::decoded::Decoded;
use super::error::ImageError;
use super::jpeg::decode_jpeg;
use super::png::decode_png;
use super::scale::{Scale, ScaledImage};
use super::target::Target;
use crate::decode::context::Ctx;

/// The codec a format string names.
#[derive(Debug, Clone, PartialEq, Eq)]
pub(super) enum Declared {
    /// Empty: only the magic bytes tell.
    Unspecified,
    /// JPEG or PNG.
    Codec(Codec),
    /// Something else (`webp`, `avif`, `qoi`, ...).
    Other,
}

/// What a `format` string says.
#[derive(Debug, Clone, PartialEq, Eq)]
pub(super) struct FormatHint {
    /// The codec named.
    pub(super) declared: Declared,
    /// An image_transport target starting with `rgb`: the file is channel-swapped.
    pub(super) swap_red_blue: bool,
    /// An image_transport `compressedDepth` payload.
    pub(super) depth: bool,
}

impl FormatHint {
    /// Parses `"jpeg"`, `"png"`, `"<src>; <codec> compressed <target>"`,
    /// `"<src>; compressedDepth ..."`, ... (case-insensitive).
    pub(super) fn parse(format: &str) -> Self {
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
pub(super) fn sniff(data: &[u8]) -> Option<Codec> {
    if data.starts_with(&[0xFF, 0xD8]) {
        Some(Codec::Jpeg)
    } else if data.starts_with(&[0x89, b'P', b'N', b'G']) {
        Some(Codec::Png)
    } else {
        None
    }
}

/// A compressed payload, what its `format` says, and what the caller wants.
#[derive(Debug, Clone, Copy)]
struct Compressed<'a> {
    data: &'a [u8],
    format: &'a str,
    target: Target,
    scale: Scale,
    ctx: Ctx<'a>,
}

/// Decodes JPEG or PNG bytes described by `format` (see the module documentation).
pub(super) fn decode_compressed(
    data: &[u8],
    format: &str,
    target: Target,
    scale: Scale,
    ctx: Ctx<'_>,
) -> Result<ScaledImage, ImageError> {
    let hint = FormatHint::parse(format);
    let payload = Compressed {
        data,
        format,
        target,
        scale,
        ctx,
    };
    if hint.depth {
        return Err(ImageError::CompressedDepth {
            frame_id: ctx.id(),
            stamp: ctx.stamp,
            format: format.to_string(),
        });
    }
    let mut decoded = match (sniff(data), &hint.declared) {
        (Some(sniffed), declared) => payload.sniffed(sniffed, declared)?,
        (None, Declared::Codec(codec)) => payload.codec(*codec)?,
        (None, Declared::Other) => return Err(payload.unsupported()),
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
    let native = decoded.native;
    Ok(ScaledImage {
        image: ctx.image(decoded)?,
        native,
    })
}

impl Compressed<'_> {
    /// Decodes with `codec`, a panic inside it caught.
    fn codec(&self, codec: Codec) -> Result<Decoded, ImageError> {
        let Self {
            data,
            target,
            scale,
            ctx,
            ..
        } = *self;
        guarded(codec, ctx, || match codec {
            Codec::Jpeg => decode_jpeg(data, target, scale, ctx),
            Codec::Png => decode_png(data, target, ctx),
        })
    }

    /// Decodes with the codec the magic bytes name; when that codec rejects the data and
    /// the format string names another, tries that one and reports both failures.
    fn sniffed(&self, sniffed: Codec, declared: &Declared) -> Result<Decoded, ImageError> {
        let sniffed_reason = match self.codec(sniffed) {
            Err(ImageError::Corrupt { reason, .. })
                if *declared != Declared::Codec(sniffed) && *declared != Declared::Unspecified =>
            {
                reason.to_string()
            }
            other => return other,
        };
        let declared_result = match declared {
            Declared::Codec(codec) => self.codec(*codec),
            _ => Err(self.unsupported()),
        };
        declared_result.map_err(|declared_error| ImageError::FormatMismatch {
            frame_id: self.ctx.id(),
            stamp: self.ctx.stamp,
            format: self.format.to_string(),
            sniffed,
            sniffed_reason,
            declared_reason: match declared_error {
                ImageError::Corrupt { reason, .. } => reason.to_string(),
                ImageError::UnsupportedFormat { .. } => "not a supported codec".to_string(),
                other => other.to_string(),
            },
        })
    }

    /// [`ImageError::UnsupportedFormat`] for this payload's format string.
    fn unsupported(&self) -> ImageError {
        ImageError::UnsupportedFormat {
            frame_id: self.ctx.id(),
            stamp: self.ctx.stamp,
            format: self.format.to_string(),
        }
    }
}
