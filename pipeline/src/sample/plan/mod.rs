//! The [`Plan`] of a dataset: every usable keyframe with the sweeps of its temporal
//! context (the nearest usable sweep to `t + k·Δt`, or the edge policy), and the
//! shuffled keyframe order of an epoch.

use super::recipe::{EdgePolicy, KeyframeChoice, SampleConfig};
use super::rng::{Purpose, SampleRng};
use super::timing::{CameraScan, ScanFrom, camera_scan, camera_scan_from, median_sweep_period};
use crate::drive::{CameraStream, Dataset, Drive, FrameRef, nearest};
use rayon::prelude::*;
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
    frame_within(
        camera,
        camera.period_nanos().unwrap_or(0) / 2,
        stamp,
        moments,
    )
}

/// [`camera_frame_for`] with the camera's half period `half` worked out by the caller.
fn frame_within<'a>(
    camera: &'a CameraStream,
    half: i64,
    stamp: Stamp,
    moments: &[i64],
) -> Option<(&'a FrameRef, i64)> {
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

/// Per sweep, its worst camera offset when it can be a frame of a sample (the ego pose
/// is known at the sweep, and every camera has a calibration and an image within half
/// its period of its scan instant whose pose is known); `None` when it cannot. Each
/// camera's period is worked out once and each pose looked up once: an image is the
/// nearest of several sweeps, and a sweep is a context frame of several keyframes.
fn usable_sweeps(drive: &Drive, scan: &CameraScan) -> Vec<Option<i64>> {
    let Some(lidar) = &drive.lidar else {
        return Vec::new();
    };
    let (Some(map), Some(ego)) = (&drive.map_frame, &drive.ego_frame) else {
        return vec![None; lidar.sweeps.len()];
    };
    if drive.cameras.is_empty() || drive.cameras.iter().any(|c| c.calibrations.is_empty()) {
        return vec![None; lidar.sweeps.len()];
    }
    let pose_ok = |s: Stamp| drive.tf.lookup(map, ego, s).is_ok();
    let halves: Vec<i64> = drive
        .cameras
        .iter()
        .map(|c| c.period_nanos().unwrap_or(0) / 2)
        .collect();
    let mut image_pose: Vec<Vec<Option<bool>>> = drive
        .cameras
        .iter()
        .map(|c| vec![None; c.frames.len()])
        .collect();
    lidar
        .sweeps
        .iter()
        .map(|sweep| {
            if !pose_ok(sweep.stamp) {
                return None;
            }
            let mut worst = 0;
            let cameras = drive.cameras.iter().zip(&scan.offsets_nanos);
            for ((camera, moments), (half, poses)) in
                cameras.zip(halves.iter().zip(&mut image_pose))
            {
                let (frame, offset) = frame_within(camera, *half, sweep.stamp, moments)?;
                // Frames are sorted by stamp, no two alike.
                let f = camera.frames.partition_point(|x| x.stamp < frame.stamp);
                if !*poses[f].get_or_insert_with(|| pose_ok(frame.stamp)) {
                    return None;
                }
                worst = worst.max(offset.abs());
            }
            Some(worst)
        })
        .collect()
}

/// The keyframes of `drive` with their worst camera offsets, from its usable sweeps
/// ([`usable_sweeps`]): one per interval of `interval` nanoseconds from the first usable
/// sweep (the least offset, the earliest on a tie), or the first usable sweep and the
/// next at least an interval later.
fn keyframes(
    drive: &Drive,
    usable: &[Option<i64>],
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
        let Some(worst) = usable.get(i).copied().flatten() else {
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

/// The usable sweeps of `drive` ([`usable_sweeps`]); none looked at when its ego poses
/// are missing (it has no keyframes).
fn usable_unless_poseless(drive: &Drive, scan: &CameraScan) -> Vec<Option<i64>> {
    if drive.ego_poses_missing() {
        Vec::new()
    } else {
        usable_sweeps(drive, scan)
    }
}

/// When `drive`'s LiDAR scans its cameras (through the index cache, see
/// [`camera_scan`]), and its keyframes (sweep index, worst camera offset in
/// nanoseconds) under `config`'s interval and choice.
pub fn drive_keyframes(drive: &Drive, config: &SampleConfig) -> (CameraScan, Vec<(usize, i64)>) {
    let scan = camera_scan(drive, config);
    let interval = (config.keyframe_interval_secs * 1e9).round() as i64;
    let usable = usable_unless_poseless(drive, &scan);
    let keys = keyframes(drive, &usable, interval, config.keyframe_choice);
    (scan, keys)
}

/// Where the camera scans of a plan came from, in drives.
#[derive(Debug, Clone, Copy, Default, PartialEq, Eq, Serialize)]
pub struct ScanCounts {
    /// Read from the index cache.
    pub from_cache: usize,
    /// Measured from a sweep.
    pub measured: usize,
    /// Not measured: every camera at the sweep stamp.
    pub at_stamp: usize,
}

/// The part of the plan one drive contributes.
struct DrivePlan {
    keyframes: Vec<KeyframeRef>,
    skipped_at_edges: u64,
    scan: CameraScan,
    from: ScanFrom,
}

/// The keyframes of drive number `d` with their context frames (see [`Plan::new`]).
fn plan_drive(d: usize, drive: &Drive, config: &SampleConfig) -> DrivePlan {
    let interval = (config.keyframe_interval_secs * 1e9).round() as i64;
    let delta = (config.delta_t_secs * 1e9).round() as i64;
    let (scan, from) = camera_scan_from(drive, config);
    let mut out = DrivePlan {
        keyframes: Vec::new(),
        skipped_at_edges: 0,
        scan,
        from,
    };
    let Some(lidar) = &drive.lidar else {
        return out;
    };
    let usable = usable_unless_poseless(drive, &out.scan);
    let half_period = median_sweep_period(drive) / 2;
    for (key, worst) in keyframes(drive, &usable, interval, config.keyframe_choice) {
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
                .filter(|&i| usable[i].is_some());
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
            out.skipped_at_edges += 1;
        } else {
            out.keyframes.push(KeyframeRef {
                drive: d as u32,
                sweep: key as u32,
                frame_sweeps,
                reused,
                worst_camera_offset_nanos: worst,
            });
        }
    }
    out
}

impl Plan {
    /// Keyframes of every drive (one per `keyframe_interval_secs`, chosen by
    /// `keyframe_choice`) with their context frames: the sweep nearest to `t + k·Δt` if
    /// within half a LiDAR period and usable, else the edge policy decides. Drives are
    /// planned in parallel (each on its own, the camera scan from the index cache when
    /// it holds it) and joined in dataset order.
    pub fn new(dataset: &Dataset, config: &SampleConfig) -> Plan {
        Self::with_counts(dataset, config).0
    }

    /// [`Plan::new`], and where its camera scans came from.
    pub fn with_counts(dataset: &Dataset, config: &SampleConfig) -> (Plan, ScanCounts) {
        let paths = dataset
            .drives
            .iter()
            .flat_map(|d| d.files.iter().map(|f| f.path()));
        // A measured scan reads a sweep: of a drive in an object store, over the network.
        let drives: Vec<DrivePlan> = crate::source::on_read_pool(paths, || {
            dataset
                .drives
                .par_iter()
                .enumerate()
                // One drive per task: a drive whose scan is measured takes far longer
                // than one whose scan is read.
                .with_max_len(1)
                .map(|(d, drive)| plan_drive(d, drive, config))
                .collect()
        });
        let mut plan = Plan {
            keyframes: Vec::with_capacity(drives.iter().map(|p| p.keyframes.len()).sum()),
            skipped_at_edges: 0,
            scans: Vec::with_capacity(drives.len()),
        };
        let mut counts = ScanCounts::default();
        for drive in drives {
            plan.keyframes.extend(drive.keyframes);
            plan.skipped_at_edges += drive.skipped_at_edges;
            plan.scans.push(drive.scan);
            *match drive.from {
                ScanFrom::Cache => &mut counts.from_cache,
                ScanFrom::Measured => &mut counts.measured,
                ScanFrom::Stamp => &mut counts.at_stamp,
            } += 1;
        }
        (plan, counts)
    }

    /// The keyframe order of `epoch`: a shuffle seeded by `(seed, epoch)`.
    pub fn epoch_order(&self, seed: u64, epoch: u64) -> Vec<u32> {
        let mut order: Vec<u32> = (0..self.keyframes.len() as u32).collect();
        SampleRng::new(seed, epoch, 0, Purpose::Shuffle).shuffle(&mut order);
        order
    }
}

#[cfg(test)]
mod tests;
