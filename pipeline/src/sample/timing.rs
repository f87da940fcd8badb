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
//!
//! [`camera_scan`] is that measurement kept in the index cache ([`IndexCache`]) beside
//! the indexes of the drive's files: a start with a warm cache reads a few hundred
//! bytes per drive instead of decompressing a chunk and decoding a sweep.

use super::recipe::{CameraSync, SampleConfig};
use crate::drive::index_cache::EntryKind;
use crate::drive::{Drive, IndexCache, LidarFacts, ReadError};
use crate::source::ChunkCache;
use nalgebra::Vector3;
use serde::{Deserialize, Serialize};

/// Half-width of the azimuth sector around a camera's axis whose points time its scan.
const SECTOR_RAD: f64 = 2.0 * std::f64::consts::PI / 180.0;

/// Fewest points in that sector for a measurement (else the offset is 0: the stamp).
const MIN_POINTS: usize = 8;

/// How the moments a drive's LiDAR scans its cameras were found.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Serialize, Deserialize)]
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
/// and at the end: it has two moments; every other camera one. The sweep measured also
/// says what the LiDAR's sweeps hold (its rig, for `index` and the service's start-up
/// lines), kept with the moments so that a warm start reads no sweep.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct CameraScan {
    /// Offsets from the sweep stamp, per camera one or two.
    pub offsets_nanos: Vec<Vec<i64>>,
    /// How they were found.
    pub timing: ScanTiming,
    /// What the measured sweep held: the LiDAR's facts and its points (`None` when no
    /// sweep was read).
    pub lidar: Option<(LidarFacts, usize)>,
}

impl CameraScan {
    /// Every camera at the sweep stamp.
    fn at_stamp(cameras: usize) -> Self {
        Self {
            offsets_nanos: vec![vec![0]; cameras],
            timing: ScanTiming::Stamp,
            lidar: None,
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

/// The index cache's entries of camera scans: one per drive, keyed by [`scan_key`].
pub const SCAN_ENTRY: EntryKind = EntryKind {
    magic: *b"SFSCAN\0\0",
    // Raised whenever the measurement (or what `ScanEntry` holds) changes.
    version: 2,
    extension: "sfscan",
    what: "camera scan",
};

/// What a camera-scan entry holds: the key again (an entry copied under another name
/// is not another drive's) and the measurement.
#[derive(Debug, Serialize, Deserialize)]
struct ScanEntry {
    key: u128,
    scan: CameraScan,
}

/// What a drive's camera scan is stored under in the index cache: a hash of everything
/// the measurement depends on — the drive's files (their fingerprints), the choices of
/// its `[ingest]` configuration that shape its streams and transforms, the sweep
/// measured, the LiDAR and the cameras it found. `None` when the drive has no
/// fingerprint (index cache off, a file without a summary).
pub fn scan_key(drive: &Drive) -> Option<u128> {
    let fingerprint = drive.fingerprint?;
    let lidar = drive.lidar.as_ref()?;
    let (sweep, frame) = lidar.timing_sweep()?;
    let mut hash = xxhash_rust::xxh3::Xxh3::new();
    hash.update(SCAN_ENTRY.extension.as_bytes());
    hash.update(&fingerprint.to_le_bytes());
    // Where the cache is and how many files stay open change no stream.
    let shaping = crate::drive::IngestConfig {
        max_open_files: None,
        index_cache: None,
        ..drive.config.clone()
    };
    hash.update(&bincode::serde::encode_to_vec(&shaping, bincode::config::standard()).ok()?);
    hash.update(&(sweep as u64).to_le_bytes());
    hash.update(&frame.stamp.nanos().to_le_bytes());
    for name in [&lidar.topic, &lidar.frame_id] {
        hash.update(&(name.len() as u64).to_le_bytes());
        hash.update(name.as_bytes());
    }
    hash.update(&(drive.cameras.len() as u64).to_le_bytes());
    for camera in &drive.cameras {
        for name in [&camera.name, &camera.frame_id] {
            hash.update(&(name.len() as u64).to_le_bytes());
            hash.update(name.as_bytes());
        }
    }
    Some(hash.digest128())
}

/// [`scan_offsets`] through the index cache of `drive`'s configuration: read from the
/// drive's entry when it has a usable one; else measured and stored. An entry that is
/// damaged, of another version or of another drive is ignored (one INFO line) and
/// rewritten; a sweep that cannot be read is never stored. Without a cache (or a
/// fingerprint) it is [`scan_offsets`].
pub fn camera_scan(drive: &Drive, config: &SampleConfig) -> CameraScan {
    camera_scan_from(drive, config).0
}

/// Where a camera scan came from.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum ScanFrom {
    /// Read from the index cache.
    Cache,
    /// Measured from a sweep (and stored in the cache, if there is one).
    Measured,
    /// Not measured: every camera at the sweep stamp (`camera_sync = "stamp"`, no
    /// sweep, or a sweep that does not read).
    Stamp,
}

/// [`camera_scan`], and where it came from.
pub fn camera_scan_from(drive: &Drive, config: &SampleConfig) -> (CameraScan, ScanFrom) {
    let cameras = drive.cameras.len();
    if config.camera_sync == CameraSync::Stamp {
        return (CameraScan::at_stamp(cameras), ScanFrom::Stamp);
    }
    let cache = drive.config.index_cache().zip(scan_key(drive));
    if let Some((cache, key)) = &cache
        && let Some(scan) = load(cache, *key, drive)
    {
        return (scan, ScanFrom::Cache);
    }
    match measure(drive) {
        Ok(scan) if scan.timing == ScanTiming::Stamp => (scan, ScanFrom::Stamp),
        Ok(scan) => {
            if let Some((cache, key)) = &cache {
                let entry = ScanEntry {
                    key: *key,
                    scan: scan.clone(),
                };
                cache.store_entry(&SCAN_ENTRY, *key, &entry);
            }
            (scan, ScanFrom::Measured)
        }
        Err(e) => (unmeasured(cameras, &e), ScanFrom::Stamp),
    }
}

/// The camera scan stored under `key`, if its entry is usable for `drive`.
fn load(cache: &IndexCache, key: u128, drive: &Drive) -> Option<CameraScan> {
    let ignored = |why: &dyn std::fmt::Display| {
        tracing::info!(drive = %drive.file_list(), entry = %cache.path_of(&SCAN_ENTRY, key).display(), "camera scan cache entry ignored: {why}; measuring again");
    };
    match cache.load_entry::<ScanEntry>(&SCAN_ENTRY, key) {
        Ok(None) => None,
        Ok(Some(entry)) if entry.key != key => {
            ignored(&"it is another drive's");
            None
        }
        Ok(Some(entry))
            if entry.scan.offsets_nanos.len() != drive.cameras.len()
                || entry
                    .scan
                    .offsets_nanos
                    .iter()
                    .any(|m| !(1..=2).contains(&m.len())) =>
        {
            ignored(&"it does not fit the drive's cameras");
            None
        }
        Ok(Some(entry)) => Some(entry.scan),
        Err(e) => {
            ignored(&e);
            None
        }
    }
}

/// Every camera at the sweep stamp, saying why.
fn unmeasured(cameras: usize, e: &ReadError) -> CameraScan {
    tracing::warn!("camera timing: cameras matched at the sweep stamp ({e})");
    CameraScan::at_stamp(cameras)
}

/// The scan moments of `drive`'s cameras (see the module documentation), measured from
/// its data; every camera at the stamp when `config` says so or nothing can be
/// measured.
pub fn scan_offsets(drive: &Drive, config: &SampleConfig) -> CameraScan {
    if config.camera_sync == CameraSync::Stamp {
        return CameraScan::at_stamp(drive.cameras.len());
    }
    measure(drive).unwrap_or_else(|e| unmeasured(drive.cameras.len(), &e))
}

/// The scan moments measured from the drive's middle sweep; every camera at the stamp
/// without a sweep; the error when the sweep does not read.
fn measure(drive: &Drive) -> Result<CameraScan, ReadError> {
    let cameras = drive.cameras.len();
    let Some(lidar) = drive.lidar.as_ref().filter(|l| !l.sweeps.is_empty()) else {
        return Ok(CameraScan::at_stamp(cameras));
    };
    let Some((_, frame)) = lidar.timing_sweep() else {
        return Ok(CameraScan::at_stamp(cameras));
    };
    let mut cache = ChunkCache::new(2);
    let decoded = drive.read_sweep(frame, &mut cache)?;
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
    Ok(CameraScan {
        offsets_nanos,
        timing,
        lidar: Some((LidarFacts::of(&decoded), decoded.cloud.len())),
    })
}
