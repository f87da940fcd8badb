// Shared by the targets (included with `#[path]`, not a crate of its own).
#![allow(dead_code)]

use superflow_pipeline::drive::TransformTree;
use superflow_schemas::Stamp;
use superflow_schemas::sensor::{CameraCalibration, StampedTransform};

/// Uses a decoded calibration the way sample building does: projects points in front
/// of the camera, unprojects pixels, distorts and undistorts.
pub fn exercise_calibration(calibration: &CameraCalibration) {
    use nalgebra::{Point2, Point3, Vector2};
    let (w, h) = (f64::from(calibration.width), f64::from(calibration.height));
    for (x, y, z) in [
        (0.0, 0.0, 1.0),
        (1.0, -1.0, 5.0),
        (-3.0, 2.0, 0.5),
        (0.1, 0.1, 1e-6),
    ] {
        if let Some(pixel) = calibration.project(&Point3::new(x, y, z)) {
            let _ = calibration.contains_strict(&pixel);
            let _ = calibration.unproject(&pixel);
        }
    }
    for (u, v) in [(0.0, 0.0), (w / 2.0, h / 2.0), (w, h), (-w, 2.0 * h)] {
        let _ = calibration.unproject(&Point2::new(u, v));
    }
    let d = &calibration.distortion;
    for (x, y) in [(0.0, 0.0), (0.5, -0.5), (2.0, 3.0)] {
        let p = d.distort(Vector2::new(x, y));
        let _ = d.undistort(p);
    }
    let _ = (d.model_name(), d.coeffs());
}

/// Inserts transforms into a tree and looks up every pair of frames around their stamps.
pub fn exercise_transforms(transforms: Vec<StampedTransform>, tolerance_nanos: i64) {
    let mut tree = TransformTree::new(tolerance_nanos);
    let mut stamps: Vec<Stamp> = Vec::new();
    for t in transforms.into_iter().take(64) {
        stamps.push(t.stamp);
        let _ = tree.insert(t);
    }
    let _ = tree.freeze_constant_edges();
    let frames = tree.frames();
    let _ = tree.edges();
    for f in frames.iter().take(8) {
        let _ = tree.root_of(f);
    }
    stamps.sort();
    stamps.dedup();
    let mut probes: Vec<Stamp> = Vec::new();
    for s in stamps.iter().take(4) {
        probes.extend([*s, s.add_nanos(1), s.add_nanos(-1_000_000)]);
    }
    // Recorded stamps come from `(i32 sec, u32 nanosec)`: stay in that range.
    probes.push(Stamp::from_nanos(0));
    for a in frames.iter().take(6) {
        for b in frames.iter().take(6) {
            for s in &probes {
                let _ = tree.lookup(a, b, *s);
            }
        }
    }
}

/// libFuzzer's panic hook aborts on every panic, also one that is caught. The image
/// decoder runs the third-party JPEG and PNG decoders under `catch_unwind` and reports
/// their panics as corrupt images (`decode::image::guarded`): let exactly those unwind
/// (noted on stderr); any other panic still aborts and is reported as a crash.
pub fn let_guarded_decoder_panics_unwind() {
    static ONCE: std::sync::Once = std::sync::Once::new();
    ONCE.call_once(|| {
        let fuzzer_hook = std::panic::take_hook();
        std::panic::set_hook(Box::new(move |info| {
            let file = info.location().map_or("", |l| l.file());
            let third_party = ["/turbojpeg-", "/png-", "/fdeflate-", "/miniz_oxide-"]
                .iter()
                .any(|krate| file.contains(krate));
            if third_party {
                eprintln!("note: image decoder panic, contained by the pipeline: {info}");
            } else {
                fuzzer_hook(info);
            }
        }));
    });
}
