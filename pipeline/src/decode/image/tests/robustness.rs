//! Malformed input never panics: every truncation, and garbage.

use super::*;

#[test]
fn every_truncation_of_a_png_and_a_jpeg_fails_cleanly() {
    let rgb = gradient(24, 16);
    let png_rgb = png8(&rgb, 24, 16, ::png::ColorType::Rgb);
    let png_grey = png8(&rgb[..24 * 16], 24, 16, ::png::ColorType::Grayscale);
    let jpg = jpeg(&rgb, 24, 16, jpeg_encoder::ColorType::Rgb);
    let mut progressive = Vec::new();
    {
        let mut encoder = jpeg_encoder::Encoder::new(&mut progressive, 90);
        encoder.set_progressive(true);
        encoder
            .encode(&rgb, 24, 16, jpeg_encoder::ColorType::Rgb)
            .unwrap();
    }
    for (name, bytes, grey) in [
        ("png", &png_rgb, false),
        ("png", &png_grey, true),
        ("jpeg", &jpg, false),
        ("jpeg", &progressive, false),
    ] {
        for len in 0..bytes.len() {
            for format in [name, "", "webp"] {
                for target in [Target::Rgb, Target::Mono] {
                    // Must not panic; a result is allowed only when all the image data is there.
                    let result = decode_ros2_compressed(
                        &ros2_compressed(format, bytes[..len].to_vec()),
                        target,
                    );
                    if len < bytes.len() - 12 {
                        assert!(
                            result.is_err(),
                            "{name} truncated to {len} of {} decoded",
                            bytes.len()
                        );
                    }
                }
            }
        }
        for target in [Target::Rgb, Target::Mono] {
            let full = decode_ros2_compressed(&ros2_compressed(name, bytes.to_vec()), target);
            if grey || target == Target::Rgb {
                assert!(full.is_ok(), "{name}: {:?}", full.err());
            }
        }
    }
}

#[test]
fn garbage_never_panics() {
    let mut state = 0x1234_5678_u32;
    let mut next = move || {
        state ^= state << 13;
        state ^= state >> 17;
        state ^= state << 5;
        state
    };
    let png_ok = png8(&gradient(8, 8), 8, 8, ::png::ColorType::Rgb);
    let jpg_ok = jpeg(&gradient(16, 16), 16, 16, jpeg_encoder::ColorType::Rgb);
    for round in 0..400 {
        let mut bytes = match round % 3 {
            0 => png_ok.clone(),
            1 => jpg_ok.clone(),
            _ => (0..(next() % 300)).map(|_| next() as u8).collect(),
        };
        // Flip a few bytes past the magic.
        if bytes.len() > 8 {
            for _ in 0..(1 + next() % 4) {
                let at = 4 + (next() as usize) % (bytes.len() - 4);
                bytes[at] = next() as u8;
            }
        }
        for format in ["png", "jpeg", "", "rgb8; png compressed rgb8"] {
            let _ = decode_ros2_compressed(&ros2_compressed(format, bytes.clone()), Target::Rgb);
            let _ =
                decode_foxglove_compressed(&fox_compressed(format, bytes.clone()), Target::Mono);
        }
        let w = next() % 64;
        let h = next() % 64;
        let _ = decode_ros2_raw(
            &ros2_raw("bgra8", w, h, next() % 300, bytes.clone()),
            Target::Rgb,
        );
        let _ = decode_foxglove_raw(&fox_raw("mono8", w, h, next() % 70, bytes), Target::Mono);
    }
}
