//! Image encoders of the writers: camera images as baseline JPEG, class maps as 8-bit
//! grey PNG, and whole cameras' frames encoded in parallel (the bytes are the same as
//! encoding one after another).

use crate::JPEG_QUALITY;
use crate::error::{GenerateError, Result};
use crate::sim::CameraFrame;
use rayon::prelude::*;
use superflow_schemas::sensor::{Image, PixelFormat};

/// Encodes an RGB8 image as a baseline JPEG (deterministic: scalar code path).
pub fn encode_jpeg(image: &Image) -> Result<Vec<u8>> {
    let mut out = Vec::new();
    let mut encoder = jpeg_encoder::Encoder::new(&mut out, JPEG_QUALITY);
    encoder.set_optimized_huffman_tables(true);
    let (Ok(w), Ok(h)) = (u16::try_from(image.width), u16::try_from(image.height)) else {
        return Err(GenerateError::ImageTooLarge {
            frame_id: image.frame_id.clone(),
            width: image.width,
            height: image.height,
        });
    };
    encoder
        .encode(&image.data, w, h, jpeg_encoder::ColorType::Rgb)
        .map_err(|source| GenerateError::Jpeg {
            frame_id: image.frame_id.clone(),
            source,
        })?;
    Ok(out)
}

/// Encodes a Mono8 image (a class map) as an 8-bit grey PNG, values kept as they are.
pub fn encode_png_mono(image: &Image) -> Result<Vec<u8>> {
    let png_error = |source| GenerateError::Png {
        frame_id: image.frame_id.clone(),
        source,
    };
    if image.format != PixelFormat::Mono8 {
        return Err(GenerateError::NotMono8 {
            frame_id: image.frame_id.clone(),
        });
    }
    let mut out = Vec::new();
    let mut encoder = png::Encoder::new(&mut out, image.width, image.height);
    encoder.set_color(png::ColorType::Grayscale);
    encoder.set_depth(png::BitDepth::Eight);
    encoder.set_compression(png::Compression::Fast);
    let mut writer = encoder.write_header().map_err(png_error)?;
    writer.write_image_data(&image.data).map_err(png_error)?;
    writer.finish().map_err(png_error)?;
    Ok(out)
}

/// The JPEG of every frame's colour image, in order.
pub fn jpegs(frames: &[CameraFrame]) -> Result<Vec<Vec<u8>>> {
    frames.par_iter().map(|f| encode_jpeg(&f.image)).collect()
}

/// The PNG of every frame's class map, in order.
pub fn class_map_pngs(frames: &[CameraFrame]) -> Result<Vec<Vec<u8>>> {
    frames.par_iter().map(|f| encode_png_mono(&f.classes)).collect()
}
