//! Image encoders of the writers: camera images as baseline JPEG, class maps as 8-bit
//! grey PNG, and whole cameras' frames encoded in parallel (the bytes are the same as
//! encoding one after another).

use crate::error::{GenerateError, Result};
use crate::options::JpegCoding;
use crate::render::CameraFrame;
use crate::sample_drive::JPEG_QUALITY;
use rayon::prelude::*;
use superflow_schemas::sensor::{Image, PixelFormat};

/// Encodes an RGB8 image as a baseline JPEG coded as `coding` says (deterministic:
/// scalar code path).
pub fn encode_jpeg(image: &Image, coding: JpegCoding) -> Result<Vec<u8>> {
    let mut out = Vec::new();
    let mut encoder = jpeg_encoder::Encoder::new(&mut out, JPEG_QUALITY);
    encoder.set_optimized_huffman_tables(coding == JpegCoding::OptimizedPerComponent);
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
pub fn jpegs(frames: &[CameraFrame], coding: JpegCoding) -> Result<Vec<Vec<u8>>> {
    frames
        .par_iter()
        .map(|f| encode_jpeg(&f.image, coding))
        .collect()
}

/// The PNG of every frame's class map, in order.
pub fn class_map_pngs(frames: &[CameraFrame]) -> Result<Vec<Vec<u8>>> {
    frames
        .par_iter()
        .map(|f| encode_png_mono(&f.classes))
        .collect()
}

#[cfg(test)]
mod tests {
    #![allow(clippy::unwrap_used, clippy::expect_used)] // tests fail loudly on purpose
    use crate::dialect::Dialect;
    use crate::generate::generate_with;
    use crate::options::{ClassMapStorage, DriveOptions, JpegCoding};
    use prost::Message as _;
    use superflow_schemas::ros2;

    /// A class map as read back: topic, log time, stamp, frame id and class ids.
    type ClassMap = (String, u64, i64, String, Vec<u8>);

    fn decode_png(data: &[u8]) -> Vec<u8> {
        let mut decoder = png::Decoder::new(std::io::Cursor::new(data));
        decoder.set_transformations(png::Transformations::IDENTITY);
        let mut reader = decoder.read_info().unwrap();
        let info = reader.info();
        assert_eq!(info.color_type, png::ColorType::Grayscale);
        assert_eq!(info.bit_depth, png::BitDepth::Eight);
        let mut out = vec![0; reader.output_buffer_size().unwrap()];
        let frame = reader.next_frame(&mut out).unwrap();
        out.truncate(frame.buffer_size());
        out
    }

    /// Every class map of `mcap`, decoded.
    fn class_maps(mcap: &[u8], dialect: Dialect) -> Vec<ClassMap> {
        let mut out = Vec::new();
        for message in mcap::MessageStream::new(mcap).unwrap() {
            let m = message.unwrap();
            if !m.channel.topic.ends_with("/superpixels") {
                continue;
            }
            let schema = m.channel.schema.as_ref().unwrap().name.clone();
            let (stamp, frame_id, classes) = match (dialect, schema.as_str()) {
                (Dialect::Foxglove, "foxglove.RawImage") => {
                    let image = foxglove::messages::RawImage::decode(&m.data[..]).unwrap();
                    let t = image.timestamp.unwrap();
                    let stamp = i64::from(t.sec()) * 1_000_000_000 + i64::from(t.nsec());
                    (stamp, image.frame_id, image.data.to_vec())
                }
                (Dialect::Foxglove, "foxglove.CompressedImage") => {
                    let image = foxglove::messages::CompressedImage::decode(&m.data[..]).unwrap();
                    assert_eq!(image.format, "png");
                    let t = image.timestamp.unwrap();
                    let stamp = i64::from(t.sec()) * 1_000_000_000 + i64::from(t.nsec());
                    (stamp, image.frame_id, decode_png(&image.data))
                }
                (Dialect::Ros2, "sensor_msgs/msg/Image") => {
                    let image: ros2::Image = ros2::decode(&m.data).unwrap();
                    let h = image.header;
                    (h.stamp.as_nanos(), h.frame_id, image.data)
                }
                (Dialect::Ros2, "sensor_msgs/msg/CompressedImage") => {
                    let image: ros2::CompressedImage = ros2::decode(&m.data).unwrap();
                    assert_eq!(image.format, "png");
                    let h = image.header;
                    (h.stamp.as_nanos(), h.frame_id, decode_png(&image.data))
                }
                other => panic!("class map of schema {other:?}"),
            };
            out.push((
                m.channel.topic.to_string(),
                m.log_time,
                stamp,
                frame_id,
                classes,
            ));
        }
        out
    }

    /// The markers of a JPEG up to its end (entropy-coded `FF` bytes are stuffed, so
    /// every `FF xx` with `xx` not 0 or a restart is a marker).
    fn markers(jpeg: &[u8]) -> Vec<u8> {
        jpeg.windows(2)
            .filter(|w| w[0] == 0xFF && w[1] != 0 && !(0xD0..=0xD7).contains(&w[1]))
            .map(|w| w[1])
            .collect()
    }

    #[test]
    fn jpeg_codings_write_one_scan_or_one_per_component() {
        let (width, height) = (64u32, 48u32);
        let image = superflow_schemas::sensor::Image::new(
            superflow_schemas::Stamp::from_nanos(0),
            "camera",
            width,
            height,
            superflow_schemas::sensor::PixelFormat::Rgb8,
            (0..width * height * 3)
                .map(|i| (i * 7 % 251) as u8)
                .collect(),
        )
        .unwrap();
        for (coding, scans) in [
            (JpegCoding::StandardInterleaved, 1),
            (JpegCoding::OptimizedPerComponent, 3),
        ] {
            let jpeg = super::encode_jpeg(&image, coding).unwrap();
            let markers = markers(&jpeg);
            assert_eq!(markers.first(), Some(&0xD8), "{coding:?}: starts with SOI");
            assert_eq!(markers.last(), Some(&0xD9), "{coding:?}: ends with EOI");
            assert_eq!(
                markers.iter().filter(|&&m| m == 0xC0).count(),
                1,
                "{coding:?}: one baseline frame"
            );
            let sos = markers.iter().filter(|&&m| m == 0xDA).count();
            assert_eq!(sos, scans, "{coding:?}");
        }
    }

    #[test]
    fn the_png_sidecar_holds_the_class_maps_of_the_drive() {
        for dialect in Dialect::ALL {
            let in_drive = generate_with(dialect, &DriveOptions::short()).unwrap();
            let options = DriveOptions {
                class_maps: ClassMapStorage::PngSidecar,
                ..DriveOptions::short()
            };
            let split = generate_with(dialect, &options).unwrap();
            assert!(in_drive.sidecar.is_none());
            let sidecar = split.sidecar.as_deref().expect("a sidecar");
            assert!(class_maps(&split.mcap, dialect).is_empty(), "{dialect:?}");
            let expected = class_maps(&in_drive.mcap, dialect);
            assert_eq!(expected.len(), 2 * 18, "{dialect:?}");
            assert!(class_maps(sidecar, dialect) == expected, "{dialect:?}");
            let truth = split.truth.sidecar.expect("sidecar truth");
            assert_eq!(Some(truth.file), options.sidecar_name(dialect));
            assert!(truth.channels.iter().all(|c| c.role == "superpixels"));
            assert_eq!(truth.channels.len(), 2);
            assert!(!split.truth.channels.iter().any(|c| c.role == "superpixels"));
        }
    }
}
