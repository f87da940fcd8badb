//! LiDAR → camera geometry (paper Eq. 1, done right): each point goes through the ego
//! pose at the LiDAR stamp into the map, then through the ego pose at the camera stamp
//! into the camera, then through `K` and the lens distortion.

use crate::drive::{TfError, TransformTree};
use nalgebra::{Isometry3, Matrix3, Point2, Point3, Vector3};
use superflow_schemas::Stamp;
use superflow_schemas::sensor::CameraCalibration;

/// Points nearer than this (along the optical axis) are not paired (the paper's 1 m).
pub const MIN_DEPTH_M: f64 = 1.0;

/// `camera_from_lidar` for a sweep at `lidar_stamp` seen by an image at `camera_stamp`:
/// `camera_from_map(t_cam) · map_from_lidar(t_lidar)`; the map is the fixed frame that
/// carries the ego motion between the two instants.
pub fn camera_from_lidar(
    tf: &TransformTree,
    map_frame: &str,
    lidar_frame: &str,
    lidar_stamp: Stamp,
    camera_frame: &str,
    camera_stamp: Stamp,
) -> Result<Isometry3<f64>, TfError> {
    let map_from_lidar = tf.lookup(map_frame, lidar_frame, lidar_stamp)?;
    let camera_from_map = tf.lookup(camera_frame, map_frame, camera_stamp)?;
    Ok(camera_from_map * map_from_lidar)
}

/// A camera ready to receive points: its calibration, the transform from the LiDAR
/// frame, and the largest undistorted radius its image covers (points beyond it are
/// outside the field of view even if the distortion polynomial folds them back in).
#[derive(Debug, Clone)]
pub struct CameraView<'a> {
    calibration: &'a CameraCalibration,
    /// `camera_from_lidar` as a rotation matrix and a translation: the depth row alone
    /// rejects the points behind the camera (most of them) before the rest is computed.
    rotation: Matrix3<f64>,
    translation: Vector3<f64>,
    max_ideal_radius_sq: f64,
}

impl<'a> CameraView<'a> {
    /// A view of `calibration` from the LiDAR frame.
    pub fn new(calibration: &'a CameraCalibration, camera_from_lidar: Isometry3<f64>) -> Self {
        let (w, h) = (f64::from(calibration.width), f64::from(calibration.height));
        let max_ideal_radius = [
            (0.0, 0.0),
            (w - 1.0, 0.0),
            (0.0, h - 1.0),
            (w - 1.0, h - 1.0),
        ]
        .iter()
        .map(|(u, v)| {
            calibration
                .unproject(&Point2::new(*u, *v))
                .coords
                .xy()
                .norm()
        })
        .fold(0.0, f64::max);
        let max_ideal_radius = max_ideal_radius * 1.02;
        Self {
            calibration,
            rotation: camera_from_lidar.rotation.to_rotation_matrix().into_inner(),
            translation: camera_from_lidar.translation.vector,
            max_ideal_radius_sq: max_ideal_radius * max_ideal_radius,
        }
    }

    /// The pixel `(u, v)` of the raw image and the depth of a LiDAR-frame point, if it
    /// lies more than [`MIN_DEPTH_M`] in front of the camera and strictly inside the
    /// image (`0 < u < W − 1`, `0 < v < H − 1`).
    pub fn project(&self, point_in_lidar: [f32; 3]) -> Option<(Point2<f64>, f64)> {
        let q = Vector3::from(point_in_lidar.map(f64::from));
        let (r, t) = (&self.rotation, &self.translation);
        let depth = r.row(2).transpose().dot(&q) + t.z;
        if depth <= MIN_DEPTH_M {
            return None;
        }
        let p = Point3::new(
            r.row(0).transpose().dot(&q) + t.x,
            r.row(1).transpose().dot(&q) + t.y,
            depth,
        );
        let (ix, iy) = (p.x / p.z, p.y / p.z);
        if ix * ix + iy * iy > self.max_ideal_radius_sq {
            return None;
        }
        let pixel = self.calibration.project(&p)?;
        self.calibration
            .contains_strict(&pixel)
            .then_some((pixel, p.z))
    }
}

/// One point seen in one image.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct Pairing {
    /// Index of the point in its cloud.
    pub point: u32,
    /// Column in the raw image (OpenCV convention, float).
    pub u: f32,
    /// Row in the raw image.
    pub v: f32,
    /// Depth along the optical axis, metres.
    pub depth: f32,
}

/// Every point of `xyz` that `view` sees, in point order.
///
/// Most points are behind or beside a camera. A first pass over each block of points
/// moves them into the camera in `f32` lanes (no branch per point) and drops those
/// clearly behind [`MIN_DEPTH_M`] or clearly outside the cone of the image (by more than
/// `f32` rounding could move them); every other point goes through
/// [`CameraView::project`], the per-point path, so the pairings are the same.
#[allow(unsafe_code)]
pub fn pair_points(xyz: &[[f32; 3]], view: &CameraView<'_>) -> Vec<Pairing> {
    #[cfg(target_arch = "x86_64")]
    if super::simd::has_avx512() {
        // SAFETY: the CPU runs AVX-512 F and BW (checked just above), the only
        // requirement of calling a function compiled with them enabled.
        return unsafe { pair_points_avx512(xyz, view) };
    }
    #[cfg(target_arch = "x86_64")]
    if crate::sample::simd::has_avx2() {
        // SAFETY: the CPU runs AVX2 (checked just above), the only requirement of calling
        // a function compiled with it enabled.
        return unsafe { pair_points_avx2(xyz, view) };
    }
    pair_points_inline(xyz, view)
}

/// [`pair_points`] compiled with AVX-512 enabled (not used for FMA: Rust never
/// contracts, so the same results).
#[cfg(target_arch = "x86_64")]
#[target_feature(enable = "avx512f,avx512bw,avx2")]
fn pair_points_avx512(xyz: &[[f32; 3]], view: &CameraView<'_>) -> Vec<Pairing> {
    pair_points_inline(xyz, view)
}

/// [`pair_points`] compiled with AVX2 enabled (not FMA: no contraction, same results).
#[cfg(target_arch = "x86_64")]
#[target_feature(enable = "avx2")]
fn pair_points_avx2(xyz: &[[f32; 3]], view: &CameraView<'_>) -> Vec<Pairing> {
    pair_points_inline(xyz, view)
}

#[inline(always)]
fn pair_points_inline(xyz: &[[f32; 3]], view: &CameraView<'_>) -> Vec<Pairing> {
    const BLOCK: usize = 64;
    let rows = [0, 1, 2].map(|i| {
        let r = view.rotation.row(i);
        [
            r[0] as f32,
            r[1] as f32,
            r[2] as f32,
            view.translation[i] as f32,
        ]
    });
    // The cone, widened by far more than the f32 and f64 roundings of both tests.
    let cone = (view.max_ideal_radius_sq * (1.0 + 1e-5)) as f32;
    let mut out = Vec::new();
    // The block's coordinates axis by axis, so that the test runs in full lanes; made
    // once (a short last block leaves stale lanes behind, which are never read).
    let mut axes = [[0f32; BLOCK]; 3];
    let mut maybe = [false; BLOCK];
    for (b, block) in xyz.chunks(BLOCK).enumerate() {
        for (i, p) in block.iter().enumerate() {
            for a in 0..3 {
                axes[a][i] = p[a];
            }
        }
        for (i, m) in maybe.iter_mut().enumerate() {
            *m = might_be_seen([axes[0][i], axes[1][i], axes[2][i]], &rows, cone);
        }
        for (i, p) in block.iter().enumerate() {
            if !maybe[i] {
                continue;
            }
            if let Some((pixel, depth)) = view.project(*p) {
                out.push(Pairing {
                    point: (b * BLOCK + i) as u32,
                    u: pixel.x as f32,
                    v: pixel.y as f32,
                    depth: depth as f32,
                });
            }
        }
    }
    out
}

/// Whether the `f32` camera coordinates `(x, y, z)` of a point do not rule it out:
/// each is within `e` of the exact value, `e` covering the rounding of the rotation, the
/// products and the sums (8 ulps of the sum of the magnitudes involved) plus a
/// millimetre, so a point is dropped only when even its most favourable exact position
/// is at most [`MIN_DEPTH_M`] deep, or outside the widened `cone` (`(x² + y²)/z²`).
/// Points that are not finite numbers are kept (the exact test decides).
#[inline(always)]
fn might_be_seen(p: [f32; 3], rows: &[[f32; 4]; 3], cone: f32) -> bool {
    let mut c = [0f32; 3];
    let mut scale = 0f32;
    for (c, [r0, r1, r2, t]) in c.iter_mut().zip(rows) {
        let terms = [r0 * p[0], r1 * p[1], r2 * p[2], *t];
        *c = terms[0] + terms[1] + terms[2] + terms[3];
        scale += terms[0].abs() + terms[1].abs() + terms[2].abs() + terms[3].abs();
    }
    let e = scale * (8.0 * f32::EPSILON) + 1e-3;
    let (x, y, z) = (
        (c[0].abs() - e).max(0.0),
        (c[1].abs() - e).max(0.0),
        c[2] + e,
    );
    let behind = z <= MIN_DEPTH_M as f32;
    let beside = x * x + y * y > cone * (z * z);
    !(behind || beside)
}

#[cfg(test)]
mod tests {
    use super::*;
    use nalgebra::{Translation3, UnitQuaternion};
    use superflow_schemas::sensor::Distortion;

    /// The pairings of every point taken one at a time through [`CameraView::project`].
    fn one_by_one(xyz: &[[f32; 3]], view: &CameraView<'_>) -> Vec<Pairing> {
        xyz.iter()
            .enumerate()
            .filter_map(|(i, p)| {
                view.project(*p).map(|(pixel, depth)| Pairing {
                    point: i as u32,
                    u: pixel.x as f32,
                    v: pixel.y as f32,
                    depth: depth as f32,
                })
            })
            .collect()
    }

    #[test]
    fn the_depth_prefilter_keeps_every_pairing() {
        let calibration = CameraCalibration {
            stamp: Stamp::default(),
            frame_id: "cam".into(),
            width: 800,
            height: 450,
            k: Matrix3::new(640.0, 0.0, 400.0, 0.0, 640.0, 225.0, 0.0, 0.0, 1.0),
            distortion: Distortion::PlumbBob {
                coeffs: [-0.05, 0.01, 0.0002, -0.0001, 0.0],
            },
        };
        // A camera looking along the LiDAR's y axis, 1.5 m up and 0.7 m forward, tilted.
        let rotation = UnitQuaternion::from_euler_angles(-1.55, 0.03, 0.02);
        let camera_from_lidar = Isometry3::from_parts(Translation3::new(0.1, 1.5, -0.7), rotation);
        let view = CameraView::new(&calibration, camera_from_lidar);
        let mut rng = crate::test_rng::TestRng(0x2545_f491_4f6c_dd1d);
        let mut uniform = move || rng.uniform();
        let mut xyz: Vec<[f32; 3]> = (0..50_000)
            .map(|_| {
                let range = 0.5 + 80.0 * uniform();
                let azimuth = std::f64::consts::TAU * uniform();
                let elevation = -0.5 + 0.7 * uniform();
                [
                    (range * elevation.cos() * azimuth.cos()) as f32,
                    (range * elevation.cos() * azimuth.sin()) as f32,
                    (range * elevation.sin()) as f32,
                ]
            })
            .collect();
        // Points at exactly the minimum depth and a hair either side of it, and ones
        // that are not numbers.
        let lidar_from_camera = camera_from_lidar.inverse();
        for k in 0..2_000 {
            let depth = MIN_DEPTH_M + (k as f64 - 1_000.0) * 1e-9;
            let (u, v) = (-0.4 + 0.8 * uniform(), -0.3 + 0.6 * uniform());
            let p = lidar_from_camera * Point3::new(u * depth, v * depth, depth);
            xyz.push([p.x as f32, p.y as f32, p.z as f32]);
        }
        xyz.extend([
            [f32::NAN, 1.0, 0.0],
            [0.0, f32::INFINITY, 0.0],
            [1e30, 1e30, 1e30],
        ]);
        let want = one_by_one(&xyz, &view);
        assert!(want.len() > 2_000, "{} pairings", want.len());
        assert!(
            want.iter().any(|p| p.point >= 50_000),
            "threshold points pair"
        );
        assert_eq!(pair_points(&xyz, &view), want);
        // Every compiled copy the CPU runs.
        assert_eq!(pair_points_inline(&xyz, &view), want, "baseline copy");
        #[cfg(target_arch = "x86_64")]
        #[allow(unsafe_code)]
        {
            if crate::sample::simd::has_avx2() {
                // SAFETY: the CPU runs AVX2.
                let avx2 = unsafe { pair_points_avx2(&xyz, &view) };
                assert_eq!(avx2, want, "AVX2 copy");
            }
            if crate::sample::simd::has_avx512() {
                // SAFETY: the CPU runs AVX-512 F and BW.
                let avx512 = unsafe { pair_points_avx512(&xyz, &view) };
                assert_eq!(avx512, want, "AVX-512 copy");
            }
        }
    }
}
