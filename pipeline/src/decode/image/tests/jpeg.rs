//! JPEG: colours, grey, truncation and absurd sizes.

use super::*;

/// Camera JPEGs are chroma-subsampled (4:2:0) with optimized Huffman tables, as the
/// sample drives' are; zune-jpeg 0.5.15 decoded those to green, which this catches.
#[test]
fn subsampled_camera_jpegs_keep_their_colours() {
    let (w, h) = (64usize, 48usize);
    let mut rgb = Vec::with_capacity(w * h * 3);
    for y in 0..h {
        for x in 0..w {
            let (r, g, b) = if x < w / 2 {
                (140u8, 140u8, 145u8)
            } else {
                (200, 40, 30)
            };
            let _ = y;
            rgb.extend_from_slice(&[r, g, b]);
        }
    }
    let mut bytes = Vec::new();
    let mut encoder = jpeg_encoder::Encoder::new(&mut bytes, 80);
    encoder.set_optimized_huffman_tables(true);
    encoder.set_sampling_factor(jpeg_encoder::SamplingFactor::F_2_2);
    encoder
        .encode(&rgb, w as u16, h as u16, jpeg_encoder::ColorType::Rgb)
        .unwrap();
    let msg = foxglove::CompressedImage {
        timestamp: Some(Timestamp::new(1, 0)),
        frame_id: "cam".into(),
        data: bytes.into(),
        format: "jpeg".into(),
    };
    let image = decode_foxglove_compressed(&msg, Target::Rgb).unwrap();
    for (x, expected) in [(8u32, [140i32, 140, 145]), (56, [200, 40, 30])] {
        let got = image.pixel(x, 20).unwrap();
        for c in 0..3 {
            assert!(
                (i32::from(got[c]) - expected[c]).abs() <= 6,
                "pixel {x}: {got:?} vs {expected:?}"
            );
        }
    }
}

#[test]
fn jpeg_decodes_to_rgb_within_tolerance() {
    let (w, h) = (64, 48);
    let rgb = gradient(w, h);
    let bytes = jpeg(&rgb, w as u16, h as u16, jpeg_encoder::ColorType::Rgb);
    for format in [
        "jpeg",
        "JPEG",
        "jpg",
        "rgb8; jpeg compressed bgr8",
        "bgr8; jpeg compressed bgr8",
        "",
    ] {
        let image = decode_ros2_compressed(&ros2_compressed(format, bytes.clone()), Target::Rgb)
            .unwrap_or_else(|e| panic!("{format}: {e}"));
        assert_eq!(
            (image.width, image.height, image.format),
            (w, h, PixelFormat::Rgb8)
        );
        assert_eq!(image.frame_id, FRAME);
        assert_eq!(image.stamp, stamp());
        let diff = max_abs_diff(&image.data, &rgb);
        assert!(diff <= 8, "{format}: max abs diff {diff}");
    }
}

#[test]
fn red_stays_red_in_every_jpeg_path() {
    let (w, h) = (16, 16);
    let bytes = jpeg(
        &solid(w, h, RED),
        w as u16,
        h as u16,
        jpeg_encoder::ColorType::Rgb,
    );
    for format in [
        "jpeg",
        "rgb8; jpeg compressed bgr8",
        "bgr8; jpeg compressed bgr8",
        "png",
    ] {
        assert_red(
            &decode_ros2_compressed(&ros2_compressed(format, bytes.clone()), Target::Rgb).unwrap(),
        );
    }
    assert_red(
        &decode_foxglove_compressed(&fox_compressed("jpeg", bytes.clone()), Target::Rgb).unwrap(),
    );
    // A JPEG written from BGR samples (as cv::imencode does with a bgr8 Mat) is a
    // standard JPEG: still red.
    let bgr = jpeg(
        &solid(w, h, [0, 0, 255]),
        w as u16,
        h as u16,
        jpeg_encoder::ColorType::Bgr,
    );
    assert_red(
        &decode_ros2_compressed(
            &ros2_compressed("rgb8; jpeg compressed bgr8", bgr),
            Target::Rgb,
        )
        .unwrap(),
    );
    // An `rgb8` target: an RGB Mat handed to cv::imencode, stored channel-swapped
    // (the file holds blue where the image is red) and swapped back on decode.
    let swapped = jpeg(
        &solid(w, h, BLUE),
        w as u16,
        h as u16,
        jpeg_encoder::ColorType::Rgb,
    );
    assert_red(
        &decode_ros2_compressed(
            &ros2_compressed("rgb8; jpeg compressed rgb8", swapped),
            Target::Rgb,
        )
        .unwrap(),
    );
}

#[test]
fn grey_jpeg_decodes_to_mono_and_to_replicated_rgb() {
    let (w, h) = (32, 24);
    let grey: Vec<u8> = (0..w * h).map(|i| (50 + (i % w) * 4) as u8).collect();
    let bytes = jpeg(&grey, w as u16, h as u16, jpeg_encoder::ColorType::Luma);
    let mono = decode_ros2_compressed(
        &ros2_compressed("mono8; jpeg compressed ", bytes.clone()),
        Target::Mono,
    )
    .unwrap();
    assert_eq!(mono.format, PixelFormat::Mono8);
    assert!(max_abs_diff(&mono.data, &grey) <= 8);
    let rgb = decode_ros2_compressed(&ros2_compressed("jpeg", bytes), Target::Rgb).unwrap();
    assert_eq!(rgb.format, PixelFormat::Rgb8);
    for (px, g) in rgb.data.chunks_exact(3).zip(&grey) {
        assert!(px[0] == px[1] && px[1] == px[2], "{px:?}");
        assert!(px[0].abs_diff(*g) <= 8);
    }
}

#[test]
fn colour_jpeg_to_mono_is_an_error() {
    let bytes = jpeg(&gradient(8, 8), 8, 8, jpeg_encoder::ColorType::Rgb);
    let err =
        named(decode_ros2_compressed(&ros2_compressed("jpeg", bytes), Target::Mono).unwrap_err());
    assert!(matches!(err, ImageError::NotMono { .. }), "{err}");
}

#[test]
fn truncated_and_garbage_jpeg_are_errors() {
    let bytes = jpeg(&gradient(64, 64), 64, 64, jpeg_encoder::ColorType::Rgb);
    for len in [2, 20, bytes.len() / 2, bytes.len() - 10, bytes.len() - 2] {
        let err =
            decode_ros2_compressed(&ros2_compressed("jpeg", bytes[..len].to_vec()), Target::Rgb)
                .expect_err(&format!("truncated to {len}"));
        let err = named(err);
        assert!(
            matches!(
                err,
                ImageError::Corrupt {
                    codec: Codec::Jpeg,
                    ..
                }
            ),
            "{len}: {err}"
        );
    }
    let mut garbage = vec![0xFF, 0xD8];
    garbage.extend((0..500u32).map(|i| (i.wrapping_mul(2_654_435_761) >> 13) as u8));
    let err =
        named(decode_ros2_compressed(&ros2_compressed("jpeg", garbage), Target::Rgb).unwrap_err());
    assert!(matches!(err, ImageError::Corrupt { .. }), "{err}");
}

#[test]
fn absurd_jpeg_dimensions_are_rejected_before_allocating() {
    let mut bytes = jpeg(&gradient(8, 8), 8, 8, jpeg_encoder::ColorType::Rgb);
    let sof = bytes.windows(2).position(|w| w == [0xFF, 0xC0]).unwrap();
    // SOF0: FF C0, length (2), precision (1), height (2), width (2). 65 000 × 65 000
    // RGB is 12.7 GB: over MAX_IMAGE_BYTES.
    bytes[sof + 5..sof + 9].copy_from_slice(&[0xFD, 0xE8, 0xFD, 0xE8]);
    let err = named(
        decode_ros2_compressed(&ros2_compressed("jpeg", bytes.clone()), Target::Rgb).unwrap_err(),
    );
    assert!(matches!(err, ImageError::TooLarge { .. }), "{err}");
    // Beyond JPEG's own 65 500-pixel limit, libjpeg-turbo refuses the header itself.
    bytes[sof + 5..sof + 9].copy_from_slice(&[0xFF, 0xFF, 0xFF, 0xFF]);
    let err =
        named(decode_ros2_compressed(&ros2_compressed("jpeg", bytes), Target::Rgb).unwrap_err());
    assert!(
        matches!(&err, ImageError::Corrupt { reason, .. } if reason.to_string().contains("dimension")),
        "{err}"
    );
}

/// A 1600×900 street-like test card as a 4:2:0 quality-85 JPEG (what nuScenes cameras
/// store): smooth gradients, hard edges and fine texture.
fn camera_jpeg(w: usize, h: usize) -> Vec<u8> {
    let rgb: Vec<u8> = (0..w * h)
        .flat_map(|i| {
            let (x, y) = (i % w, i / w);
            let edge = if (x / 97 + y / 61) % 2 == 0 { 60 } else { 0 };
            let texture = ((x * 7 + y * 13) % 23) as u8;
            [
                (x * 200 / w) as u8 + texture,
                (y * 180 / h) as u8 + edge,
                (((x ^ y) % 64) as u8 * 3).wrapping_add(edge),
            ]
        })
        .collect();
    let mut bytes = Vec::new();
    let mut encoder = jpeg_encoder::Encoder::new(&mut bytes, 85);
    encoder.set_sampling_factor(jpeg_encoder::SamplingFactor::F_2_2);
    encoder
        .encode(&rgb, w as u16, h as u16, jpeg_encoder::ColorType::Rgb)
        .unwrap();
    bytes
}

/// Mean and largest absolute difference of two equally long byte slices.
fn mean_and_max_diff(a: &[u8], b: &[u8]) -> (f64, u8) {
    assert_eq!(a.len(), b.len());
    let sum: u64 = a
        .iter()
        .zip(b)
        .map(|(x, y)| u64::from(x.abs_diff(*y)))
        .sum();
    (sum as f64 / a.len() as f64, max_abs_diff(a, b))
}

#[test]
fn reduced_scale_decodes_average_the_full_decode() {
    use crate::sample::image_ops::resize_bilinear;
    let (w, h) = (1600usize, 900usize);
    let msg = ros2_compressed("jpeg", camera_jpeg(w, h));
    let decode = |scale| decode_ros2_compressed_scaled(&msg, Target::Rgb, scale).unwrap();
    let full = decode(Scale::Full);
    assert_eq!(
        (full.image.width, full.image.height, full.native),
        (1600, 900, (1600, 900))
    );
    // 448×224 is reached by 1/2 (800×450), not by 1/4 (400×225).
    let half = decode(Scale::AtLeast {
        width: 448,
        height: 224,
    });
    assert_eq!(
        (half.image.width, half.image.height, half.native),
        (800, 450, (1600, 900))
    );
    let quarter = decode(Scale::AtLeast {
        width: 400,
        height: 225,
    });
    assert_eq!((quarter.image.width, quarter.image.height), (400, 225));
    // Nothing smaller than asked: an 800×450 request of an 800×450 image stays whole.
    let small = ros2_compressed("jpeg", camera_jpeg(800, 450));
    let same = decode_ros2_compressed_scaled(
        &small,
        Target::Rgb,
        Scale::AtLeast {
            width: 448,
            height: 224,
        },
    )
    .unwrap();
    assert_eq!((same.image.width, same.image.height), (800, 450));

    // The 1/2 decode is the full decode averaged 2×2, up to the IDCT's rounding.
    let boxed = resize_bilinear(&full.image.data, w, h, 3, w / 2, h / 2);
    let (mean, max) = mean_and_max_diff(&half.image.data, &boxed);
    eprintln!("1/2 decode vs full decode averaged 2x2: mean {mean:.3}, max {max}");
    assert!(
        mean < 3.0,
        "1/2 decode vs full decode averaged 2x2: mean {mean:.3}"
    );
    // What a sample sees: both resized to 448×224.
    let from_full = resize_bilinear(&full.image.data, w, h, 3, 448, 224);
    let from_half = resize_bilinear(&half.image.data, w / 2, h / 2, 3, 448, 224);
    let (mean, max) = mean_and_max_diff(&from_half, &from_full);
    eprintln!("448x224 from the 1/2 decode vs from the full decode: mean {mean:.3}, max {max}");
    // The bilinear resize of the full decode skips pixels (no antialiasing), the DCT
    // scaling averages them: they differ at fine texture and hard edges only (this test
    // card is mostly both; a wrong decode, e.g. a chroma shift, is off by tens).
    assert!(mean < 2.0, "resized from 1/2 vs from full: mean {mean:.3}");
}
