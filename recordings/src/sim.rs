//! The simulated drive: ego trajectory, sensor rig, a spinning LiDAR ray-cast per
//! column, and cameras rendered per pixel from the same scene at their own stamps.

use crate::scene::{CLASSES, Scene};
use nalgebra::{Isometry3, Point3, Rotation3, Translation3, UnitQuaternion, Vector3};
use std::f64::consts::{PI, TAU};
use superflow_schemas::Stamp;
use superflow_schemas::sensor::{CameraCalibration, Distortion};

/// Longest LiDAR range, metres.
pub const LIDAR_MAX_RANGE: f64 = 70.0;
/// Ego speed along the street, m/s.
pub const EGO_SPEED: f64 = 8.0;
/// Amplitude (m) and period (s) of the ego's lateral weave.
pub const WEAVE: (f64, f64) = (1.5, 6.0);

/// When the timing of the drive happens and how fine its stamps are.
#[derive(Debug, Clone)]
pub struct DriveTiming {
    /// First stamp of the drive (start of the first LiDAR sweep).
    pub start: Stamp,
    /// Length of the drive.
    pub duration_nanos: i64,
    /// One LiDAR revolution (20 Hz).
    pub sweep_nanos: i64,
    /// Camera period (~12 Hz).
    pub camera_period_nanos: i64,
    /// Stamps are rounded to multiples of this (1000 for microsecond recorders).
    pub quantum_nanos: i64,
}

impl DriveTiming {
    /// Sweep `k` spans `[start + k·T, start + (k+1)·T]`.
    pub fn sweep_span(&self, k: usize) -> (Stamp, Stamp) {
        let begin = self.start.add_nanos(k as i64 * self.sweep_nanos);
        (begin, begin.add_nanos(self.sweep_nanos))
    }

    /// Number of complete sweeps in the drive.
    pub fn sweep_count(&self) -> usize {
        (self.duration_nanos / self.sweep_nanos) as usize
    }

    /// Stamps of camera `index` (cameras are triggered in turn as the LiDAR sweeps by).
    pub fn camera_stamps(&self, index: usize) -> Vec<Stamp> {
        let offset = 5_000_000 + index as i64 * 7_500_000 + 1_234;
        let end = self.start.add_nanos(self.duration_nanos);
        (0..)
            .map(|n| {
                let raw = offset + n * self.camera_period_nanos;
                self.start
                    .add_nanos(raw - raw.rem_euclid(self.quantum_nanos))
            })
            .take_while(|s| *s < end)
            .collect()
    }
}

/// The ego pose `map_from_ego` at any time: constant speed along x with a lateral weave,
/// heading along the velocity, on flat ground (z = 0, rear axle convention).
pub fn map_from_ego(start: Stamp, at: Stamp) -> Isometry3<f64> {
    let s = at.secs_since(start);
    let (amplitude, period) = WEAVE;
    let w = 2.0 * std::f64::consts::PI / period;
    let x = EGO_SPEED * s;
    let y = amplitude * (w * s).sin();
    let yaw = (amplitude * w * (w * s).cos()).atan2(EGO_SPEED);
    Isometry3::from_parts(
        Translation3::new(x, y, 0.0),
        UnitQuaternion::from_euler_angles(0.0, 0.0, yaw),
    )
}

/// One camera of the rig.
#[derive(Debug, Clone)]
pub struct CameraRig {
    /// nuScenes channel name (`CAM_FRONT`, ...).
    pub name: &'static str,
    /// Body mount of the camera (x forward), before the optical axis swap.
    pub ego_from_camera_body: Isometry3<f64>,
    /// Intrinsics and distortion.
    pub calibration: CameraCalibration,
}

impl CameraRig {
    /// `ego_from_camera` for the optical frame (x right, y down, z forward).
    pub fn ego_from_optical(&self) -> Isometry3<f64> {
        self.ego_from_camera_body * body_from_optical()
    }
}

/// The rotation from an optical frame (x right, y down, z forward) to the body frame
/// it is attached to (x forward, y left, z up).
pub fn body_from_optical() -> Isometry3<f64> {
    let r = Rotation3::from_matrix_unchecked(nalgebra::Matrix3::new(
        0.0, 0.0, 1.0, //
        -1.0, 0.0, 0.0, //
        0.0, -1.0, 0.0,
    ));
    Isometry3::from_parts(
        Translation3::identity(),
        UnitQuaternion::from_rotation_matrix(&r),
    )
}

/// The sensor rig: LiDAR mount and six surround cameras.
#[derive(Debug, Clone)]
pub struct Rig {
    /// LiDAR mount; rotated −90° about z as nuScenes' `LIDAR_TOP` (x right, y forward).
    pub ego_from_lidar: Isometry3<f64>,
    /// Beam elevations, lowest first (ring 0), radians.
    pub beam_elevations: Vec<f64>,
    /// Firings per revolution.
    pub columns: usize,
    /// Nanoseconds between two successive beams of a column, lowest first (0: at once).
    pub beam_interval_nanos: i64,
    /// The cameras, in nuScenes order.
    pub cameras: Vec<CameraRig>,
}

impl Rig {
    /// The rig with images of `width × height` and the given lens distortion.
    pub fn new(width: u32, height: u32, distortion: Distortion) -> Self {
        let mount = |x: f64, y: f64, z: f64, yaw_deg: f64| {
            Isometry3::from_parts(
                Translation3::new(x, y, z),
                UnitQuaternion::from_euler_angles(0.0, 2.0f64.to_radians(), yaw_deg.to_radians()),
            )
        };
        let specs = [
            ("CAM_FRONT", mount(1.70, 0.00, 1.52, 0.0), 70.0),
            ("CAM_FRONT_RIGHT", mount(1.55, -0.49, 1.50, -55.0), 70.0),
            ("CAM_BACK_RIGHT", mount(1.03, -0.48, 1.57, -110.0), 70.0),
            ("CAM_BACK", mount(0.03, 0.00, 1.57, 180.0), 100.0),
            ("CAM_BACK_LEFT", mount(1.04, 0.48, 1.57, 110.0), 70.0),
            ("CAM_FRONT_LEFT", mount(1.52, 0.49, 1.51, 55.0), 70.0),
        ];
        let cameras = specs
            .iter()
            .enumerate()
            .map(|(i, (name, ego_from_camera_body, hfov_deg))| {
                let fx = f64::from(width) / 2.0 / (hfov_deg / 2.0f64).to_radians().tan();
                let fy = fx * 1.004;
                let cx = f64::from(width) / 2.0 - 0.5 + 2.3 - i as f64 * 0.4;
                let cy = f64::from(height) / 2.0 - 0.5 - 1.6 + i as f64 * 0.3;
                CameraRig {
                    name,
                    ego_from_camera_body: *ego_from_camera_body,
                    calibration: CameraCalibration {
                        stamp: Stamp::default(),
                        frame_id: (*name).to_string(),
                        width,
                        height,
                        k: nalgebra::Matrix3::new(fx, 0.0, cx, 0.0, fy, cy, 0.0, 0.0, 1.0),
                        distortion,
                    },
                }
            })
            .collect();
        Rig {
            ego_from_lidar: Isometry3::from_parts(
                Translation3::new(0.94, 0.0, 1.84),
                UnitQuaternion::from_euler_angles(0.0, 0.0, -std::f64::consts::FRAC_PI_2),
            ),
            beam_elevations: beam_elevations(16),
            columns: 300,
            beam_interval_nanos: 0,
            cameras,
        }
    }
}

/// Azimuth in the LiDAR frame of column `c` of `columns` (0 = first firing of a sweep):
/// the LiDAR spins clockwise seen from above, starting behind the sensor.
pub fn column_azimuth(column: usize, columns: usize) -> f64 {
    PI * 1.5 - TAU * column as f64 / columns as f64
}

/// Elevations of `beams` LiDAR beams, lowest first, radians: 16 beams spread evenly over
/// -25°..+5° (the sample drives), any other count over an HDL-32E-like -30.67°..+10.67°
/// (one beam: the middle of that).
pub fn beam_elevations(beams: usize) -> Vec<f64> {
    let (low, high) = if beams == 16 {
        (-25.0, 5.0)
    } else {
        (-30.67, 10.67)
    };
    if beams < 2 {
        return vec![((low + high) / 2.0f64).to_radians(); beams];
    }
    (0..beams)
        .map(|b| (low + (high - low) * b as f64 / (beams - 1) as f64).to_radians())
        .collect()
}

/// One LiDAR return, before it is expressed in any sensor frame.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct Return {
    /// Hit point in the map frame.
    pub point_in_map: Point3<f64>,
    /// Firing time.
    pub stamp: Stamp,
    /// Beam index (0 = lowest).
    pub ring: u16,
    /// Intensity in 0..255.
    pub intensity: f32,
    /// Semantic class of the surface hit.
    pub class: u8,
    /// Id of the scene box hit ([`crate::scene::Hit::object`]); `None` for the ground.
    /// Simulation ground truth, not written to the drive.
    pub object: Option<u32>,
}

/// Fires every column of sweep `k`: column `c` at `begin + c·T/C`, beams bottom to top,
/// beam `b` [`Rig::beam_interval_nanos`]` · b` after its column.
pub fn simulate_sweep(scene: &Scene, rig: &Rig, timing: &DriveTiming, k: usize) -> Vec<Return> {
    let (begin, _) = timing.sweep_span(k);
    let mut out = Vec::with_capacity(rig.columns * rig.beam_elevations.len());
    for c in 0..rig.columns {
        let column = begin.add_nanos(c as i64 * timing.sweep_nanos / rig.columns as i64);
        // Clockwise spin seen from above, starting behind the sensor.
        let azimuth = column_azimuth(c, rig.columns);
        let mut pose = None;
        for (ring, elevation) in rig.beam_elevations.iter().enumerate() {
            let stamp = column.add_nanos(ring as i64 * rig.beam_interval_nanos);
            let (map_from_lidar, t_secs) = match pose {
                Some((at, iso, t)) if at == stamp => (iso, t),
                _ => {
                    let iso = map_from_ego(timing.start, stamp) * rig.ego_from_lidar;
                    let t = stamp.secs_since(timing.start);
                    pose = Some((stamp, iso, t));
                    (iso, t)
                }
            };
            let origin = map_from_lidar.translation.vector.into();
            let d_lidar = Vector3::new(
                elevation.cos() * azimuth.cos(),
                elevation.cos() * azimuth.sin(),
                elevation.sin(),
            );
            let direction = map_from_lidar.rotation * d_lidar;
            if let Some(hit) = scene.cast(&origin, &direction, t_secs, LIDAR_MAX_RANGE) {
                let incidence = hit.normal.dot(&direction).abs();
                let intensity = (255.0 * hit.reflectivity * (0.3 + 0.7 * incidence)).round();
                out.push(Return {
                    point_in_map: hit.point,
                    stamp,
                    ring: ring as u16,
                    intensity: intensity as f32,
                    class: hit.class,
                    object: hit.object,
                });
            }
        }
    }
    out
}

/// Number of classes in the class maps.
pub const CLASS_COUNT: usize = CLASSES.len();
