//! PNG decoding (`png` crate, no transformations): grey 1/2/4/8/16-bit, grey+alpha,
//! RGB(A) 8/16-bit and palette images into `Rgb8`, or into `Mono8` with the stored values
//! (class ids, palette indices) kept.

use std::io::Cursor;

use png::{BitDepth, ColorType};

use superflow_schemas::sensor::PixelFormat;

use super::checks::MAX_IMAGE_BYTES;
use super::codec::Codec;
use super::decoded::Decoded;
use super::error::{ImageError, Rejection};
use super::target::Target;
use crate::decode::context::Ctx;

/// The header of a PNG: size, colour type and bit depth.
#[derive(Debug, Clone, Copy)]
struct Header {
    width: u32,
    height: u32,
    color: ColorType,
    depth: BitDepth,
}

/// The samples of a decoded PNG frame as the decoder wrote them (no transformations),
/// with what reading them needs.
#[derive(Debug)]
struct Frame {
    header: Header,
    /// Bytes per row in `raw`.
    line: usize,
    /// The `PLTE` entries, 3 bytes each (empty without a palette).
    palette: Vec<u8>,
    raw: Vec<u8>,
}

/// Decodes a PNG into `format` for `target` (see the module documentation of
/// [`super`]): the header is checked against [`MAX_IMAGE_BYTES`] before the decoder
/// allocates its rows.
pub(super) fn decode_png(data: &[u8], target: Target, ctx: Ctx<'_>) -> Result<Decoded, ImageError> {
    let limits = png::Limits {
        bytes: usize::try_from(MAX_IMAGE_BYTES).unwrap_or(usize::MAX),
    };
    let mut decoder = png::Decoder::new_with_limits(Cursor::new(data), limits);
    // Raw samples: bit depths, palettes and alpha are handled below, so that class ids
    // in 1/2/4-bit grey or palette PNGs are not rescaled.
    decoder.set_transformations(png::Transformations::IDENTITY);
    // The header alone first: the size checks come before the decoder allocates rows.
    let info = decoder.read_header_info().map_err(|e| png_error(ctx, e))?;
    let header = Header {
        width: info.width,
        height: info.height,
        color: info.color_type,
        depth: info.bit_depth,
    };
    let format = output_format(target, header, ctx)?;
    let (w, h) = (u64::from(header.width), u64::from(header.height));
    let out_len = ctx.checked_size(w, h, format.channels() as u64)?;
    // Class maps (8-bit grey as Mono8) mostly take the fast path; the png crate decodes
    // everything else, and anything that path does not expect.
    let fast = (format == PixelFormat::Mono8)
        .then(|| super::png_grey::decode_grey8(data, MAX_IMAGE_BYTES))
        .flatten();
    let pixels = match fast {
        Some(pixels) => pixels,
        None => read_frame(decoder, header, ctx)?.into_pixels(format, out_len, ctx)?,
    };
    Ok(Decoded {
        width: header.width,
        height: header.height,
        native: (header.width, header.height),
        format,
        data: pixels,
    })
}

/// A decoder error as [`ImageError::Corrupt`], naming the buffer limit when it is hit.
fn png_error(ctx: Ctx<'_>, e: png::DecodingError) -> ImageError {
    match e {
        png::DecodingError::LimitsExceeded => ctx.corrupt(
            Codec::Png,
            format!("the decoder needs more than {MAX_IMAGE_BYTES} bytes of buffers"),
        ),
        e => ctx.corrupt(Codec::Png, Rejection::Png(e)),
    }
}

/// The output format for `target`: anything gives `Rgb8`; `Mono8` only from grey (up to
/// 8 bits) and palette images, whose values are kept.
fn output_format(target: Target, header: Header, ctx: Ctx<'_>) -> Result<PixelFormat, ImageError> {
    let Header { color, depth, .. } = header;
    Ok(match (target, color) {
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
    })
}

/// Reads the frame's samples, after checking the decoder's sample buffer against
/// [`MAX_IMAGE_BYTES`].
fn read_frame(
    decoder: png::Decoder<Cursor<&[u8]>>,
    header: Header,
    ctx: Ctx<'_>,
) -> Result<Frame, ImageError> {
    let (w, h) = (u64::from(header.width), u64::from(header.height));
    // The decoder's sample buffer: whole bytes per row, up to 8 bytes per pixel.
    let bits_per_row = w * header.color.samples() as u64 * u64::from(header.depth as u8);
    let raw_bytes = bits_per_row.div_ceil(8) * h;
    if raw_bytes > MAX_IMAGE_BYTES {
        return Err(ctx.too_large(w, h, raw_bytes));
    }
    let mut reader = decoder.read_info().map_err(|e| png_error(ctx, e))?;
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
        .output_line_size(header.width)
        .ok_or_else(|| ctx.too_large(w, h, u64::MAX))?;
    let mut raw = super::buffers::take(raw_len);
    reader.next_frame(&mut raw).map_err(|e| png_error(ctx, e))?;
    Ok(Frame {
        header,
        line,
        palette,
        raw,
    })
}

impl Frame {
    /// [`Frame::pixels`], taking the decoder's buffer itself when its rows are already
    /// the output (8-bit grey as `Mono8`, 8-bit RGB as `Rgb8`: rows without padding).
    fn into_pixels(
        mut self,
        format: PixelFormat,
        out_len: usize,
        ctx: Ctx<'_>,
    ) -> Result<Vec<u8>, ImageError> {
        let Header { color, depth, .. } = self.header;
        let same = matches!(
            (color, depth, format),
            (ColorType::Rgb, BitDepth::Eight, PixelFormat::Rgb8)
                | (ColorType::Grayscale, BitDepth::Eight, PixelFormat::Mono8)
        );
        let height = self.header.height as usize;
        if same && self.line * height == out_len && self.raw.len() >= out_len {
            self.raw.truncate(out_len);
            return Ok(self.raw);
        }
        let pixels = self.pixels(format, out_len, ctx);
        super::buffers::give_back(self.raw);
        pixels
    }

    /// The pixels in `format`, `out_len` bytes (checked).
    fn pixels(
        &self,
        format: PixelFormat,
        out_len: usize,
        ctx: Ctx<'_>,
    ) -> Result<Vec<u8>, ImageError> {
        let corrupt = |reason: String| ctx.corrupt(Codec::Png, reason);
        let Header { color, depth, .. } = self.header;
        let (width, height) = (self.header.width as usize, self.header.height as usize);
        let bits = depth as u8;
        let spp = color.samples();
        let mut out = Vec::with_capacity(out_len);
        let mut samples: Vec<u16> = Vec::with_capacity(width * spp);
        for row in self.raw.chunks(self.line).take(height) {
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
            self.push_row(&samples, format, &mut out, ctx)?;
        }
        if out.len() != out_len {
            return Err(corrupt(format!(
                "{} bytes decoded for {width}x{height} {format:?}",
                out.len()
            )));
        }
        Ok(out)
    }

    /// Appends one row of unpacked `samples` to `out` in `format`.
    fn push_row(
        &self,
        samples: &[u16],
        format: PixelFormat,
        out: &mut Vec<u8>,
        ctx: Ctx<'_>,
    ) -> Result<(), ImageError> {
        let Header { color, depth, .. } = self.header;
        let bits = depth as u8;
        let spp = color.samples();
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
                for &index in samples {
                    match format {
                        PixelFormat::Mono8 => out.push(index as u8),
                        PixelFormat::Rgb8 => {
                            let at = usize::from(index) * 3;
                            let rgb = self.palette.get(at..at + 3).ok_or_else(|| {
                                ctx.corrupt(
                                    Codec::Png,
                                    format!(
                                        "palette index {index} outside the {}-entry palette",
                                        self.palette.len() / 3
                                    ),
                                )
                            })?;
                            out.extend_from_slice(rgb);
                        }
                    }
                }
            }
        }
        Ok(())
    }
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
