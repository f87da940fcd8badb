//! JPEG decoding with libjpeg-turbo (the `turbojpeg` crate, which builds libjpeg-turbo 3
//! with its SIMD code): YCbCr and grey into `Rgb8`, grey into `Mono8`, optionally at
//! 1/2 or 1/4 scale in the DCT domain ([`Scale::AtLeast`]). The output is libjpeg's
//! accurate IDCT with smooth chroma upsampling, bit-exact with Pillow and `djpeg`
//! (also at reduced scale, with `Image.draft` / `djpeg -scale`). A JPEG without an
//! end-of-image marker after its scan data is truncated.

use std::cell::RefCell;

use superflow_schemas::sensor::PixelFormat;
use turbojpeg::{Colorspace, Decompressor, Image as TjImage, PixelFormat as TjFormat};
use turbojpeg::{DecompressHeader, ScalingFactor};

use super::codec::Codec;
use super::decoded::Decoded;
use super::error::{ImageError, Rejection};
use super::scale::Scale;
use super::target::Target;
use crate::decode::context::Ctx;

/// Scans a progressive JPEG may have before it is rejected (libjpeg-turbo's advice
/// against crafted files with thousands of tiny scans; real encoders write ~10).
const SCAN_LIMIT: u32 = 500;

/// The reduced scales tried, smallest first: the two libjpeg-turbo decodes with SIMD
/// (3/8, 5/8 and 6/8 exist but are slower than 1/2 there).
const REDUCED: [ScalingFactor; 2] = [ScalingFactor::ONE_QUARTER, ScalingFactor::ONE_HALF];

thread_local! {
    /// One decompressor per thread (a handle is `Send`, not `Sync`), dropped after any
    /// error so that a failed decode never leaves state for the next image.
    static DECOMPRESSOR: RefCell<Option<Decompressor>> = const { RefCell::new(None) };
}

/// Whether an end-of-image marker (`FF D9`) follows the first start-of-scan marker
/// (`FF DA`). Inside entropy-coded data every `FF` byte is stuffed (`FF 00`) or a restart
/// marker, so a JPEG cut anywhere after its headers has no `FF D9` after the scan start.
fn jpeg_has_end(data: &[u8]) -> bool {
    let sos = data.windows(2).position(|w| w == [0xFF, 0xDA]);
    let eoi = data.windows(2).rposition(|w| w == [0xFF, 0xD9]);
    matches!((sos, eoi), (Some(sos), Some(eoi)) if eoi > sos)
}

/// A libjpeg warning that leaves a complete, correct image: stray bytes between the
/// scan data and the end-of-image marker (written by some encoders; Pillow, `djpeg` and
/// jpeg-decoder accept them). Every other warning (bad Huffman code, premature end, ...)
/// means damaged pixels and is an error.
fn harmless_warning(message: &str) -> bool {
    message.contains("extraneous bytes before marker 0xd9")
}

/// The scale to decode a `width × height` JPEG at: the smallest of 1/4 and 1/2 that keeps
/// at least the requested size, else full size. Lossless JPEGs do not scale.
fn scale_for(header: &DecompressHeader, scale: Scale) -> ScalingFactor {
    let Scale::AtLeast { width, height } = scale else {
        return ScalingFactor::ONE;
    };
    if header.is_lossless {
        return ScalingFactor::ONE;
    }
    REDUCED
        .into_iter()
        .find(|f| {
            f.scale(header.width) >= width as usize && f.scale(header.height) >= height as usize
        })
        .unwrap_or(ScalingFactor::ONE)
}

/// Decodes a JPEG into `Rgb8`, or into `Mono8` when it is grey and `target` is
/// [`Target::Mono`]; CMYK and truncated JPEGs are errors. Colour images decode at a
/// reduced scale when `scale` allows it; the result carries the full size too.
pub(super) fn decode_jpeg(
    data: &[u8],
    target: Target,
    scale: Scale,
    ctx: Ctx<'_>,
) -> Result<Decoded, ImageError> {
    DECOMPRESSOR.with(|cell| {
        let mut slot = cell.borrow_mut();
        let decompressor = match slot.as_mut() {
            Some(d) => d,
            None => {
                let made = Decompressor::new()
                    .map_err(|e| ctx.corrupt(Codec::Jpeg, Rejection::Jpeg(e)))?;
                slot.insert(made)
            }
        };
        let result = decode_with(decompressor, data, target, scale, ctx);
        if result.is_err() {
            *slot = None;
        }
        result
    })
}

/// [`decode_jpeg`] with this thread's decompressor.
fn decode_with(
    tj: &mut Decompressor,
    data: &[u8],
    target: Target,
    scale: Scale,
    ctx: Ctx<'_>,
) -> Result<Decoded, ImageError> {
    let corrupt = |reason: String| ctx.corrupt(Codec::Jpeg, reason);
    let tj_err = |e: turbojpeg::Error| ctx.corrupt(Codec::Jpeg, Rejection::Jpeg(e));
    let header = tj.read_header(data).map_err(tj_err)?;
    let (format, tj_format) = match (target, header.colorspace) {
        (Target::Rgb, Colorspace::YCbCr | Colorspace::RGB | Colorspace::Gray) => {
            (PixelFormat::Rgb8, TjFormat::RGB)
        }
        (Target::Mono, Colorspace::Gray) => (PixelFormat::Mono8, TjFormat::GRAY),
        (Target::Mono, other) => return Err(ctx.not_mono(format!("a colour JPEG ({other:?})"))),
        (Target::Rgb, Colorspace::CMYK | Colorspace::YCCK) => {
            return Err(corrupt(
                "CMYK JPEGs are not camera images; not supported".into(),
            ));
        }
    };
    let (width, height) = (header.width as u64, header.height as u64);
    ctx.checked_size(width, height, format.channels() as u64)?;
    if !jpeg_has_end(data) {
        return Err(corrupt(
            "truncated: no end-of-image marker after the scan data".into(),
        ));
    }
    // Class ids (Mono) are never blended: only colour images decode at a reduced scale.
    let factor = match target {
        Target::Rgb => scale_for(&header, scale),
        Target::Mono => ScalingFactor::ONE,
    };
    tj.set_scaling_factor(factor).map_err(tj_err)?;
    tj.set_scan_limit(SCAN_LIMIT).map_err(tj_err)?;
    let out = header.scaled(factor);
    let channels = format.channels();
    let mut pixels = super::buffers::take(out.width * out.height * channels);
    let image = TjImage {
        pixels: &mut pixels[..],
        width: out.width,
        pitch: out.width * channels,
        height: out.height,
        format: tj_format,
    };
    match tj.decompress(data, image) {
        Ok(()) => {}
        Err(turbojpeg::Error::TurboJpegError(message)) if harmless_warning(&message) => {}
        Err(e) => return Err(tj_err(e)),
    }
    let dim = |v: usize| u32::try_from(v).map_err(|_| corrupt(format!("dimension {v}")));
    Ok(Decoded {
        width: dim(out.width)?,
        height: dim(out.height)?,
        native: (dim(header.width)?, dim(header.height)?),
        format,
        data: pixels,
    })
}
