//! Raw images (`sensor_msgs/msg/Image`, `foxglove.RawImage`): the 8-bit RGB, BGR, RGBA,
//! BGRA and mono encodings, with row padding, into `Rgb8` or `Mono8`.

use superflow_schemas::sensor::{Image, PixelFormat};

use super::decoded::Decoded;
use super::error::ImageError;
use super::target::Target;
use crate::decode::context::Ctx;

/// The fields of a raw image message.
#[derive(Debug, Clone, Copy)]
pub(super) struct Raw<'a> {
    /// The `encoding` string.
    pub(super) encoding: &'a str,
    /// Width in pixels.
    pub(super) width: u32,
    /// Height in pixels.
    pub(super) height: u32,
    /// Bytes per row (0: tightly packed).
    pub(super) step: u32,
    /// The pixels.
    pub(super) data: &'a [u8],
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

    /// Bytes per pixel.
    fn channels(self) -> usize {
        match self {
            Self::Mono8 => 1,
            Self::Rgb8 | Self::Bgr8 => 3,
            Self::Rgba8 | Self::Bgra8 => 4,
        }
    }
}

/// Decodes raw pixels (see the module documentation for encodings and `step`).
pub(super) fn decode_raw(raw: &Raw<'_>, target: Target, ctx: Ctx<'_>) -> Result<Image, ImageError> {
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
    let step = row_step(raw, row_bytes, ctx)?;
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
        native: (raw.width, raw.height),
        format,
        data: out,
    })
}

/// The byte distance between rows (`step`, or `row_bytes` when 0), checked against a
/// row of pixels and against the data's length (the last row's padding may be left out).
/// The image is not empty (checked before).
fn row_step(raw: &Raw<'_>, row_bytes: u64, ctx: Ctx<'_>) -> Result<u64, ImageError> {
    let h = u64::from(raw.height);
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
    Ok(step)
}
