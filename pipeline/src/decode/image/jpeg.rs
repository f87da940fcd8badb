//! JPEG decoding (jpeg-decoder): YCbCr and grey into `Rgb8`, grey into `Mono8`; a JPEG
//! without an end-of-image marker after its scan data is truncated.

use superflow_schemas::sensor::PixelFormat;

use super::{Codec, Decoded, ImageError, MAX_IMAGE_BYTES, Target};
use crate::decode::context::Ctx;

/// Whether an end-of-image marker (`FF D9`) follows the first start-of-scan marker
/// (`FF DA`). Inside entropy-coded data every `FF` byte is stuffed (`FF 00`) or a restart
/// marker, so a JPEG cut anywhere after its headers has no `FF D9` after the scan start.
fn jpeg_has_end(data: &[u8]) -> bool {
    let sos = data.windows(2).position(|w| w == [0xFF, 0xDA]);
    let eoi = data.windows(2).rposition(|w| w == [0xFF, 0xD9]);
    matches!((sos, eoi), (Some(sos), Some(eoi)) if eoi > sos)
}

/// Decodes a JPEG into `Rgb8`, or into `Mono8` when it is grey and `target` is
/// [`Target::Mono`]; CMYK and truncated JPEGs are errors.
pub(super) fn decode_jpeg(
    data: &[u8],
    target: Target,
    ctx: Ctx<'_>,
) -> Result<Decoded, ImageError> {
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
