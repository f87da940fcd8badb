//! PNG: every colour type and bit depth, class maps, truncation and absurd sizes.

use super::*;

#[test]
fn png_rgb_and_rgba_decode_exactly() {
    let (w, h) = (7, 5);
    let rgb = gradient(w, h);
    let bytes = png8(&rgb, w, h, ::png::ColorType::Rgb);
    for format in [
        "png",
        "PNG",
        "",
        "jpeg",
        "rgb8; png compressed bgr8",
        "bgr8; png compressed bgr8",
    ] {
        let image = decode_ros2_compressed(&ros2_compressed(format, bytes.clone()), Target::Rgb)
            .unwrap_or_else(|e| panic!("{format}: {e}"));
        assert_eq!((image.width, image.height), (w, h));
        assert_eq!(image.data, rgb, "{format}");
    }
    let rgba: Vec<u8> = rgb
        .chunks_exact(3)
        .flat_map(|p| [p[0], p[1], p[2], 17])
        .collect();
    let bytes = png8(&rgba, w, h, ::png::ColorType::Rgba);
    for format in ["png", "bgra8; png compressed bgra8"] {
        let image = decode_foxglove_compressed(&fox_compressed(format, bytes.clone()), Target::Rgb)
            .unwrap();
        assert_eq!(image.data, rgb, "{format}");
    }
}

#[test]
fn red_stays_red_in_every_png_path() {
    let (w, h) = (3, 2);
    // image_transport's bgr8/bgra8 targets: cv::imencode writes a standard RGB(A) PNG
    // (OpenCV's PNG encoder calls png_set_bgr), so the file holds red as red.
    let red = png8(&solid(w, h, RED), w, h, ::png::ColorType::Rgb);
    for format in [
        "png",
        "rgb8; png compressed bgr8",
        "bgr8; png compressed bgr8",
        "8UC3; png compressed bgr8",
        "",
    ] {
        assert_red(
            &decode_ros2_compressed(&ros2_compressed(format, red.clone()), Target::Rgb).unwrap(),
        );
    }
    let red16: Vec<u8> = RED
        .iter()
        .flat_map(|&c| [c, c])
        .collect::<Vec<u8>>()
        .repeat((w * h) as usize);
    let red16 = png_bytes(
        &red16,
        w,
        h,
        ::png::ColorType::Rgb,
        ::png::BitDepth::Sixteen,
        None,
    );
    assert_red(
        &decode_ros2_compressed(
            &ros2_compressed("rgb16; png compressed bgr16", red16),
            Target::Rgb,
        )
        .unwrap(),
    );
    let red_rgba = png8(
        &[255, 0, 0, 255].repeat((w * h) as usize),
        w,
        h,
        ::png::ColorType::Rgba,
    );
    assert_red(
        &decode_ros2_compressed(
            &ros2_compressed("rgba8; png compressed bgra8", red_rgba),
            Target::Rgb,
        )
        .unwrap(),
    );
    // An `rgb8` target: an RGB Mat through cv::imencode is stored channel-swapped.
    let swapped = png8(&solid(w, h, BLUE), w, h, ::png::ColorType::Rgb);
    assert_red(
        &decode_ros2_compressed(
            &ros2_compressed("rgb8; png compressed rgb8", swapped),
            Target::Rgb,
        )
        .unwrap(),
    );
    assert_red(&decode_foxglove_compressed(&fox_compressed("png", red), Target::Rgb).unwrap());
}

#[test]
fn mono_png_class_map_is_kept_exact() {
    let (w, h) = (16, 16);
    let ids: Vec<u8> = (0..=255).collect();
    let bytes = png8(&ids, w, h, ::png::ColorType::Grayscale);
    for format in ["png", "mono8; png compressed ", "8UC1; png compressed "] {
        let image =
            decode_ros2_compressed(&ros2_compressed(format, bytes.clone()), Target::Mono).unwrap();
        assert_eq!(image.format, PixelFormat::Mono8);
        assert_eq!(image.data, ids);
    }
    let image =
        decode_foxglove_compressed(&fox_compressed("png", bytes.clone()), Target::Mono).unwrap();
    assert_eq!(image.data, ids);
    // Mono to RGB replicates the channel.
    let rgb = decode_ros2_compressed(&ros2_compressed("png", bytes), Target::Rgb).unwrap();
    let expected: Vec<u8> = ids.iter().flat_map(|&g| [g, g, g]).collect();
    assert_eq!(rgb.data, expected);
    // Grey + alpha: alpha dropped, grey kept.
    let ga: Vec<u8> = ids.iter().flat_map(|&g| [g, 99]).collect();
    let bytes = png8(&ga, w, h, ::png::ColorType::GrayscaleAlpha);
    let image =
        decode_ros2_compressed(&ros2_compressed("png", bytes.clone()), Target::Mono).unwrap();
    assert_eq!(image.data, ids);
    let rgb = decode_ros2_compressed(&ros2_compressed("png", bytes), Target::Rgb).unwrap();
    assert_eq!(rgb.data, expected);
}

#[test]
fn low_bit_grey_png_keeps_ids_for_mono_and_scales_for_rgb() {
    // 2-bit grey, width 5: rows are packed and padded to a byte.
    let (w, h) = (5, 2);
    let values: [u8; 10] = [0, 1, 2, 3, 1, 3, 2, 1, 0, 2];
    let pack = |row: &[u8]| -> Vec<u8> {
        let mut bytes = vec![0u8; 2];
        for (i, v) in row.iter().enumerate() {
            bytes[i / 4] |= v << (6 - 2 * (i % 4));
        }
        bytes
    };
    let data: Vec<u8> = values.chunks(5).flat_map(pack).collect();
    let bytes = png_bytes(
        &data,
        w,
        h,
        ::png::ColorType::Grayscale,
        ::png::BitDepth::Two,
        None,
    );
    let mono =
        decode_ros2_compressed(&ros2_compressed("png", bytes.clone()), Target::Mono).unwrap();
    assert_eq!(mono.data, values);
    let rgb = decode_ros2_compressed(&ros2_compressed("png", bytes), Target::Rgb).unwrap();
    let expected: Vec<u8> = values.iter().flat_map(|&v| [v * 85; 3]).collect();
    assert_eq!(rgb.data, expected);
}

#[test]
fn palette_png_expands_for_rgb_and_gives_indices_for_mono() {
    let (w, h) = (4, 3);
    let palette = vec![0, 0, 0, 255, 0, 0, 0, 255, 0, 10, 20, 30];
    let indices: Vec<u8> = (0..w * h).map(|i| (i % 4) as u8).collect();
    let bytes = png_bytes(
        &indices,
        w,
        h,
        ::png::ColorType::Indexed,
        ::png::BitDepth::Eight,
        Some(palette.clone()),
    );
    let rgb = decode_ros2_compressed(&ros2_compressed("png", bytes.clone()), Target::Rgb).unwrap();
    let expected: Vec<u8> = indices
        .iter()
        .flat_map(|&i| palette[usize::from(i) * 3..usize::from(i) * 3 + 3].to_vec())
        .collect();
    assert_eq!(rgb.data, expected);
    assert_eq!(rgb.pixel(1, 0), Some(&RED[..]));
    let mono = decode_ros2_compressed(&ros2_compressed("png", bytes), Target::Mono).unwrap();
    assert_eq!(mono.data, indices);
    // 4-bit palette, odd width.
    let (w, h) = (3, 2);
    let indices = [1u8, 2, 3, 0, 1, 2];
    let data: Vec<u8> = indices
        .chunks(3)
        .flat_map(|r| [(r[0] << 4) | r[1], r[2] << 4])
        .collect();
    let bytes = png_bytes(
        &data,
        w,
        h,
        ::png::ColorType::Indexed,
        ::png::BitDepth::Four,
        Some(palette.clone()),
    );
    let mono =
        decode_ros2_compressed(&ros2_compressed("png", bytes.clone()), Target::Mono).unwrap();
    assert_eq!(mono.data, indices);
    let rgb = decode_ros2_compressed(&ros2_compressed("png", bytes), Target::Rgb).unwrap();
    assert_eq!(rgb.pixel(0, 0), Some(&RED[..]));
    assert_eq!(rgb.pixel(2, 0), Some(&[10u8, 20, 30][..]));
}

#[test]
fn sixteen_bit_png_converts_for_rgb_and_is_an_error_for_mono() {
    let (w, h) = (4, 2);
    let values: Vec<u16> = vec![0, 255, 256, 0x1234, 0x7FFF, 0x8000, 0xFF00, 0xFFFF];
    let data: Vec<u8> = values.iter().flat_map(|v| v.to_be_bytes()).collect();
    let bytes = png_bytes(
        &data,
        w,
        h,
        ::png::ColorType::Grayscale,
        ::png::BitDepth::Sixteen,
        None,
    );
    let rgb = decode_ros2_compressed(&ros2_compressed("png", bytes.clone()), Target::Rgb).unwrap();
    let expected: Vec<u8> = values.iter().flat_map(|v| [(v >> 8) as u8; 3]).collect();
    assert_eq!(rgb.data, expected);
    let err =
        named(decode_ros2_compressed(&ros2_compressed("png", bytes), Target::Mono).unwrap_err());
    assert!(matches!(err, ImageError::NotMono { .. }), "{err}");
    assert!(err.to_string().contains("16-bit"), "{err}");
    // 16-bit RGB.
    let rgb16: Vec<u8> = [0xABCDu16, 0x0102, 0xFFFF]
        .iter()
        .flat_map(|v| v.to_be_bytes())
        .collect();
    let bytes = png_bytes(
        &rgb16,
        1,
        1,
        ::png::ColorType::Rgb,
        ::png::BitDepth::Sixteen,
        None,
    );
    let image = decode_foxglove_compressed(&fox_compressed("png", bytes), Target::Rgb).unwrap();
    assert_eq!(image.data, [0xAB, 0x01, 0xFF]);
}

#[test]
fn colour_png_to_mono_is_an_error() {
    let bytes = png8(&gradient(2, 2), 2, 2, ::png::ColorType::Rgb);
    let err =
        named(decode_ros2_compressed(&ros2_compressed("png", bytes), Target::Mono).unwrap_err());
    assert!(matches!(err, ImageError::NotMono { .. }), "{err}");
}

/// CRC-32 (PNG chunks), for hand-made files.
fn crc32(bytes: &[u8]) -> u32 {
    let mut crc = 0xFFFF_FFFFu32;
    for &b in bytes {
        crc ^= u32::from(b);
        for _ in 0..8 {
            crc = if crc & 1 == 1 {
                (crc >> 1) ^ 0xEDB8_8320
            } else {
                crc >> 1
            };
        }
    }
    !crc
}

fn chunk(kind: &[u8; 4], body: &[u8]) -> Vec<u8> {
    let mut out = (body.len() as u32).to_be_bytes().to_vec();
    let mut typed = kind.to_vec();
    typed.extend_from_slice(body);
    out.extend_from_slice(&typed);
    out.extend_from_slice(&crc32(&typed).to_be_bytes());
    out
}

#[test]
fn absurd_png_dimensions_are_rejected_before_allocating() {
    for (width, height) in [(100_000u32, 100_000u32), (0x7FFF_FFFF, 0x7FFF_FFFF)] {
        let mut ihdr = width.to_be_bytes().to_vec();
        ihdr.extend_from_slice(&height.to_be_bytes());
        ihdr.extend_from_slice(&[8, 2, 0, 0, 0]); // 8-bit RGB
        let mut bytes = vec![0x89, b'P', b'N', b'G', 0x0D, 0x0A, 0x1A, 0x0A];
        bytes.extend(chunk(b"IHDR", &ihdr));
        bytes.extend(chunk(
            b"IDAT",
            &[0x78, 0x9C, 0x03, 0x00, 0x00, 0x00, 0x00, 0x01],
        ));
        bytes.extend(chunk(b"IEND", &[]));
        let err =
            named(decode_ros2_compressed(&ros2_compressed("png", bytes), Target::Rgb).unwrap_err());
        assert!(matches!(err, ImageError::TooLarge { .. }), "{err}");
    }
}

#[test]
fn truncated_png_is_an_error() {
    let bytes = png8(&gradient(32, 32), 32, 32, ::png::ColorType::Rgb);
    for len in [0, 4, 8, 20, 40, bytes.len() / 2, bytes.len() - 20] {
        let err =
            decode_ros2_compressed(&ros2_compressed("png", bytes[..len].to_vec()), Target::Rgb)
                .expect_err(&format!("truncated to {len}"));
        named(err);
    }
}
