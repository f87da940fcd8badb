//! What a dataset is made of, at the scale of a fleet: its named groups (`[[dataset]]`)
//! with their keyframes and share of every epoch, and its rigs (sensor sets) with the
//! drives that share each. `index` and `inspect` print it, the service logs it at start
//! (one line per group and per rig, whatever the number of drives).

use crate::drive::rig::{LidarFacts, drive_ranges, rigs};
use crate::drive::{Dataset, Rig};
use crate::sample::Plan;
use crate::sample::epochs::per_epoch;
use rayon::prelude::*;
use serde::{Deserialize, Serialize};
use std::fmt::Write as _;

/// One group of the dataset.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct GroupReport {
    /// Its name.
    pub name: String,
    /// Serves per keyframe and epoch.
    pub repeat: f64,
    /// Its drives.
    pub drives: usize,
    /// Its usable keyframes.
    pub keyframes: usize,
    /// Samples it gives each epoch (keyframes × repeat, exactly).
    pub per_epoch: usize,
    /// Its share of each epoch, 0 to 1.
    pub share: f64,
}

/// One rig of the dataset.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct RigReport {
    /// The sensor set.
    pub rig: Rig,
    /// Its drives (0-based, dataset order).
    pub drives: Vec<usize>,
    /// Their usable keyframes.
    pub keyframes: usize,
    /// Points of the sweeps read for the LiDAR facts, fewest and most over the drives.
    pub points_per_sweep: Option<(usize, usize)>,
}

/// The groups and rigs of a dataset.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct FleetReport {
    /// Every group, in order.
    pub groups: Vec<GroupReport>,
    /// Every rig, in the order it first appears.
    pub rigs: Vec<RigReport>,
    /// Samples of an epoch, every group's.
    pub samples_per_epoch: usize,
}

/// The keyframes of each of `drives` drives in `plan`.
pub fn keyframes_per_drive(plan: &Plan, drives: usize) -> Vec<usize> {
    let mut counts = vec![0; drives];
    for k in &plan.keyframes {
        if let Some(c) = counts.get_mut(k.drive as usize) {
            *c += 1;
        }
    }
    counts
}

/// Each drive's LiDAR facts and the points of the sweep they were read from, as the
/// plan's camera scans learned them (from the index cache on a warm start: no sweep is
/// read again).
pub fn lidar_facts_of(plan: &Plan) -> Vec<Option<(LidarFacts, usize)>> {
    plan.scans.iter().map(|scan| scan.lidar).collect()
}

/// Each drive's LiDAR facts and the points of the sweep they were read from (its middle
/// one), drives in parallel; `None` for a drive whose sweep could not be read (said at
/// DEBUG: `inspect` reports the drive's problems).
pub fn read_lidar_facts(dataset: &Dataset) -> Vec<Option<(LidarFacts, usize)>> {
    dataset
        .drives
        .par_iter()
        .with_max_len(1)
        .map(|drive| match LidarFacts::read(drive) {
            Ok(facts) => facts,
            Err(e) => {
                tracing::debug!(files = %drive.file_list(), "LiDAR facts: {e}");
                None
            }
        })
        .collect()
}

impl FleetReport {
    /// The report of `dataset` with `keyframes[d]` usable keyframes in drive `d` and,
    /// per drive, its LiDAR's facts and the points of the sweep they were read from when
    /// a sweep was read (`lidar` may be empty: rigs are then told apart by their cameras
    /// and LiDAR topic).
    pub fn new(
        dataset: &Dataset,
        keyframes: &[usize],
        lidar: &[Option<(LidarFacts, usize)>],
    ) -> Self {
        let of_drives = |drives: &mut dyn Iterator<Item = usize>| {
            drives
                .map(|d| keyframes.get(d).copied().unwrap_or(0))
                .sum::<usize>()
        };
        let groups: Vec<(String, f64, usize, usize)> = dataset
            .groups
            .iter()
            .map(|g| {
                let n = of_drives(&mut g.drives.clone());
                (g.name.clone(), g.repeat, g.drives.len(), n)
            })
            .collect();
        let samples_per_epoch: usize = groups.iter().map(|(_, r, _, n)| per_epoch(*r, *n)).sum();
        let facts: Vec<Option<LidarFacts>> = lidar.iter().map(|l| l.map(|(f, _)| f)).collect();
        let rigs = rigs(&dataset.drives, &facts)
            .into_iter()
            .map(|share| {
                let points = share
                    .drives
                    .iter()
                    .filter_map(|&d| lidar.get(d).copied().flatten().map(|(_, p)| p));
                let points_per_sweep = points.fold(None, |range: Option<(usize, usize)>, p| {
                    Some(range.map_or((p, p), |(lo, hi)| (lo.min(p), hi.max(p))))
                });
                RigReport {
                    keyframes: of_drives(&mut share.drives.iter().copied()),
                    rig: share.rig,
                    drives: share.drives,
                    points_per_sweep,
                }
            })
            .collect();
        Self {
            groups: groups
                .into_iter()
                .map(|(name, repeat, drives, keyframes)| {
                    let per = per_epoch(repeat, keyframes);
                    GroupReport {
                        name,
                        repeat,
                        drives,
                        keyframes,
                        per_epoch: per,
                        share: per as f64 / samples_per_epoch.max(1) as f64,
                    }
                })
                .collect(),
            rigs,
            samples_per_epoch,
        }
    }

    /// One line per group, then one per rig.
    pub fn lines(&self) -> Vec<String> {
        let mut lines = Vec::new();
        for g in &self.groups {
            lines.push(format!(
                "group {}: {} drive(s), {} keyframes × repeat {} = {} samples an epoch ({:.1} %)",
                g.name,
                g.drives,
                g.keyframes,
                g.repeat,
                g.per_epoch,
                g.share * 100.0
            ));
        }
        for (i, r) in self.rigs.iter().enumerate() {
            let mut line = format!(
                "rig {}: {}; {} drive(s) ({}), {} keyframes",
                i + 1,
                r.rig,
                r.drives.len(),
                drive_ranges(&r.drives),
                r.keyframes
            );
            if let Some((lo, hi)) = r.points_per_sweep {
                if lo == hi {
                    let _ = write!(line, ", {lo} points a sweep");
                } else {
                    let _ = write!(line, ", {lo}-{hi} points a sweep");
                }
            }
            lines.push(line);
        }
        lines
    }

    /// Logs [`FleetReport::lines`] at INFO: a fleet of 1 000 drives in a few lines.
    pub fn log(&self) {
        for line in self.lines() {
            tracing::info!("{line}");
        }
        tracing::info!(
            groups = self.groups.len(),
            rigs = self.rigs.len(),
            samples_per_epoch = self.samples_per_epoch,
            "dataset"
        );
    }
}
