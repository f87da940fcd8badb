//! LiDAR → camera geometry (paper Eq. 1, done right): each point goes through the ego
//! pose at the LiDAR stamp into the map, then through the ego pose at the camera stamp
//! into the camera, then through `K` and the lens distortion. Also per-point de-skew of
//! raw sweeps with per-point time.

use crate::drive::{TfError, TransformTree};
use nalgebra::{Isometry3, Matrix3, Point2, Point3, Vector3};
use superflow_schemas::Stamp;
use superflow_schemas::sensor::{CameraCalibration, PointCloud};

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
pub fn pair_points(xyz: &[[f32; 3]], view: &CameraView<'_>) -> Vec<Pairing> {
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

/// Moves every point of a raw sweep (per-point time, each point in the LiDAR frame at
/// its own firing instant) into the LiDAR frame at the sweep's stamp:
/// `p_stamp = lidar_from_map(stamp) · map_from_lidar(stamp + t_i) · p_i`. Points sharing
/// a firing time share one transform lookup. A cloud without per-point time is returned
/// unchanged.
pub fn deskew(
    cloud: &PointCloud,
    tf: &TransformTree,
    map_frame: &str,
) -> Result<PointCloud, TfError> {
    let Some(times) = &cloud.time_offset_secs else {
        return Ok(cloud.clone());
    };
    let lidar_from_map = tf
        .lookup(map_frame, &cloud.frame_id, cloud.stamp)?
        .inverse();
    let mut out = cloud.clone();
    let mut cached: Option<(f32, Isometry3<f64>)> = None;
    for (p, t) in out.xyz.iter_mut().zip(times) {
        let stamp_from_firing = match cached {
            Some((ct, iso)) if ct == *t => iso,
            _ => {
                let firing = cloud.stamp.add_nanos((f64::from(*t) * 1e9).round() as i64);
                let iso = lidar_from_map * tf.lookup(map_frame, &cloud.frame_id, firing)?;
                cached = Some((*t, iso));
                iso
            }
        };
        let q = stamp_from_firing * Point3::new(f64::from(p[0]), f64::from(p[1]), f64::from(p[2]));
        *p = [q.x as f32, q.y as f32, q.z as f32];
    }
    out.time_offset_secs = Some(vec![0.0; times.len()]);
    Ok(out)
}
