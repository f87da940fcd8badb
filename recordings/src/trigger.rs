//! Camera triggering: the fixed phases of the sample drives, or nuScenes-style staggered
//! triggers, where each camera fires as the spinning LiDAR's beam passes the centre of its
//! field of view. The phase comes from the rig's geometry: the LiDAR mount and the
//! camera's body yaw.

use crate::options::CameraTrigger;

use crate::sim::{DriveTiming, Rig};
use nalgebra::Vector3;
use std::f64::consts::{PI, TAU};
use superflow_schemas::Stamp;

/// Yaw of camera `camera`'s viewing direction (body x axis) in the ego frame, radians.
pub fn camera_yaw(rig: &Rig, camera: usize) -> Option<f64> {
    let cam = rig.cameras.get(camera)?;
    let forward = cam.ego_from_camera_body.rotation * Vector3::x();
    Some(forward.y.atan2(forward.x))
}

/// The fraction of a revolution, in `[0, 1)`, at which the LiDAR's beam points along the
/// ego-frame yaw `yaw`.
pub fn sweep_fraction_at_yaw(rig: &Rig, yaw: f64) -> f64 {
    let in_ego = Vector3::new(yaw.cos(), yaw.sin(), 0.0);
    let in_lidar = rig.ego_from_lidar.rotation.inverse() * in_ego;
    let azimuth = in_lidar.y.atan2(in_lidar.x);
    // column_azimuth(f·C, C) = 1.5π − 2π·f = azimuth (mod 2π).
    ((PI * 1.5 - azimuth) / TAU).rem_euclid(1.0)
}

/// The time within a sweep, in `[0, sweep_nanos)`, at which the LiDAR's beam passes the
/// centre of camera `camera`'s field of view.
pub fn trigger_phase_nanos(rig: &Rig, camera: usize, sweep_nanos: i64) -> Option<i64> {
    let yaw = camera_yaw(rig, camera)?;
    let phase = (sweep_fraction_at_yaw(rig, yaw) * sweep_nanos as f64).round() as i64;
    Some(phase.rem_euclid(sweep_nanos))
}

impl DriveTiming {
    /// Stamps of a camera firing `phase_nanos` after the start and then every camera
    /// period, rounded down to the stamp quantum, up to the end of the drive.
    pub fn camera_stamps_at_phase(&self, phase_nanos: i64) -> Vec<Stamp> {
        let end = self.start.add_nanos(self.duration_nanos);
        (0..)
            .map(|n| {
                let raw = phase_nanos + n * self.camera_period_nanos;
                self.start
                    .add_nanos(raw - raw.rem_euclid(self.quantum_nanos))
            })
            .take_while(|s| *s < end)
            .collect()
    }
}

/// Stamps of camera `camera` of `rig` under `trigger` (empty for a camera the rig lacks).
pub fn camera_stamps(
    trigger: CameraTrigger,
    timing: &DriveTiming,
    rig: &Rig,
    camera: usize,
) -> Vec<Stamp> {
    match trigger {
        CameraTrigger::Fixed => timing.camera_stamps(camera),
        CameraTrigger::Staggered => trigger_phase_nanos(rig, camera, timing.sweep_nanos)
            .map(|phase| timing.camera_stamps_at_phase(phase))
            .unwrap_or_default(),
    }
}

#[cfg(test)]
mod tests {
    #![allow(clippy::unwrap_used)] // tests fail loudly on purpose
    use super::*;
    use crate::dialect::Dialect;
    use crate::sim::column_azimuth;
    use superflow_schemas::sensor::Distortion;

    /// Angle between two azimuths, in `[0, π]`.
    fn angle_between(a: f64, b: f64) -> f64 {
        let d = (a - b).rem_euclid(TAU);
        d.min(TAU - d)
    }

    #[test]
    fn staggered_cameras_fire_as_the_beam_passes_their_centre() {
        let mut rig = Rig::new(800, 450, Distortion::None);
        rig.columns = 1084;
        let mut timing = Dialect::Foxglove.timing();
        timing.duration_nanos = 2_000_000_000;
        let lidar_yaw = {
            let x = rig.ego_from_lidar.rotation * Vector3::x();
            x.y.atan2(x.x)
        };
        let column_angle = TAU / rig.columns as f64;
        for camera in 0..rig.cameras.len() {
            let yaw = camera_yaw(&rig, camera).unwrap();
            let stamps = camera_stamps(CameraTrigger::Staggered, &timing, &rig, camera);
            assert!((24..=25).contains(&stamps.len()), "12 Hz for 2 s");
            let mut checked = 0;
            // Three camera periods are five sweeps (to 1 ns a period): stamp 3m falls in
            // sweep 5m, or at the very end of sweep 5m − 1 for a phase of about 0.
            for (n, stamp) in stamps.iter().enumerate().step_by(3) {
                let since_start = stamp.nanos_since(timing.start);
                let k = since_start.div_euclid(timing.sweep_nanos);
                let expected = (n / 3 * 5) as i64;
                assert!(
                    k == expected || k == expected - 1,
                    "{camera} {n}: sweep {k}"
                );
                let since = since_start - k * timing.sweep_nanos;
                // The column fired last at or before the stamp.
                let column = (0..rig.columns)
                    .rev()
                    .find(|c| *c as i64 * timing.sweep_nanos / rig.columns as i64 <= since)
                    .unwrap();
                let azimuth = lidar_yaw + column_azimuth(column, rig.columns);
                let off = angle_between(azimuth, yaw);
                assert!(
                    off <= column_angle + 1e-9,
                    "camera {camera}, stamp {n}: beam at {azimuth}, camera yaw {yaw}: {off} rad off"
                );
                checked += 1;
            }
            assert_eq!(checked, stamps.len().div_ceil(3));
        }
    }

    #[test]
    fn the_front_camera_fires_mid_sweep_and_the_back_camera_at_its_start() {
        let rig = Rig::new(480, 270, Distortion::None);
        let sweep = 50_000_000;
        assert_eq!(trigger_phase_nanos(&rig, 0, sweep), Some(25_000_000));
        let back = trigger_phase_nanos(&rig, 3, sweep).unwrap();
        assert!(back < 1_000 || back > sweep - 1_000, "{back}");
        // Clockwise: front-right after the front, front-left before it.
        assert!(trigger_phase_nanos(&rig, 1, sweep).unwrap() > 25_000_000);
        assert!(trigger_phase_nanos(&rig, 5, sweep).unwrap() < 25_000_000);
        assert_eq!(trigger_phase_nanos(&rig, 6, sweep), None);
    }

    #[test]
    fn fixed_triggers_are_the_sample_drives_stamps() {
        let rig = Rig::new(480, 270, Distortion::None);
        let timing = Dialect::Ros2.timing();
        for camera in 0..6 {
            assert_eq!(
                camera_stamps(CameraTrigger::Fixed, &timing, &rig, camera),
                timing.camera_stamps(camera)
            );
        }
    }
}
