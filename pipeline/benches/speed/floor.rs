//! What the libraries alone cost for the work a sample's decoding is made of, measured
//! on the same drive without the pipeline: libzstd decompressing the drive's chunks,
//! libjpeg-turbo decoding its camera JPEGs at the scale the recipe decodes them, and the
//! `png` crate decoding its class maps. With the chunks and bytes a sample really
//! decompresses (counted by the pipeline's files), they give the cost of a sample's
//! decoding if the pipeline added nothing to the libraries' own work.

use prost::Message;
use std::path::Path;
use std::time::Instant;
use superflow_pipeline::decode::foxglove::{CompressedImage, Timestamp};
use superflow_pipeline::decode::image::{Target, decode_foxglove_compressed};
use superflow_pipeline::decode::ros2;
use turbojpeg::{Decompressor, Image, PixelFormat, ScalingFactor};

/// Rounds of each measurement; the fastest counts (the VM drifts by 10–30 %).
pub const ROUNDS: usize = 3;

/// Images of each kind decoded per round.
const IMAGES: usize = 48;

/// ms per decompressed MB (10⁶ bytes) of the drive's zstd chunks, with one reused
/// libzstd context into a buffer of each chunk's declared size; `None` when the drive
/// has no zstd chunk.
pub fn zstd_ms_per_mb(path: &Path) -> anyhow::Result<Option<f64>> {
    let bytes = std::fs::read(path)?;
    let mut chunks = Vec::new();
    for record in mcap::read::LinearReader::new(&bytes)? {
        if let mcap::records::Record::Chunk { header, data } = record?
            && header.compression == "zstd"
        {
            chunks.push((header.uncompressed_size as usize, data.into_owned()));
        }
    }
    if chunks.is_empty() {
        return Ok(None);
    }
    let total: usize = chunks.iter().map(|c| c.0).sum();
    let mut context = zstd::bulk::Decompressor::new()?;
    let ms = ms_per_item(&chunks, |(size, data)| {
        let mut out = Vec::with_capacity(*size);
        context.decompress_to_buffer(&data[..], &mut out)?;
        std::hint::black_box(&out);
        Ok(())
    })?;
    Ok(Some(ms * chunks.len() as f64 / (total as f64 / 1e6)))
}

/// The first `IMAGES` compressed images of `path` (`foxglove.CompressedImage` or ROS 2
/// `sensor_msgs/msg/CompressedImage`) whose format names `format` (`jpeg`, `png`), as
/// `foxglove.CompressedImage`s of format `format`.
fn compressed_images(path: &Path, format: &str) -> anyhow::Result<Vec<CompressedImage>> {
    let bytes = std::fs::read(path)?;
    let mut out = Vec::new();
    for message in mcap::MessageStream::new(&bytes)? {
        let message = message?;
        let schema = message.channel.schema.as_ref().map(|s| s.name.as_str());
        let image = match schema {
            Some("foxglove.CompressedImage") => CompressedImage::decode(&message.data[..])?,
            Some("sensor_msgs/msg/CompressedImage") => {
                let image: ros2::CompressedImage = ros2::decode(&message.data)?;
                CompressedImage {
                    timestamp: Some(Timestamp::new(
                        image.header.stamp.sec as u32,
                        image.header.stamp.nanosec,
                    )),
                    frame_id: image.header.frame_id,
                    format: image.format,
                    data: image.data.into(),
                }
            }
            _ => continue,
        };
        // ROS 2 spells it `rgb8; jpeg compressed bgr8` or `mono8; png compressed mono8`.
        if image.format == format || image.format.contains(&format!(" {format} ")) {
            out.push(CompressedImage {
                format: format.to_string(),
                ..image
            });
            if out.len() == IMAGES {
                break;
            }
        }
    }
    Ok(out)
}

/// The fastest of [`ROUNDS`] runs of `decode` over every item of `items`, ms per item.
fn ms_per_item<T>(
    items: &[T],
    mut decode: impl FnMut(&T) -> anyhow::Result<()>,
) -> anyhow::Result<f64> {
    let mut best = f64::INFINITY;
    for _ in 0..ROUNDS {
        let started = Instant::now();
        for item in items {
            decode(item)?;
        }
        best = best.min(started.elapsed().as_secs_f64() * 1e3);
    }
    Ok(best / items.len().max(1) as f64)
}

/// ms per camera JPEG of `path` decoded by libjpeg-turbo into RGB at the scale the
/// recipe decodes it for `width × height` (the smallest of 1/4 and 1/2 that keeps at
/// least that size, else full size), into a reused buffer; `None` without JPEGs.
pub fn jpeg_ms(path: &Path, width: usize, height: usize) -> anyhow::Result<Option<f64>> {
    let jpegs = compressed_images(path, "jpeg")?;
    if jpegs.is_empty() {
        return Ok(None);
    }
    let mut decompressor = Decompressor::new()?;
    let mut pixels = Vec::new();
    let ms = ms_per_item(&jpegs, |jpeg| {
        let jpeg = &jpeg.data[..];
        let header = decompressor.read_header(jpeg)?;
        let factor = [ScalingFactor::ONE_QUARTER, ScalingFactor::ONE_HALF]
            .into_iter()
            .find(|f| f.scale(header.width) >= width && f.scale(header.height) >= height)
            .unwrap_or(ScalingFactor::ONE);
        decompressor.set_scaling_factor(factor)?;
        let scaled = header.scaled(factor);
        let pitch = scaled.width * PixelFormat::RGB.size();
        pixels.resize(pitch * scaled.height, 0);
        let image = Image {
            pixels: &mut pixels[..],
            width: scaled.width,
            pitch,
            height: scaled.height,
            format: PixelFormat::RGB,
        };
        decompressor.decompress(jpeg, image)?;
        std::hint::black_box(&pixels);
        Ok(())
    })?;
    Ok(Some(ms))
}

/// ms per PNG class map of `path` (the drive's `superpixels` sidecar) decoded alone, by
/// the `png` crate into a reused buffer and by the pipeline's own reader of grey PNGs
/// (`decode::image`); `None` without PNGs.
pub fn png_ms(path: &Path) -> anyhow::Result<Option<(f64, f64)>> {
    let pngs = compressed_images(path, "png")?;
    if pngs.is_empty() {
        return Ok(None);
    }
    let mut pixels = Vec::new();
    let png_crate = ms_per_item(&pngs, |png| {
        let cursor = std::io::Cursor::new(&png.data[..]);
        let mut reader = png::Decoder::new(cursor).read_info()?;
        pixels.resize(reader.output_buffer_size().unwrap_or(0), 0);
        reader.next_frame(&mut pixels)?;
        std::hint::black_box(&pixels);
        Ok(())
    })?;
    let pipeline = ms_per_item(&pngs, |png| {
        std::hint::black_box(decode_foxglove_compressed(png, Target::Mono)?);
        Ok(())
    })?;
    Ok(Some((png_crate, pipeline)))
}
