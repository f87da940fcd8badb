//! The sensor data model: what the pipeline decodes recorded messages into.
//!
//! Frames follow the `a_from_b` convention: a transform named `map_from_ego` maps points
//! expressed in the ego frame to the map frame, so `point_in_map = map_from_ego * point_in_ego`.
//! Camera frames are optical frames (x right, y down, z forward, REP-103). Pixel
//! coordinates are OpenCV's: the centre of the top-left pixel is `(0, 0)`, `u` grows to
//! the right and `v` downwards.

use crate::time::Stamp;
use nalgebra::{Isometry3, Matrix3, Point2, Point3, Vector2};
use serde::{Deserialize, Serialize};

/// A sensor record whose parts disagree (lengths, sizes, parameters).
#[derive(Debug, Clone, PartialEq, thiserror::Error)]
pub enum SensorError {
    /// A per-point attribute does not have one value per point.
    #[error("point cloud in frame `{frame_id}`: {attribute} has {got} values for {points} points")]
    AttributeLength {
        /// Frame of the cloud.
        frame_id: String,
        /// Name of the attribute.
        attribute: &'static str,
        /// Values present.
        got: usize,
        /// Points in the cloud.
        points: usize,
    },
    /// Image data does not match `width × height × channels`.
    #[error(
        "image in frame `{frame_id}`: {got} bytes for {width}x{height} {format:?} (expected {expected})"
    )]
    ImageSize {
        /// Frame of the image.
        frame_id: String,
        /// Width in pixels.
        width: u32,
        /// Height in pixels.
        height: u32,
        /// Pixel format.
        format: PixelFormat,
        /// Bytes present.
        got: usize,
        /// Bytes expected.
        expected: usize,
    },
    /// A distortion model with the wrong number of coefficients, or an unknown model.
    #[error("distortion model `{model}` with {count} coefficients is not supported")]
    Distortion {
        /// Model name as recorded.
        model: String,
        /// Coefficients recorded.
        count: usize,
    },
    /// A calibration that cannot project (zero size, zero or non-finite focal length).
    #[error("camera calibration for `{frame_id}` is degenerate: {reason}")]
    Calibration {
        /// Optical frame of the camera.
        frame_id: String,
        /// What is wrong.
        reason: String,
    },
}

/// One LiDAR sweep, stored as a structure of arrays.
///
/// Points are in the frame `frame_id` (the LiDAR frame). `time_offset_secs`, when present,
/// is each point's capture time relative to `stamp` (negative when the stamp is the end
/// of the sweep), for clouds that are not motion compensated. `label`, when present, is
/// each point's semantic class id as recorded (nuScenes-lidarseg, SemanticKITTI after its
/// instance bits are masked off): raw ids, before any mapping to training classes.
#[derive(Debug, Clone, PartialEq, Default, Serialize, Deserialize)]
pub struct PointCloud {
    /// The sensor's stamp of the sweep.
    pub stamp: Stamp,
    /// The frame the points are expressed in.
    pub frame_id: String,
    /// Positions in metres.
    pub xyz: Vec<[f32; 3]>,
    /// Return intensity, in the sensor's own scale.
    pub intensity: Vec<f32>,
    /// Laser (beam) index, when the sensor reports it.
    pub ring: Option<Vec<u16>>,
    /// Per-point time relative to `stamp`, in seconds.
    pub time_offset_secs: Option<Vec<f32>>,
    /// Per-point raw semantic class id, when the recording labels its points and the
    /// reader was asked for them (absent from older serialized clouds).
    #[serde(default)]
    pub label: Option<Vec<u32>>,
}

impl PointCloud {
    /// Number of points.
    pub fn len(&self) -> usize {
        self.xyz.len()
    }

    /// Whether the sweep has no points.
    pub fn is_empty(&self) -> bool {
        self.xyz.is_empty()
    }

    /// Checks that every per-point attribute has one value per point.
    pub fn validate(&self) -> Result<(), SensorError> {
        let points = self.xyz.len();
        let check = |attribute: &'static str, got: usize| {
            if got == points {
                Ok(())
            } else {
                Err(SensorError::AttributeLength {
                    frame_id: self.frame_id.clone(),
                    attribute,
                    got,
                    points,
                })
            }
        };
        check("intensity", self.intensity.len())?;
        if let Some(ring) = &self.ring {
            check("ring", ring.len())?;
        }
        if let Some(time) = &self.time_offset_secs {
            check("time_offset_secs", time.len())?;
        }
        if let Some(label) = &self.label {
            check("label", label.len())?;
        }
        Ok(())
    }
}

/// Pixel layout of a decoded [`Image`].
#[derive(Debug, Clone, Copy, PartialEq, Eq, Hash, Serialize, Deserialize)]
pub enum PixelFormat {
    /// Three bytes per pixel, red first.
    Rgb8,
    /// One byte per pixel (grey levels, or class ids for a semantic map).
    Mono8,
}

impl PixelFormat {
    /// Bytes per pixel.
    pub const fn channels(self) -> usize {
        match self {
            PixelFormat::Rgb8 => 3,
            PixelFormat::Mono8 => 1,
        }
    }
}

/// A decoded camera image (or a per-pixel class map), row-major, tightly packed.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct Image {
    /// The sensor's capture stamp.
    pub stamp: Stamp,
    /// The camera's optical frame.
    pub frame_id: String,
    /// Width in pixels.
    pub width: u32,
    /// Height in pixels.
    pub height: u32,
    /// Pixel layout.
    pub format: PixelFormat,
    /// `height × width × channels` bytes.
    pub data: Vec<u8>,
}

impl Image {
    /// An image, checked for a consistent size.
    pub fn new(
        stamp: Stamp,
        frame_id: impl Into<String>,
        width: u32,
        height: u32,
        format: PixelFormat,
        data: Vec<u8>,
    ) -> Result<Self, SensorError> {
        let image = Self {
            stamp,
            frame_id: frame_id.into(),
            width,
            height,
            format,
            data,
        };
        let expected = image.width as usize * image.height as usize * format.channels();
        if image.data.len() != expected || expected == 0 {
            return Err(SensorError::ImageSize {
                frame_id: image.frame_id,
                width,
                height,
                format,
                got: image.data.len(),
                expected,
            });
        }
        Ok(image)
    }

    /// The bytes of pixel `(col, row)`, or `None` outside the image.
    pub fn pixel(&self, col: u32, row: u32) -> Option<&[u8]> {
        if col >= self.width || row >= self.height {
            return None;
        }
        let channels = self.format.channels();
        let start = (row as usize * self.width as usize + col as usize) * channels;
        self.data.get(start..start + channels)
    }
}

/// Lens distortion, with the coefficient order of ROS `CameraInfo` and OpenCV.
#[derive(Debug, Clone, Copy, PartialEq, Serialize, Deserialize)]
pub enum Distortion {
    /// A rectified or ideal pinhole camera.
    None,
    /// Brown–Conrady, ROS `plumb_bob`: `k1, k2, p1, p2, k3`.
    PlumbBob {
        /// Radial and tangential coefficients `[k1, k2, p1, p2, k3]`.
        coeffs: [f64; 5],
    },
    /// ROS `rational_polynomial`: `k1, k2, p1, p2, k3, k4, k5, k6`.
    RationalPolynomial {
        /// Coefficients `[k1, k2, p1, p2, k3, k4, k5, k6]`.
        coeffs: [f64; 8],
    },
    /// Fisheye, ROS `equidistant` / Foxglove `kannala_brandt`: `k1, k2, k3, k4`.
    Equidistant {
        /// Coefficients `[k1, k2, k3, k4]` of `θ_d = θ (1 + k1 θ² + k2 θ⁴ + k3 θ⁶ + k4 θ⁸)`.
        coeffs: [f64; 4],
    },
}

impl Distortion {
    /// Builds a model from the name and coefficients a recording carries.
    ///
    /// An empty model name or all-zero coefficients mean no distortion. ROS writes
    /// `plumb_bob` with 5 coefficients; some tools write 4 or 8 for it, which are
    /// accepted when the extra ones are zero.
    pub fn from_recorded(model: &str, coeffs: &[f64]) -> Result<Self, SensorError> {
        let unsupported = || SensorError::Distortion {
            model: model.to_string(),
            count: coeffs.len(),
        };
        if coeffs.iter().all(|c| *c == 0.0) {
            return Ok(Distortion::None);
        }
        let padded = |n: usize| -> Option<Vec<f64>> {
            let (head, tail) = coeffs.split_at(coeffs.len().min(n));
            tail.iter().all(|c| *c == 0.0).then(|| {
                let mut v = head.to_vec();
                v.resize(n, 0.0);
                v
            })
        };
        match model {
            "plumb_bob" | "radtan" => {
                let c = padded(5).ok_or_else(unsupported)?;
                Ok(Distortion::PlumbBob {
                    coeffs: [c[0], c[1], c[2], c[3], c[4]],
                })
            }
            "rational_polynomial" => {
                let c = padded(8).ok_or_else(unsupported)?;
                let mut coeffs = [0.0; 8];
                coeffs.copy_from_slice(&c);
                Ok(Distortion::RationalPolynomial { coeffs })
            }
            "equidistant" | "kannala_brandt" | "fisheye" if coeffs.len() == 4 => {
                Ok(Distortion::Equidistant {
                    coeffs: [coeffs[0], coeffs[1], coeffs[2], coeffs[3]],
                })
            }
            _ => Err(unsupported()),
        }
    }

    /// The model's ROS name (`""` for none).
    pub fn model_name(&self) -> &'static str {
        match self {
            Distortion::None => "",
            Distortion::PlumbBob { .. } => "plumb_bob",
            Distortion::RationalPolynomial { .. } => "rational_polynomial",
            Distortion::Equidistant { .. } => "equidistant",
        }
    }

    /// The coefficients in recorded order.
    pub fn coeffs(&self) -> Vec<f64> {
        match self {
            Distortion::None => Vec::new(),
            Distortion::PlumbBob { coeffs } => coeffs.to_vec(),
            Distortion::RationalPolynomial { coeffs } => coeffs.to_vec(),
            Distortion::Equidistant { coeffs } => coeffs.to_vec(),
        }
    }

    /// Maps an ideal normalized image point `(x/z, y/z)` to its distorted position.
    #[inline]
    pub fn distort(&self, ideal: Vector2<f64>) -> Vector2<f64> {
        let (x, y) = (ideal.x, ideal.y);
        let r2 = x * x + y * y;
        let brown = |radial: f64, p1: f64, p2: f64| {
            Vector2::new(
                x * radial + 2.0 * p1 * x * y + p2 * (r2 + 2.0 * x * x),
                y * radial + p1 * (r2 + 2.0 * y * y) + 2.0 * p2 * x * y,
            )
        };
        match *self {
            Distortion::None => ideal,
            Distortion::PlumbBob {
                coeffs: [k1, k2, p1, p2, k3],
            } => brown(1.0 + r2 * (k1 + r2 * (k2 + r2 * k3)), p1, p2),
            Distortion::RationalPolynomial {
                coeffs: [k1, k2, p1, p2, k3, k4, k5, k6],
            } => {
                let num = 1.0 + r2 * (k1 + r2 * (k2 + r2 * k3));
                let den = 1.0 + r2 * (k4 + r2 * (k5 + r2 * k6));
                brown(num / den, p1, p2)
            }
            Distortion::Equidistant {
                coeffs: [k1, k2, k3, k4],
            } => {
                let r = r2.sqrt();
                if r < 1e-12 {
                    return ideal;
                }
                let theta = r.atan();
                let t2 = theta * theta;
                let theta_d = theta * (1.0 + t2 * (k1 + t2 * (k2 + t2 * (k3 + t2 * k4))));
                ideal * (theta_d / r)
            }
        }
    }

    /// Inverts [`Distortion::distort`] by Newton iteration on the 2×2 Jacobian
    /// (numerical); converges to 1e-12 within the lens's monotonic range.
    pub fn undistort(&self, distorted: Vector2<f64>) -> Vector2<f64> {
        if matches!(self, Distortion::None) {
            return distorted;
        }
        let mut ideal = distorted;
        for _ in 0..50 {
            let residual = self.distort(ideal) - distorted;
            if residual.norm() < 1e-13 {
                break;
            }
            let h = 1e-7;
            let jx = (self.distort(ideal + Vector2::new(h, 0.0)) - self.distort(ideal)) / h;
            let jy = (self.distort(ideal + Vector2::new(0.0, h)) - self.distort(ideal)) / h;
            let det = jx.x * jy.y - jy.x * jx.y;
            if det.abs() < 1e-15 {
                break;
            }
            let step = Vector2::new(
                (jy.y * residual.x - jy.x * residual.y) / det,
                (-jx.y * residual.x + jx.x * residual.y) / det,
            );
            ideal -= step;
        }
        ideal
    }
}

/// Intrinsic calibration of one camera: the pinhole matrix `K` of the raw image, its
/// distortion, its size and its optical frame.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct CameraCalibration {
    /// Stamp of the calibration message (informational).
    pub stamp: Stamp,
    /// The optical frame (x right, y down, z forward) the calibration belongs to.
    pub frame_id: String,
    /// Image width in pixels.
    pub width: u32,
    /// Image height in pixels.
    pub height: u32,
    /// `image_from_camera`: `[fx s cx; 0 fy cy; 0 0 1]` for the raw (distorted) image.
    pub k: Matrix3<f64>,
    /// Lens distortion of the raw image.
    pub distortion: Distortion,
}

impl CameraCalibration {
    /// Checks that the calibration can project: positive size, finite positive focal
    /// lengths, a last row of `[0 0 1]`.
    pub fn validate(&self) -> Result<(), SensorError> {
        let fail = |reason: String| {
            Err(SensorError::Calibration {
                frame_id: self.frame_id.clone(),
                reason,
            })
        };
        if self.width == 0 || self.height == 0 {
            return fail(format!("image size {}x{}", self.width, self.height));
        }
        if !self.k.iter().all(|v| v.is_finite()) {
            return fail("K has non-finite entries".into());
        }
        if self.k[(0, 0)] <= 0.0 || self.k[(1, 1)] <= 0.0 {
            return fail(format!(
                "focal lengths fx={} fy={}",
                self.k[(0, 0)],
                self.k[(1, 1)]
            ));
        }
        if self.k.row(2) != Matrix3::identity().row(2) {
            return fail("K's last row is not [0 0 1]".into());
        }
        Ok(())
    }

    /// Projects a point in the camera's optical frame to a pixel of the raw image.
    /// Returns `None` for points at or behind the image plane (`z <= 0`); bounds are
    /// not checked (see [`CameraCalibration::contains_strict`]).
    #[inline]
    pub fn project(&self, point_in_camera: &Point3<f64>) -> Option<Point2<f64>> {
        if point_in_camera.z <= 0.0 {
            return None;
        }
        let ideal = Vector2::new(
            point_in_camera.x / point_in_camera.z,
            point_in_camera.y / point_in_camera.z,
        );
        let d = self.distortion.distort(ideal);
        let k = &self.k;
        Some(Point2::new(
            k[(0, 0)] * d.x + k[(0, 1)] * d.y + k[(0, 2)],
            k[(1, 1)] * d.y + k[(1, 2)],
        ))
    }

    /// The unit-depth ray `(x, y, 1)` in the optical frame that images onto `pixel`.
    pub fn unproject(&self, pixel: &Point2<f64>) -> Point3<f64> {
        let k = &self.k;
        let y = (pixel.y - k[(1, 2)]) / k[(1, 1)];
        let x = (pixel.x - k[(0, 2)] - k[(0, 1)] * y) / k[(0, 0)];
        let ideal = self.distortion.undistort(Vector2::new(x, y));
        Point3::new(ideal.x, ideal.y, 1.0)
    }

    /// The paper's strict bounds: `0 < u < W − 1` and `0 < v < H − 1`.
    #[inline]
    pub fn contains_strict(&self, pixel: &Point2<f64>) -> bool {
        pixel.x > 0.0
            && pixel.x < f64::from(self.width) - 1.0
            && pixel.y > 0.0
            && pixel.y < f64::from(self.height) - 1.0
    }
}

/// A rigid transform between two frames at one instant.
///
/// `parent_from_child` maps points in `child_frame` into `parent_frame`, as a ROS
/// `TransformStamped` or a Foxglove `FrameTransform` does.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct StampedTransform {
    /// When the transform holds (ignored for static transforms).
    pub stamp: Stamp,
    /// The frame points are mapped into.
    pub parent_frame: String,
    /// The frame points are mapped from.
    pub child_frame: String,
    /// The transform itself.
    pub parent_from_child: Isometry3<f64>,
    /// Whether it holds at all times (`/tf_static`, sensor extrinsics).
    pub is_static: bool,
}

#[cfg(test)]
mod tests {
    use super::*;
    use nalgebra::Matrix3;

    fn calibration(distortion: Distortion) -> CameraCalibration {
        CameraCalibration {
            stamp: Stamp::default(),
            frame_id: "cam".into(),
            width: 640,
            height: 480,
            k: Matrix3::new(500.0, 0.0, 320.0, 0.0, 510.0, 240.0, 0.0, 0.0, 1.0),
            distortion,
        }
    }

    #[test]
    fn pinhole_projection_matches_hand_computation() {
        let cam = calibration(Distortion::None);
        let px = cam.project(&Point3::new(1.0, -0.5, 4.0)).unwrap();
        assert!((px.x - (500.0 * 0.25 + 320.0)).abs() < 1e-12);
        assert!((px.y - (510.0 * -0.125 + 240.0)).abs() < 1e-12);
        assert!(cam.project(&Point3::new(1.0, 0.0, -1.0)).is_none());
        assert!(cam.project(&Point3::new(1.0, 0.0, 0.0)).is_none());
    }

    #[test]
    fn plumb_bob_matches_opencv_formula() {
        // x = 0.3, y = -0.2, r² = 0.13; values worked out by hand from the Brown model.
        let d = Distortion::PlumbBob {
            coeffs: [-0.3, 0.1, 0.001, -0.002, 0.01],
        };
        let out = d.distort(Vector2::new(0.3, -0.2));
        let r2: f64 = 0.13;
        let radial = 1.0 - 0.3 * r2 + 0.1 * r2 * r2 + 0.01 * r2 * r2 * r2;
        let x = 0.3 * radial + 2.0 * 0.001 * 0.3 * -0.2 + -0.002 * (r2 + 2.0 * 0.09);
        let y = -0.2 * radial + 0.001 * (r2 + 2.0 * 0.04) + 2.0 * -0.002 * 0.3 * -0.2;
        assert!((out.x - x).abs() < 1e-15 && (out.y - y).abs() < 1e-15);
        assert!((out.x - 0.288_073_591).abs() < 1e-9, "{}", out.x);
    }

    #[test]
    fn equidistant_matches_fisheye_formula() {
        let d = Distortion::Equidistant {
            coeffs: [0.05, -0.01, 0.002, 0.0],
        };
        let ideal = Vector2::new(0.6, 0.8); // r = 1, θ = π/4
        let theta = std::f64::consts::FRAC_PI_4;
        let t2 = theta * theta;
        let theta_d = theta * (1.0 + 0.05 * t2 - 0.01 * t2 * t2 + 0.002 * t2 * t2 * t2);
        let out = d.distort(ideal);
        assert!((out - ideal * theta_d).norm() < 1e-15);
    }

    #[test]
    fn unproject_inverts_project_for_every_model() {
        let models = [
            Distortion::None,
            Distortion::PlumbBob {
                coeffs: [-0.28, 0.07, 0.0005, -0.0004, 0.0],
            },
            Distortion::RationalPolynomial {
                coeffs: [0.4, -0.1, 0.001, 0.0005, 0.01, 0.6, -0.05, 0.02],
            },
            Distortion::Equidistant {
                coeffs: [0.02, -0.005, 0.001, 0.0],
            },
        ];
        for model in models {
            let cam = calibration(model);
            for &(u, v) in &[(1.0, 1.0), (320.0, 240.0), (600.5, 30.25), (100.0, 470.0)] {
                let ray = cam.unproject(&Point2::new(u, v));
                let back = cam.project(&(ray * 7.0)).unwrap();
                assert!(
                    (back.x - u).abs() < 1e-6 && (back.y - v).abs() < 1e-6,
                    "{model:?}: ({u}, {v}) -> {back:?}"
                );
            }
        }
    }

    #[test]
    fn recorded_models_parse_and_unknown_ones_are_errors() {
        assert_eq!(
            Distortion::from_recorded("", &[]).unwrap(),
            Distortion::None
        );
        assert_eq!(
            Distortion::from_recorded("plumb_bob", &[0.0; 5]).unwrap(),
            Distortion::None
        );
        assert!(matches!(
            Distortion::from_recorded("plumb_bob", &[0.1, 0.0, 0.0, 0.0, 0.0, 0.0, 0.0, 0.0]),
            Ok(Distortion::PlumbBob { .. })
        ));
        assert!(matches!(
            Distortion::from_recorded("rational_polynomial", &[0.1; 8]),
            Ok(Distortion::RationalPolynomial { .. })
        ));
        assert!(Distortion::from_recorded("equidistant", &[0.1; 5]).is_err());
        let err = Distortion::from_recorded("mei", &[0.1]).unwrap_err();
        assert!(err.to_string().contains("mei"), "{err}");
    }

    #[test]
    fn strict_bounds_exclude_the_border() {
        let cam = calibration(Distortion::None);
        assert!(cam.contains_strict(&Point2::new(0.5, 0.5)));
        assert!(!cam.contains_strict(&Point2::new(0.0, 10.0)));
        assert!(!cam.contains_strict(&Point2::new(639.0, 10.0)));
        assert!(cam.contains_strict(&Point2::new(638.99, 478.99)));
        assert!(!cam.contains_strict(&Point2::new(10.0, 479.0)));
    }

    #[test]
    fn inconsistent_records_are_rejected() {
        let cloud = PointCloud {
            frame_id: "lidar".into(),
            xyz: vec![[0.0; 3]; 3],
            intensity: vec![0.0; 2],
            ..Default::default()
        };
        assert!(
            cloud
                .validate()
                .unwrap_err()
                .to_string()
                .contains("intensity has 2")
        );
        let cloud = PointCloud {
            frame_id: "lidar".into(),
            xyz: vec![[0.0; 3]; 3],
            intensity: vec![0.0; 3],
            label: Some(vec![4; 4]),
            ..Default::default()
        };
        assert!(
            cloud
                .validate()
                .unwrap_err()
                .to_string()
                .contains("label has 4 values for 3 points")
        );
        let image = Image::new(
            Stamp::default(),
            "cam",
            4,
            2,
            PixelFormat::Rgb8,
            vec![0; 23],
        );
        assert!(image.is_err());
        let image = Image::new(
            Stamp::default(),
            "cam",
            4,
            2,
            PixelFormat::Mono8,
            vec![7; 8],
        )
        .unwrap();
        assert_eq!(image.pixel(3, 1), Some(&[7u8][..]));
        assert_eq!(image.pixel(4, 1), None);
        let mut cam = calibration(Distortion::None);
        cam.k[(1, 1)] = 0.0;
        assert!(cam.validate().is_err());
    }
}
