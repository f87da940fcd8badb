//! The per-message decoders on arbitrary bytes.
//!
//! Input: one selector byte, then the message payload (CDR with its 4-byte
//! encapsulation header for ROS 2, protobuf for Foxglove), as an MCAP message's data.
//! Selector: low nibble = message type (`% 11`, table below); bit 4 = decode images to
//! `Mono` instead of `Rgb`; bits 5..7 = a per-point time-field override for clouds
//! (0 = infer).
//!
//! Every decoded value is then used as ingest and sample building use it: calibrations
//! project and unproject, transforms go into a `TransformTree` and are looked up, clouds
//! and images are validated.
#![no_main]

#[path = "common.rs"]
mod common;

use libfuzzer_sys::fuzz_target;
use superflow_pipeline::decode::foxglove as fox;
use superflow_pipeline::decode::image::{self, Target};
use superflow_pipeline::decode::points::{self, TimeFieldSpec, TimeReference, TimeUnit};
use superflow_pipeline::decode::ros2;

fn time_spec(bits: u8) -> Option<TimeFieldSpec> {
    let (name, unit, reference) = match bits {
        1 => ("t", TimeUnit::Nanoseconds, TimeReference::RelativeToStamp),
        2 => ("time", TimeUnit::Seconds, TimeReference::RelativeToStamp),
        3 => ("timestamp", TimeUnit::Seconds, TimeReference::Absolute),
        4 => (
            "time",
            TimeUnit::Microseconds,
            TimeReference::RelativeToStamp,
        ),
        5 => ("t", TimeUnit::Nanoseconds, TimeReference::Absolute),
        6 => ("x", TimeUnit::Seconds, TimeReference::RelativeToStamp),
        7 => ("timestamp", TimeUnit::Nanoseconds, TimeReference::Absolute),
        _ => return None,
    };
    Some(TimeFieldSpec {
        name: name.into(),
        unit,
        reference,
    })
}

fn check_cloud(decoded: &points::DecodedCloud) {
    let _ = decoded.cloud.validate();
}

fn check_image(image: &superflow_schemas::sensor::Image) {
    let _ = image.pixel(0, 0);
    let _ = image.pixel(
        image.width.saturating_sub(1),
        image.height.saturating_sub(1),
    );
}

fuzz_target!(|data: &[u8]| {
    common::let_guarded_decoder_panics_unwind();
    let Some((&selector, payload)) = data.split_first() else {
        return;
    };
    let target = if selector & 0x10 != 0 {
        Target::Mono
    } else {
        Target::Rgb
    };
    let time = time_spec(selector >> 5);
    match (selector & 0x0f) % 11 {
        0 => {
            if let Ok(msg) = ros2::decode::<ros2::PointCloud2>(payload) {
                if let Ok(decoded) = points::decode_ros2(&msg, time.as_ref()) {
                    check_cloud(&decoded);
                }
            }
        }
        1 => {
            if let Ok(msg) = fox::decode::<fox::PointCloud>("foxglove.PointCloud", payload) {
                if let Ok(decoded) = points::decode_foxglove(&msg, time.as_ref()) {
                    check_cloud(&decoded);
                }
            }
        }
        2 => {
            if let Ok(msg) = ros2::decode::<ros2::CompressedImage>(payload) {
                if let Ok(img) = image::decode_ros2_compressed(&msg, target) {
                    check_image(&img);
                }
            }
        }
        3 => {
            if let Ok(msg) = ros2::decode::<ros2::Image>(payload) {
                if let Ok(img) = image::decode_ros2_raw(&msg, target) {
                    check_image(&img);
                }
            }
        }
        4 => {
            if let Ok(msg) =
                fox::decode::<fox::CompressedImage>("foxglove.CompressedImage", payload)
            {
                if let Ok(img) = image::decode_foxglove_compressed(&msg, target) {
                    check_image(&img);
                }
            }
        }
        5 => {
            if let Ok(msg) = fox::decode::<fox::RawImage>("foxglove.RawImage", payload) {
                if let Ok(img) = image::decode_foxglove_raw(&msg, target) {
                    check_image(&img);
                }
            }
        }
        6 => {
            if let Ok(msg) = ros2::decode::<ros2::CameraInfo>(payload) {
                if let Ok(calibration) = ros2::camera_info(&msg) {
                    common::exercise_calibration(&calibration);
                }
            }
        }
        7 => {
            if let Ok(msg) =
                fox::decode::<fox::CameraCalibration>("foxglove.CameraCalibration", payload)
            {
                if let Ok(calibration) = fox::camera_calibration(&msg) {
                    common::exercise_calibration(&calibration);
                }
            }
        }
        8 => {
            if let Ok(msg) = ros2::decode::<ros2::TfMessage>(payload) {
                let is_static = selector & 0x10 != 0;
                let transforms = ros2::transforms(&msg, is_static);
                common::exercise_transforms(transforms.into_iter().flatten().collect(), 60_000_000);
            }
        }
        9 => {
            if let Ok(msg) = fox::decode::<fox::FrameTransform>("foxglove.FrameTransform", payload)
            {
                if let Ok(t) = fox::frame_transform(&msg, selector & 0x10 != 0) {
                    common::exercise_transforms(vec![t], 60_000_000);
                }
            }
        }
        _ => {
            if let Ok(msg) =
                fox::decode::<fox::FrameTransforms>("foxglove.FrameTransforms", payload)
            {
                let transforms = msg
                    .transforms
                    .iter()
                    .filter_map(|t| fox::frame_transform(t, selector & 0x10 != 0).ok())
                    .collect();
                common::exercise_transforms(transforms, 60_000_000);
            }
        }
    }
});
