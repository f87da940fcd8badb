//! The [`Plan`] of a dataset: every usable keyframe with the sweeps of its temporal
//! context (the nearest usable sweep to `t + k·Δt`, or the edge policy), and the
//! shuffled keyframe order of an epoch.

use super::recipe::{EdgePolicy, KeyframeChoice, SampleConfig};
use super::rng::{Purpose, SampleRng};
use super::timing::{CameraScan, median_sweep_period, scan_offsets};
use crate::drive::{CameraStream, Dataset, Drive, FrameRef, nearest};
use serde::Serialize;
use superflow_schemas::Stamp;

/// One keyframe of the plan and the sweeps of its temporal frames.
#[derive(Debug, Clone, PartialEq, Eq, Serialize)]
pub struct KeyframeRef {
    /// Drive index in the dataset.
    pub drive: u32,
    /// LiDAR sweep index of the keyframe.
    pub sweep: u32,
    /// Sweep index of each temporal frame, in time order (see
    /// [`SampleConfig::frame_offsets`]); the keyframe's own index where the edge policy
    /// reused it.
    pub frame_sweeps: Vec<u32>,
    /// Context frames that fell outside the drive and were replaced by the keyframe.
    pub reused: u32,
    /// The keyframe's worst camera offset: the largest time between a camera's image and
    /// the moment the LiDAR scanned that camera's direction, nanoseconds.
    pub worst_camera_offset_nanos: i64,
}

/// Every usable keyframe of a dataset, in drive and time order.
#[derive(Debug, Clone, Default, Serialize)]
pub struct Plan {
    /// The keyframes.
    pub keyframes: Vec<KeyframeRef>,
    /// Keyframes left out because a context frame was missing (edge policy `skip`).
    pub skipped_at_edges: u64,
    /// Per drive, when its LiDAR scans each camera.
    pub scans: Vec<CameraScan>,
}

/// The image of `camera` for a sweep at `stamp` whose LiDAR scans the camera at
/// `stamp + m` for each of `moments`: the image nearest one of those instants, if within
/// half the camera's period of it; also its offset (image stamp − scan instant).
pub(super) fn camera_frame_for<'a>(
    camera: &'a CameraStream,
    stamp: Stamp,
    moments: &[i64],
) -> Option<(&'a FrameRef, i64)> {
    let half = camera.period_nanos().unwrap_or(0) / 2;
    moments
        .iter()
        .filter_map(|m| {
            let target = stamp.add_nanos(*m);
            nearest(&camera.frames, target)
                .map(|f| (f, f.stamp.nanos_since(target)))
                .filter(|(_, offset)| offset.abs() <= half)
        })
        .min_by_key(|(_, offset)| offset.abs())
}

/// The worst camera offset of sweep `i` when it can be a frame of a sample (the ego pose
/// is known at the sweep, and every camera has a calibration and an image within half
/// its period of its scan instant whose pose is known); `None` when it cannot.
fn usable(drive: &Drive, scan: &CameraScan, i: usize) -> Option<i64> {
    let (Some(lidar), Some(map), Some(ego)) = (&drive.lidar, &drive.map_frame, &drive.ego_frame)
    else {
        return None;
    };
    let sweep = lidar.sweeps.get(i)?;
    let pose_ok = |s: Stamp| drive.tf.lookup(map, ego, s).is_ok();
    if !pose_ok(sweep.stamp) || drive.cameras.is_empty() {
        return None;
    }
    let mut worst = 0;
    for (camera, moments) in drive.cameras.iter().zip(&scan.offsets_nanos) {
        let (frame, offset) = camera_frame_for(camera, sweep.stamp, moments)?;
        if !pose_ok(frame.stamp) || camera.calibrations.is_empty() {
            return None;
        }
        worst = worst.max(offset.abs());
    }
    Some(worst)
}

/// The keyframes of `drive` with their worst camera offsets: one per interval of
/// `interval` nanoseconds from the first usable sweep (the least offset, the earliest
/// on a tie), or the first usable sweep and the next at least an interval later.
fn keyframes(
    drive: &Drive,
    scan: &CameraScan,
    interval: i64,
    choice: KeyframeChoice,
) -> Vec<(usize, i64)> {
    let Some(lidar) = &drive.lidar else {
        return Vec::new();
    };
    if drive.ego_poses_missing() {
        return Vec::new();
    }
    let mut out: Vec<(usize, i64)> = Vec::new();
    let mut first: Option<Stamp> = None;
    let mut window = 0;
    for (i, sweep) in lidar.sweeps.iter().enumerate() {
        let Some(worst) = usable(drive, scan, i) else {
            continue;
        };
        let t0 = *first.get_or_insert(sweep.stamp);
        let since = sweep.stamp.nanos_since(t0);
        match choice {
            KeyframeChoice::First => {
                let last = out.last().map(|(k, _)| lidar.sweeps[*k].stamp);
                if last.is_none_or(|l| sweep.stamp.nanos_since(l) >= interval) {
                    out.push((i, worst));
                }
            }
            KeyframeChoice::LeastCameraOffset => {
                let w = since / interval.max(1);
                match out.last_mut() {
                    Some(last) if w == window => {
                        if worst < last.1 {
                            *last = (i, worst);
                        }
                    }
                    _ => {
                        window = w;
                        out.push((i, worst));
                    }
                }
            }
        }
    }
    out
}

/// When `drive`'s LiDAR scans its cameras, and its keyframes (sweep index, worst camera
/// offset in nanoseconds) under `config`'s interval and choice.
pub fn drive_keyframes(drive: &Drive, config: &SampleConfig) -> (CameraScan, Vec<(usize, i64)>) {
    let scan = scan_offsets(drive, config);
    let interval = (config.keyframe_interval_secs * 1e9).round() as i64;
    let keys = keyframes(drive, &scan, interval, config.keyframe_choice);
    (scan, keys)
}

impl Plan {
    /// Keyframes of every drive (one per `keyframe_interval_secs`, chosen by
    /// `keyframe_choice`) with their context frames: the sweep nearest to `t + k·Δt` if
    /// within half a LiDAR period and usable, else the edge policy decides.
    pub fn new(dataset: &Dataset, config: &SampleConfig) -> Plan {
        let mut plan = Plan::default();
        let interval = (config.keyframe_interval_secs * 1e9).round() as i64;
        let delta = (config.delta_t_secs * 1e9).round() as i64;
        for (d, drive) in dataset.drives.iter().enumerate() {
            let scan = scan_offsets(drive, config);
            let Some(lidar) = &drive.lidar else {
                plan.scans.push(scan);
                continue;
            };
            let half_period = median_sweep_period(drive) / 2;
            for (key, worst) in keyframes(drive, &scan, interval, config.keyframe_choice) {
                let t = lidar.sweeps[key].stamp;
                let mut frame_sweeps = Vec::new();
                let mut reused = 0;
                let mut skip = false;
                for &offset in config.frame_offsets() {
                    if offset == 0 {
                        frame_sweeps.push(key as u32);
                        continue;
                    }
                    let target = t.add_nanos(i64::from(offset) * delta);
                    let found = nearest(&lidar.sweeps, target)
                        .filter(|f| f.stamp.nanos_since(target).abs() <= half_period)
                        .map(|f| lidar.sweeps.partition_point(|s| s.stamp < f.stamp))
                        .filter(|&i| usable(drive, &scan, i).is_some());
                    match (found, config.edge) {
                        (Some(i), _) => frame_sweeps.push(i as u32),
                        (None, EdgePolicy::Reuse) => {
                            frame_sweeps.push(key as u32);
                            reused += 1;
                        }
                        (None, EdgePolicy::Skip) => skip = true,
                    }
                }
                if skip {
                    plan.skipped_at_edges += 1;
                } else {
                    plan.keyframes.push(KeyframeRef {
                        drive: d as u32,
                        sweep: key as u32,
                        frame_sweeps,
                        reused,
                        worst_camera_offset_nanos: worst,
                    });
                }
            }
            plan.scans.push(scan);
        }
        plan
    }

    /// The keyframe order of `epoch`: a shuffle seeded by `(seed, epoch)`.
    pub fn epoch_order(&self, seed: u64, epoch: u64) -> Vec<u32> {
        let mut order: Vec<u32> = (0..self.keyframes.len() as u32).collect();
        SampleRng::new(seed, epoch, 0, Purpose::Shuffle).shuffle(&mut order);
        order
    }
}
