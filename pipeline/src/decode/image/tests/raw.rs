//! Raw encodings: colour orders, row padding, class maps, unsupported encodings, size
//! errors, and Foxglove messages without a timestamp.

use super::*;

#[test]
fn raw_colour_encodings_come_out_rgb() {
    let (w, h) = (3, 2);
    let rgb = gradient(w, h);
    let bgr: Vec<u8> = rgb
        .chunks_exact(3)
        .flat_map(|p| [p[2], p[1], p[0]])
        .collect();
    let rgba: Vec<u8> = rgb
        .chunks_exact(3)
        .flat_map(|p| [p[0], p[1], p[2], 7])
        .collect();
    let bgra: Vec<u8> = rgb
        .chunks_exact(3)
        .flat_map(|p| [p[2], p[1], p[0], 7])
        .collect();
    let cases: [(&str, &Vec<u8>, u32); 7] = [
        ("rgb8", &rgb, 3),
        ("bgr8", &bgr, 3),
        ("8UC3", &bgr, 3),
        ("rgba8", &rgba, 4),
        ("bgra8", &bgra, 4),
        ("8UC4", &bgra, 4),
        ("BGR8", &bgr, 3),
    ];
    for (encoding, data, bpp) in cases {
        let image = decode_ros2_raw(
            &ros2_raw(encoding, w, h, w * bpp, data.clone()),
            Target::Rgb,
        )
        .unwrap_or_else(|e| panic!("{encoding}: {e}"));
        assert_eq!(image.format, PixelFormat::Rgb8);
        assert_eq!(image.data, rgb, "{encoding}");
        let image =
            decode_foxglove_raw(&fox_raw(encoding, w, h, w * bpp, data.clone()), Target::Rgb)
                .unwrap();
        assert_eq!(image.data, rgb, "{encoding}");
    }
    // A pure red pixel in each layout.
    for (encoding, px) in [
        ("rgb8", vec![255, 0, 0]),
        ("bgr8", vec![0, 0, 255]),
        ("8UC3", vec![0, 0, 255]),
        ("rgba8", vec![255, 0, 0, 0]),
        ("bgra8", vec![0, 0, 255, 0]),
    ] {
        let image =
            decode_ros2_raw(&ros2_raw(encoding, 1, 1, px.len() as u32, px), Target::Rgb).unwrap();
        assert_red(&image);
    }
}

#[test]
fn raw_rows_with_padding_are_unpadded() {
    let (w, h) = (3, 3);
    let rgb = gradient(w, h);
    let step = w * 3 + 5;
    let mut padded = Vec::new();
    for row in rgb.chunks(9) {
        padded.extend_from_slice(row);
        padded.extend_from_slice(&[0xEE; 5]);
    }
    let image =
        decode_ros2_raw(&ros2_raw("rgb8", w, h, step, padded.clone()), Target::Rgb).unwrap();
    assert_eq!(image.data, rgb);
    // The last row's padding may be missing.
    padded.truncate(padded.len() - 5);
    let image = decode_foxglove_raw(&fox_raw("rgb8", w, h, step, padded), Target::Rgb).unwrap();
    assert_eq!(image.data, rgb);
    // step 0: tightly packed.
    let image = decode_foxglove_raw(&fox_raw("rgb8", w, h, 0, rgb.clone()), Target::Rgb).unwrap();
    assert_eq!(image.data, rgb);
}

#[test]
fn raw_mono_class_map_is_kept_exact() {
    let (w, h) = (16u32, 16u32);
    let ids: Vec<u8> = (0..=255).collect();
    let step = w + 3;
    let padded: Vec<u8> = ids
        .chunks(16)
        .flat_map(|r| [r, &[9, 9, 9][..]].concat())
        .collect();
    for encoding in ["mono8", "8UC1"] {
        let image = decode_ros2_raw(
            &ros2_raw(encoding, w, h, step, padded.clone()),
            Target::Mono,
        )
        .unwrap();
        assert_eq!(image.format, PixelFormat::Mono8);
        assert_eq!(image.data, ids);
        let image =
            decode_foxglove_raw(&fox_raw(encoding, w, h, w, ids.clone()), Target::Mono).unwrap();
        assert_eq!(image.data, ids);
    }
    let rgb = decode_ros2_raw(&ros2_raw("mono8", w, h, w, ids.clone()), Target::Rgb).unwrap();
    assert_eq!(
        rgb.data,
        ids.iter().flat_map(|&g| [g, g, g]).collect::<Vec<u8>>()
    );
    // Colour to a class map is an error.
    for encoding in ["rgb8", "bgr8", "8UC3", "rgba8"] {
        let err = named(
            decode_ros2_raw(
                &ros2_raw(
                    encoding,
                    1,
                    1,
                    4,
                    vec![1, 2, 3, 4][..if encoding == "rgba8" { 4 } else { 3 }].to_vec(),
                ),
                Target::Mono,
            )
            .unwrap_err(),
        );
        assert!(matches!(err, ImageError::NotMono { .. }), "{err}");
    }
}

#[test]
fn unsupported_raw_encodings_are_clear_errors() {
    for (encoding, expect) in [
        ("mono16", "16 bits"),
        ("16UC1", "more than 8 bits"),
        ("32FC1", "more than 8 bits"),
        ("rgb16", "16 bits"),
        ("bayer_rggb8", "Bayer"),
        ("bayer_grbg16", "Bayer"),
        ("yuv422", "YUV"),
        ("uyvy", "YUV"),
        ("8UC2", "channels"),
        ("", "no encoding"),
        ("hsv8", "unknown"),
    ] {
        for target in [Target::Rgb, Target::Mono] {
            let err = named(
                decode_ros2_raw(&ros2_raw(encoding, 2, 2, 4, vec![0; 8]), target).unwrap_err(),
            );
            assert!(
                matches!(err, ImageError::UnsupportedEncoding { .. }),
                "{err}"
            );
            let msg = err.to_string();
            assert!(
                msg.contains("unsupported encoding") && msg.contains(expect),
                "{msg}"
            );
            assert!(msg.contains(&format!("`{encoding}`")), "{msg}");
        }
    }
}

#[test]
fn raw_size_errors() {
    // Zero size.
    let err =
        named(decode_ros2_raw(&ros2_raw("rgb8", 0, 4, 0, Vec::new()), Target::Rgb).unwrap_err());
    assert!(matches!(err, ImageError::ZeroSize { .. }), "{err}");
    let err = named(
        decode_foxglove_raw(&fox_raw("mono8", 4, 0, 4, Vec::new()), Target::Mono).unwrap_err(),
    );
    assert!(matches!(err, ImageError::ZeroSize { .. }), "{err}");
    // Step too small.
    let err =
        named(decode_ros2_raw(&ros2_raw("rgb8", 4, 2, 11, vec![0; 22]), Target::Rgb).unwrap_err());
    assert!(
        matches!(
            err,
            ImageError::StepTooSmall {
                step: 11,
                row_bytes: 12,
                ..
            }
        ),
        "{err}"
    );
    // Data too short, and too long.
    let err =
        named(decode_ros2_raw(&ros2_raw("rgb8", 4, 2, 12, vec![0; 23]), Target::Rgb).unwrap_err());
    assert!(
        matches!(err, ImageError::DataLength { got: 23, .. }),
        "{err}"
    );
    let err =
        named(decode_ros2_raw(&ros2_raw("bgr8", 4, 2, 12, vec![0; 25]), Target::Rgb).unwrap_err());
    assert!(
        matches!(err, ImageError::DataLength { got: 25, .. }),
        "{err}"
    );
    let err = named(
        decode_foxglove_raw(&fox_raw("mono8", 4, 2, 0, vec![0; 7]), Target::Mono).unwrap_err(),
    );
    assert!(matches!(err, ImageError::DataLength { .. }), "{err}");
    // Absurd sizes: rejected before anything is allocated.
    for (w, h, step) in [
        (u32::MAX, u32::MAX, u32::MAX),
        (100_000, 100_000, 0),
        (1 << 20, 1 << 10, 0),
    ] {
        let err = named(
            decode_ros2_raw(&ros2_raw("rgb8", w, h, step, vec![0; 16]), Target::Rgb).unwrap_err(),
        );
        assert!(matches!(err, ImageError::TooLarge { .. }), "{err}");
    }
    // Huge step with a single row is a length error, not an overflow.
    let err = decode_ros2_raw(&ros2_raw("mono8", 2, 1, u32::MAX, vec![0; 2]), Target::Mono);
    assert_eq!(err.unwrap().data, [0, 0]);
    let err =
        decode_ros2_raw(&ros2_raw("mono8", 2, 3, u32::MAX, vec![0; 6]), Target::Mono).unwrap_err();
    assert!(matches!(err, ImageError::DataLength { .. }), "{err}");
}

#[test]
fn foxglove_without_timestamp_is_an_error() {
    let mut msg = fox_raw("mono8", 1, 1, 1, vec![0]);
    msg.timestamp = None;
    let err = decode_foxglove_raw(&msg, Target::Mono).unwrap_err();
    assert!(matches!(err, ImageError::Timestamp { .. }), "{err}");
    assert!(err.to_string().contains(FRAME), "{err}");
    let mut msg = fox_compressed("png", Vec::new());
    msg.timestamp = None;
    assert!(decode_foxglove_compressed(&msg, Target::Rgb).is_err());
}
