//! The rigs of a dataset. A fleet mixes cars of several sensor sets — a 6-camera car and
//! a 2-camera one, a 32-beam LiDAR and a 64-beam one — and one run trains on all of them:
//! a sample takes `min(cameras, the rig's cameras)` cameras and the batch carries each
//! sample's own (`schemas/BATCH_FORMAT.md`). [`Rig`] is what tells two drives' sensor
//! sets apart (cameras with their image sizes, the LiDAR and what its sweeps hold);
//! [`rigs`] groups a dataset's drives by it, for `inspect`, `index` and the service's
//! start-up lines.

use super::index::Drive;
use super::read::ReadError;
use crate::decode::points::DecodedCloud;
use crate::source::ChunkCache;
use serde::{Deserialize, Serialize};
use std::fmt;

/// One camera of a rig.
#[derive(Debug, Clone, PartialEq, Eq, PartialOrd, Ord, Hash, Serialize, Deserialize)]
pub struct RigCamera {
    /// Its name (`CAM_FRONT`).
    pub name: String,
    /// Image width of its first calibration (0 when it has none).
    pub width: u32,
    /// Image height of its first calibration.
    pub height: u32,
}

/// What a LiDAR's sweeps hold, read from one sweep.
#[derive(Debug, Clone, Copy, PartialEq, Eq, PartialOrd, Ord, Hash, Serialize, Deserialize)]
pub struct LidarFacts {
    /// Beams: distinct ring values of the sweep (`None` without a ring field).
    pub beams: Option<u16>,
    /// Whether points carry their own time (raw sweeps, de-skewed by the pipeline).
    pub per_point_time: bool,
    /// Whether points carry an intensity (else it is 0).
    pub intensity: bool,
}

impl LidarFacts {
    /// The facts of a decoded sweep.
    pub fn of(decoded: &DecodedCloud) -> Self {
        let beams = decoded.cloud.ring.as_ref().map(|rings| {
            let mut seen = vec![false; usize::from(u16::MAX) + 1];
            rings
                .iter()
                .filter(|&&r| !std::mem::replace(&mut seen[usize::from(r)], true))
                .count() as u16
        });
        Self {
            beams,
            per_point_time: decoded.time_field.is_some(),
            intensity: decoded.has_intensity,
        }
    }

    /// The facts of `drive`'s LiDAR from its middle sweep, and that sweep's points;
    /// `None` without a LiDAR sweep.
    pub fn read(drive: &Drive) -> Result<Option<(Self, usize)>, ReadError> {
        let Some(lidar) = drive.lidar.as_ref().filter(|l| !l.sweeps.is_empty()) else {
            return Ok(None);
        };
        let sweep = &lidar.sweeps[lidar.sweeps.len() / 2];
        let decoded = drive.read_sweep(sweep, &mut ChunkCache::new(2))?;
        Ok(Some((Self::of(&decoded), decoded.cloud.len())))
    }
}

/// A drive's sensor set: what tells the rigs of a fleet apart.
#[derive(Debug, Clone, PartialEq, Eq, PartialOrd, Ord, Hash, Serialize, Deserialize)]
pub struct Rig {
    /// The cameras, in the drive's order.
    pub cameras: Vec<RigCamera>,
    /// The LiDAR's topic (`None`: no LiDAR).
    pub lidar_topic: Option<String>,
    /// What its sweeps hold, when a sweep was read.
    pub lidar: Option<LidarFacts>,
}

impl Rig {
    /// The rig of `drive`, with its LiDAR's `facts` when they were read.
    pub fn of(drive: &Drive, facts: Option<LidarFacts>) -> Self {
        Self {
            cameras: drive
                .cameras
                .iter()
                .map(|c| {
                    let calibration = c.calibrations.first();
                    RigCamera {
                        name: c.name.clone(),
                        width: calibration.map_or(0, |k| k.width),
                        height: calibration.map_or(0, |k| k.height),
                    }
                })
                .collect(),
            lidar_topic: drive.lidar.as_ref().map(|l| l.topic.clone()),
            lidar: facts,
        }
    }
}

impl fmt::Display for Rig {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        let cameras: Vec<String> = self
            .cameras
            .iter()
            .map(|c| format!("{} {}×{}", c.name, c.width, c.height))
            .collect();
        write!(f, "{} camera(s)", self.cameras.len())?;
        if !cameras.is_empty() {
            write!(f, " ({})", cameras.join(", "))?;
        }
        match (&self.lidar_topic, &self.lidar) {
            (None, _) => write!(f, "; no LiDAR"),
            (Some(topic), None) => write!(f, "; LiDAR {topic}"),
            (Some(topic), Some(l)) => {
                write!(f, "; LiDAR {topic}")?;
                if let Some(beams) = l.beams {
                    write!(f, ", {beams} beams")?;
                }
                let mut fields = vec!["x y z"];
                if l.intensity {
                    fields.push("intensity");
                }
                if l.per_point_time {
                    fields.push("per-point time");
                }
                write!(f, ", {}", fields.join(", "))
            }
        }
    }
}

/// One rig of a dataset and the drives that share it.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct RigShare {
    /// The rig.
    pub rig: Rig,
    /// Its drives (dataset order).
    pub drives: Vec<usize>,
}

/// The rigs of `drives` (with each drive's LiDAR facts when read), in the order they
/// first appear.
pub fn rigs(drives: &[Drive], facts: &[Option<LidarFacts>]) -> Vec<RigShare> {
    let mut out: Vec<RigShare> = Vec::new();
    for (d, drive) in drives.iter().enumerate() {
        let rig = Rig::of(drive, facts.get(d).copied().flatten());
        match out.iter_mut().find(|r| r.rig == rig) {
            Some(share) => share.drives.push(d),
            None => out.push(RigShare {
                rig,
                drives: vec![d],
            }),
        }
    }
    out
}

/// `1-3, 5, 7-8` for drive numbers (1-based, as people count them).
pub fn drive_ranges(drives: &[usize]) -> String {
    let mut parts: Vec<String> = Vec::new();
    let mut i = 0;
    while i < drives.len() {
        let start = drives[i];
        let mut end = start;
        while i + 1 < drives.len() && drives[i + 1] == end + 1 {
            i += 1;
            end = drives[i];
        }
        parts.push(if start == end {
            format!("{}", start + 1)
        } else {
            format!("{}-{}", start + 1, end + 1)
        });
        i += 1;
    }
    parts.join(", ")
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn drive_numbers_read_as_ranges() {
        assert_eq!(drive_ranges(&[0, 1, 2, 4, 6, 7]), "1-3, 5, 7-8");
        assert_eq!(drive_ranges(&[3]), "4");
        assert_eq!(drive_ranges(&[]), "");
    }

    #[test]
    fn a_rig_says_what_its_sensors_are() {
        let rig = Rig {
            cameras: vec![
                RigCamera {
                    name: "CAM_FRONT".into(),
                    width: 1600,
                    height: 900,
                },
                RigCamera {
                    name: "CAM_BACK".into(),
                    width: 1600,
                    height: 900,
                },
            ],
            lidar_topic: Some("/LIDAR_TOP".into()),
            lidar: Some(LidarFacts {
                beams: Some(32),
                per_point_time: false,
                intensity: true,
            }),
        };
        assert_eq!(
            rig.to_string(),
            "2 camera(s) (CAM_FRONT 1600×900, CAM_BACK 1600×900); LiDAR /LIDAR_TOP, 32 beams, x y z, intensity"
        );
    }
}
