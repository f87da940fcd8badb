//! When a spinning LiDAR looks at each camera. A sweep is not an instant: its points are
//! fired over a whole revolution (50 ms at 20 Hz), and a rig like nuScenes' triggers
//! each camera as the beam passes through its field of view. A camera image and a sweep
//! match best when the image was taken as the LiDAR scanned that camera's direction —
//! the sweep's stamp (its start or its end, by driver) can be up to a revolution away
//! from that moment.
//!
//! [`scan_offsets`] measures, once per drive, for every camera the time between the
//! sweep stamp and the moment the LiDAR fires along the camera's optical axis: from one
//! sweep's points near that azimuth, with their per-point time when the message has one,
//! else with the firing order (points in message order over the revolution that ends at
//! the stamp, the nuScenes convention for motion-compensated sweeps). A spinning LiDAR
//! repeats the same pattern every revolution, so one sweep is enough. The images of a
//! sample are then the ones nearest `sweep stamp + offset` ([`SampleConfig::camera_sync`]
//! `scan`), and keyframes are the sweeps whose cameras are nearest their scan moments.

use super::recipe::{CameraSync, SampleConfig};
use crate::drive::Drive;
use crate::source::ChunkCache;
use nalgebra::Vector3;
use serde::Serialize;

/// Half-width of the azimuth sector around a camera's axis whose points time its scan.
const SECTOR_RAD: f64 = 2.0 * std::f64::consts::PI / 180.0;

/// Fewest points in that sector for a measurement (else the offset is 0: the stamp).
const MIN_POINTS: usize = 8;

/// How the moments a drive's LiDAR scans its cameras were found.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Serialize)]
#[serde(rename_all = "snake_case")]
pub enum ScanTiming {
    /// From the sweep's per-point time field.
    PointTime,
    /// From the firing order of the points (no time field; the sweep ends at its stamp).
    PointOrder,
    /// Not measured (no sweep could be read, `camera_sync = "stamp"`): the sweep stamp.
    Stamp,
}

/// Per camera of a drive, the moments the LiDAR scans along its axis relative to the
/// sweep stamp, nanoseconds (in the drive's camera order), and how they were found. A
/// camera at the azimuth where the driver cuts its sweeps is scanned twice, at the start
/// and at the end: it has two moments; every other camera one.
#[derive(Debug, Clone, PartialEq, Serialize)]
pub struct CameraScan {
    /// Offsets from the sweep stamp, per camera one or two.
    pub offsets_nanos: Vec<Vec<i64>>,
    /// How they were found.
    pub timing: ScanTiming,
}

impl CameraScan {
    /// Every camera at the sweep stamp.
    fn at_stamp(cameras: usize) -> Self {
        Self {
            offsets_nanos: vec![vec![0]; cameras],
            timing: ScanTiming::Stamp,
        }
    }
}

/// The scan moments of sorted firing times near one azimuth: their median, or the
/// medians of the two groups when they straddle the sweep's cut (a gap of more than
/// half a revolution).
fn moments(sorted: &[f64], period: i64) -> Vec<i64> {
    let median = |t: &[f64]| t[t.len() / 2].round() as i64;
    let gap = sorted
        .windows(2)
        .enumerate()
        .max_by(|a, b| (a.1[1] - a.1[0]).total_cmp(&(b.1[1] - b.1[0])));
    match gap {
        Some((i, w)) if w[1] - w[0] > period as f64 / 2.0 => {
            vec![median(&sorted[..=i]), median(&sorted[i + 1..])]
        }
        _ => vec![median(sorted)],
    }
}

/// The median gap between consecutive sweeps of the drive, nanoseconds (0 for fewer
/// than two).
pub(super) fn median_sweep_period(drive: &Drive) -> i64 {
    let Some(lidar) = &drive.lidar else { return 0 };
    let mut gaps: Vec<i64> = lidar
        .sweeps
        .windows(2)
        .map(|w| w[1].stamp.nanos_since(w[0].stamp))
        .collect();
    gaps.sort_unstable();
    gaps.get(gaps.len() / 2).copied().unwrap_or(0)
}

/// Wraps an angle difference into `(-π, π]`.
fn wrap(a: f64) -> f64 {
    let two_pi = 2.0 * std::f64::consts::PI;
    let r = a.rem_euclid(two_pi);
    if r > std::f64::consts::PI {
        r - two_pi
    } else {
        r
    }
}

/// The scan moments of `drive`'s cameras (see the module documentation); every camera
/// at the stamp when `config` says so or nothing can be measured.
pub fn scan_offsets(drive: &Drive, config: &SampleConfig) -> CameraScan {
    let cameras = drive.cameras.len();
    let Some(lidar) = drive.lidar.as_ref().filter(|l| !l.sweeps.is_empty()) else {
        return CameraScan::at_stamp(cameras);
    };
    if config.camera_sync == CameraSync::Stamp {
        return CameraScan::at_stamp(cameras);
    }
    let frame = &lidar.sweeps[lidar.sweeps.len() / 2];
    let mut cache = ChunkCache::new(2);
    let decoded = match drive.read_sweep(frame, &mut cache) {
        Ok(d) => d,
        Err(e) => {
            tracing::warn!("camera timing: cameras matched at the sweep stamp ({e})");
            return CameraScan::at_stamp(cameras);
        }
    };
    let cloud = &decoded.cloud;
    let period = median_sweep_period(drive);
    let n = cloud.len().max(1) as f64;
    let (timing, times): (ScanTiming, Vec<f64>) = match &cloud.time_offset_secs {
        Some(t) => (
            ScanTiming::PointTime,
            t.iter().map(|s| f64::from(*s) * 1e9).collect(),
        ),
        None => (
            ScanTiming::PointOrder,
            (0..cloud.len())
                .map(|i| -(period as f64) + period as f64 * (i as f64 + 0.5) / n)
                .collect(),
        ),
    };
    let azimuths: Vec<Option<f64>> = cloud
        .xyz
        .iter()
        .map(|p| {
            let (x, y) = (f64::from(p[0]), f64::from(p[1]));
            (x.hypot(y) > 1.0).then(|| y.atan2(x))
        })
        .collect();
    let offsets_nanos = drive
        .cameras
        .iter()
        .map(|camera| {
            let Ok(lidar_from_camera) =
                drive
                    .tf
                    .lookup(&lidar.frame_id, &camera.frame_id, cloud.stamp)
            else {
                return vec![0];
            };
            let axis = lidar_from_camera.rotation * Vector3::z();
            let azimuth = axis.y.atan2(axis.x);
            let mut near: Vec<f64> = azimuths
                .iter()
                .zip(&times)
                .filter(|(a, _)| a.is_some_and(|a| wrap(a - azimuth).abs() < SECTOR_RAD))
                .map(|(_, t)| *t)
                .collect();
            if near.len() < MIN_POINTS {
                return vec![0];
            }
            near.sort_by(f64::total_cmp);
            moments(&near, period)
        })
        .collect();
    CameraScan {
        offsets_nanos,
        timing,
    }
}
