//! Tests of the image decoders, by concern: JPEG, PNG, format strings and magic bytes,
//! raw encodings, and robustness. This file holds the shared fixtures (messages, test
//! images, encoders).

use super::*;
use crate::decode::foxglove::{self, Timestamp};
use crate::decode::ros2::{self, Header, Ros2Time};
use superflow_schemas::Stamp;
use superflow_schemas::sensor::{Image, PixelFormat};

mod format;
mod jpeg;
mod png;
mod raw;
mod robustness;

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
    color: ::png::ColorType,
    depth: ::png::BitDepth,
    palette: Option<Vec<u8>>,
) -> Vec<u8> {
    let mut out = Vec::new();
    {
        let mut encoder = ::png::Encoder::new(&mut out, width, height);
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

fn png8(data: &[u8], width: u32, height: u32, color: ::png::ColorType) -> Vec<u8> {
    png_bytes(data, width, height, color, ::png::BitDepth::Eight, None)
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
