//! The [`Plan`] of a dataset: every usable keyframe with the sweeps of its temporal
//! context (the nearest usable sweep to `t + k·Δt`, or the edge policy), and the
//! shuffled keyframe order of an epoch.

use super::recipe::{EdgePolicy, SampleConfig};
use super::rng::{Purpose, SampleRng};
use crate::drive::dataset::{CameraStream, Dataset, Drive, FrameRef, nearest};
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
}

/// Every usable keyframe of a dataset, in drive and time order.
#[derive(Debug, Clone, Default, Serialize)]
pub struct Plan {
    /// The keyframes.
    pub keyframes: Vec<KeyframeRef>,
    /// Keyframes left out because a context frame was missing (edge policy `skip`).
    pub skipped_at_edges: u64,
}

/// Whether sweep `i` can be a frame of a sample: the ego pose is known at the sweep and
/// every camera has a calibration and an image within half its period whose pose is
/// known.
fn usable(drive: &Drive, i: usize) -> bool {
    let (Some(lidar), Some(map), Some(ego)) = (&drive.lidar, &drive.map_frame, &drive.ego_frame)
    else {
        return false;
    };
    let Some(sweep) = lidar.sweeps.get(i) else {
        return false;
    };
    let pose_ok = |s: Stamp| drive.tf.lookup(map, ego, s).is_ok();
    pose_ok(sweep.stamp)
        && !drive.cameras.is_empty()
        && drive.cameras.iter().all(|camera| {
            camera_frame_for(camera, sweep.stamp).is_some_and(|f| pose_ok(f.stamp))
                && !camera.calibrations.is_empty()
        })
}

/// The image of `camera` for a sweep at `stamp`: the nearest one, if within half the
/// camera's period.
pub(super) fn camera_frame_for(camera: &CameraStream, stamp: Stamp) -> Option<&FrameRef> {
    let half = camera.period_nanos().unwrap_or(0) / 2;
    nearest(&camera.frames, stamp).filter(|f| f.stamp.nanos_since(stamp).abs() <= half)
}

/// The median gap between consecutive sweeps of the drive, nanoseconds (0 for fewer
/// than two).
fn median_sweep_period(drive: &Drive) -> i64 {
    let Some(lidar) = &drive.lidar else { return 0 };
    let mut gaps: Vec<i64> = lidar
        .sweeps
        .windows(2)
        .map(|w| w[1].stamp.nanos_since(w[0].stamp))
        .collect();
    gaps.sort_unstable();
    gaps.get(gaps.len() / 2).copied().unwrap_or(0)
}

impl Plan {
    /// Keyframes of every drive (see `Drive::keyframes`) with their context frames: the
    /// sweep nearest to `t + k·Δt` if within half a LiDAR period and usable, else the
    /// edge policy decides.
    pub fn new(dataset: &Dataset, config: &SampleConfig) -> Plan {
        let mut plan = Plan::default();
        let interval = (config.keyframe_interval_secs * 1e9).round() as i64;
        let delta = (config.delta_t_secs * 1e9).round() as i64;
        for (d, drive) in dataset.drives.iter().enumerate() {
            let Some(lidar) = &drive.lidar else { continue };
            let half_period = median_sweep_period(drive) / 2;
            for key in drive.keyframes(interval) {
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
                        .filter(|&i| usable(drive, i));
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
                    });
                }
            }
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
