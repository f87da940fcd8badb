//! Format strings and magic bytes: parsing, `compressedDepth`, unsupported and unknown
//! formats, and disagreement between the two.

use super::*;
use crate::decode::image::format::{Declared, FormatHint};

#[test]
fn format_strings_parse() {
    let p = FormatHint::parse;
    assert_eq!(p("jpeg").declared, Declared::Codec(Codec::Jpeg));
    assert_eq!(p(" PNG ").declared, Declared::Codec(Codec::Png));
    assert_eq!(p("").declared, Declared::Unspecified);
    assert_eq!(p("webp").declared, Declared::Other);
    let it = p("rgb8; jpeg compressed bgr8");
    assert_eq!(
        (it.declared, it.swap_red_blue, it.depth),
        (Declared::Codec(Codec::Jpeg), false, false)
    );
    let it = p("bgr8; png compressed rgb8");
    assert_eq!(
        (it.declared, it.swap_red_blue),
        (Declared::Codec(Codec::Png), true)
    );
    let it = p("mono8; png compressed ");
    assert_eq!(
        (it.declared, it.swap_red_blue),
        (Declared::Codec(Codec::Png), false)
    );
    assert!(p("16UC1; compressedDepth").depth);
    assert!(p("32FC1; compressedDepth png").depth);
    assert_eq!(p("rgb8; qoi compressed bgr8").declared, Declared::Other);
}

#[test]
fn compressed_depth_is_rejected_even_with_png_bytes() {
    let bytes = png8(&[1, 2, 3, 4], 2, 2, ::png::ColorType::Grayscale);
    for format in [
        "16UC1; compressedDepth",
        "32FC1; compressedDepth png",
        "16UC1; compressedDepth rvl",
    ] {
        let err = named(
            decode_ros2_compressed(&ros2_compressed(format, bytes.clone()), Target::Mono)
                .unwrap_err(),
        );
        assert!(matches!(err, ImageError::CompressedDepth { .. }), "{err}");
        assert!(err.to_string().contains("compressedDepth"));
    }
}

#[test]
fn webp_and_avif_are_unsupported() {
    let webp = b"RIFF\x10\x00\x00\x00WEBPVP8 ".to_vec();
    for format in ["webp", "avif", "rgb8; qoi compressed bgr8"] {
        let err = named(
            decode_foxglove_compressed(&fox_compressed(format, webp.clone()), Target::Rgb)
                .unwrap_err(),
        );
        assert!(matches!(err, ImageError::UnsupportedFormat { .. }), "{err}");
        assert!(err.to_string().contains(format), "{err}");
    }
    // A mislabelled JPEG is still decoded.
    let bytes = jpeg(&solid(8, 8, RED), 8, 8, jpeg_encoder::ColorType::Rgb);
    assert_red(&decode_foxglove_compressed(&fox_compressed("webp", bytes), Target::Rgb).unwrap());
}

#[test]
fn unknown_format_names_the_bytes() {
    let err = named(
        decode_ros2_compressed(&ros2_compressed("", b"hello world".to_vec()), Target::Rgb)
            .unwrap_err(),
    );
    assert!(matches!(err, ImageError::UnknownFormat { .. }), "{err}");
    assert!(err.to_string().contains("68 65 6C 6C"), "{err}");
    let err =
        named(decode_ros2_compressed(&ros2_compressed("", Vec::new()), Target::Rgb).unwrap_err());
    assert!(
        matches!(err, ImageError::UnknownFormat { len: 0, .. }),
        "{err}"
    );
    // Declared JPEG, not JPEG bytes: the JPEG decoder's error.
    let err = named(
        decode_ros2_compressed(
            &ros2_compressed("jpeg", b"hello world".to_vec()),
            Target::Rgb,
        )
        .unwrap_err(),
    );
    assert!(
        matches!(
            err,
            ImageError::Corrupt {
                codec: Codec::Jpeg,
                ..
            }
        ),
        "{err}"
    );
    let err = named(
        decode_ros2_compressed(&ros2_compressed("png", Vec::new()), Target::Rgb).unwrap_err(),
    );
    assert!(
        matches!(
            err,
            ImageError::Corrupt {
                codec: Codec::Png,
                ..
            }
        ),
        "{err}"
    );
}

#[test]
fn disagreement_is_reported_when_neither_codec_works() {
    let bytes = jpeg(&gradient(32, 32), 32, 32, jpeg_encoder::ColorType::Rgb);
    let truncated = bytes[..bytes.len() / 2].to_vec();
    let err = named(
        decode_ros2_compressed(&ros2_compressed("png", truncated.clone()), Target::Rgb)
            .unwrap_err(),
    );
    assert!(
        matches!(
            err,
            ImageError::FormatMismatch {
                sniffed: Codec::Jpeg,
                ..
            }
        ),
        "{err}"
    );
    let msg = err.to_string();
    assert!(msg.contains("JPEG") && msg.contains("`png`"), "{msg}");
    // Same codec declared: plain decoder error, no disagreement to report.
    let err = decode_ros2_compressed(&ros2_compressed("jpeg", truncated.clone()), Target::Rgb)
        .unwrap_err();
    assert!(matches!(err, ImageError::Corrupt { .. }), "{err}");
    let err = decode_ros2_compressed(&ros2_compressed("", truncated), Target::Rgb).unwrap_err();
    assert!(matches!(err, ImageError::Corrupt { .. }), "{err}");
}
