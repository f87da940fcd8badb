//! Shared helpers of the end-to-end tests: where the sample drives are, their ground
//! truth, the transforms and calibrations a drive records, the binaries and how the tests
//! start them ([`process`]), their temporary directories ([`scratch`]), and ([`bench`])
//! the measurement code of the benchmarks.

pub mod bench;
pub mod process;
pub mod s3;
pub mod scratch;

use anyhow::{Context as _, bail};
use std::collections::BTreeMap;
use std::path::PathBuf;
use superflow_pipeline::drive::{Drive, IngestConfig, TransformTree};
use superflow_recordings::truth::GroundTruth;
use superflow_recordings::{Dialect, DriveOptions};
use superflow_schemas::sensor::CameraCalibration;

/// The repository root.
pub fn workspace_root() -> PathBuf {
    PathBuf::from(env!("CARGO_MANIFEST_DIR"))
        .parent()
        .map(PathBuf::from)
        .unwrap_or_default()
}

/// A committed sample drive and its ground truth.
#[derive(Debug)]
pub struct SampleDrive {
    /// Which dialect it is written in.
    pub dialect: Dialect,
    /// Path of the MCAP file.
    pub path: PathBuf,
    /// The MCAP bytes.
    pub bytes: Vec<u8>,
    /// The JSON ground truth, raw.
    pub truth_json: Vec<u8>,
    /// The ground truth, parsed.
    pub truth: GroundTruth,
}

/// The ROS 2 sample drive as the tests give it to the binaries: relative to the workspace
/// root, where they run ([`superflow_recordings::sample_drive_path`] of `street_ros2`, as
/// a user types it).
pub const SAMPLE_DRIVE: &str = "recordings/drives/street_ros2.mcap";

/// Loads `recordings/drives/<drive>.mcap` and its `.truth.json`.
pub fn sample_drive(dialect: Dialect) -> anyhow::Result<SampleDrive> {
    let name = dialect.drive_name();
    let path = superflow_recordings::sample_drive_path(&name);
    let truth_path = superflow_recordings::sample_drives_dir().join(format!("{name}.truth.json"));
    let bytes = std::fs::read(&path).with_context(|| format!("reading {}", path.display()))?;
    let truth_json =
        std::fs::read(&truth_path).with_context(|| format!("reading {}", truth_path.display()))?;
    let truth = serde_json::from_slice(&truth_json)
        .with_context(|| format!("parsing {}", truth_path.display()))?;
    Ok(SampleDrive {
        dialect,
        path,
        bytes,
        truth_json,
        truth,
    })
}

/// The drive indexed by the pipeline's ingest (one pass over the file).
pub fn dataset(drive: &SampleDrive) -> anyhow::Result<Drive> {
    Ok(Drive::open(
        std::slice::from_ref(&drive.path),
        &IngestConfig::default(),
    )?)
}

/// Every transform of the drive in one tree (`/tf`, `/tf_static`), with constant
/// stamped edges (re-published extrinsics) frozen into static ones.
pub fn transform_tree(drive: &SampleDrive) -> anyhow::Result<TransformTree> {
    Ok(dataset(drive)?.tf)
}

/// The calibration of each camera, by calibration topic.
pub fn calibrations(drive: &SampleDrive) -> anyhow::Result<BTreeMap<String, CameraCalibration>> {
    let dataset = dataset(drive)?;
    let mut out = BTreeMap::new();
    for camera in &dataset.cameras {
        let topic = camera.calibration_topic.clone().with_context(|| {
            format!(
                "{}: camera {} has no calibration",
                drive.path.display(),
                camera.name
            )
        })?;
        let calibration = camera
            .calibrations
            .first()
            .with_context(|| format!("{topic}: empty"))?;
        out.insert(topic, calibration.clone());
    }
    if out.is_empty() {
        bail!("{}: no calibration found", drive.path.display());
    }
    Ok(out)
}

/// The drive as a one-drive dataset, the input of the sample builder.
pub fn sample_dataset(drive: &SampleDrive) -> anyhow::Result<superflow_pipeline::drive::Dataset> {
    Ok(superflow_pipeline::drive::Dataset::open(
        std::slice::from_ref(&drive.path),
        &IngestConfig::default(),
    )?)
}

/// A drive of another rig in `dialect` ([`DriveOptions::rig`]), generated on first use
/// into the system's temporary directory, one directory per drive and generator version
/// (made whole under a temporary name, then renamed, so test processes running at once
/// share it); returns the drive's path. The generator writes it in a second or two.
pub fn rig_drive(dialect: Dialect, options: &DriveOptions) -> anyhow::Result<PathBuf> {
    let name = options.drive_name(dialect);
    let root = std::env::temp_dir().join(format!(
        "superflow-rigs-v{}",
        superflow_recordings::GENERATOR_VERSION
    ));
    let dir = root.join(&name);
    let path = dir.join(format!("{name}.mcap"));
    if path.is_file() {
        return Ok(path);
    }
    let drive = superflow_recordings::generate_with(dialect, options)?;
    // Tests of one process may write the same rig at once: the copy's name is this call's.
    static WRITES: std::sync::atomic::AtomicU64 = std::sync::atomic::AtomicU64::new(0);
    let call = WRITES.fetch_add(1, std::sync::atomic::Ordering::Relaxed);
    let tmp = root.join(format!(".{name}.{}-{call}.tmp", std::process::id()));
    let _ = std::fs::remove_dir_all(&tmp);
    std::fs::create_dir_all(&tmp).with_context(|| format!("creating {}", tmp.display()))?;
    std::fs::write(tmp.join(format!("{name}.mcap")), &drive.mcap)?;
    if let (Some(bytes), Some(sidecar)) = (&drive.sidecar, options.sidecar_name(dialect)) {
        std::fs::write(tmp.join(sidecar), bytes)?;
    }
    if let (Some(bytes), Some(sidecar)) =
        (&drive.labels_sidecar, options.labels_sidecar_name(dialect))
    {
        std::fs::write(tmp.join(sidecar), bytes)?;
    }
    std::fs::write(tmp.join(format!("{name}.truth.json")), drive.truth_json()?)?;
    // Another process may have renamed its copy into place first: then keep that one.
    if std::fs::rename(&tmp, &dir).is_err() {
        let _ = std::fs::remove_dir_all(&tmp);
    }
    anyhow::ensure!(path.is_file(), "{} was not written", path.display());
    Ok(path)
}

/// The 2-camera rig of the fleet tests: a ROS 2 car with the front and front-right
/// cameras at 640×360 and a 32-beam LiDAR.
pub fn two_camera_rig() -> DriveOptions {
    DriveOptions::rig(2, (640, 360), 32)
}

/// The 1-camera rig of the fleet tests: a Foxglove car with a front camera only.
pub fn one_camera_rig() -> DriveOptions {
    DriveOptions::rig(1, superflow_recordings::IMAGE_SIZE, 16)
}

/// A fleet of three rigs: the committed 6-camera Foxglove drive, then the 2-camera
/// ROS 2 and the 1-camera Foxglove drives ([`rig_drive`]).
pub fn fleet_drives() -> anyhow::Result<Vec<PathBuf>> {
    Ok(vec![
        sample_drive(Dialect::Foxglove)?.path,
        rig_drive(Dialect::Ros2, &two_camera_rig())?,
        rig_drive(Dialect::Foxglove, &one_camera_rig())?,
    ])
}

/// The `superflow-pipeline` binary next to this package's binaries (built by
/// `cargo test --workspace`; built here if a narrower command skipped it).
pub fn pipeline_binary(sibling: &str) -> PathBuf {
    workspace_binary(sibling, "superflow-pipeline")
}

/// The `superflow-trainer` binary next to this package's binaries, built if missing.
pub fn trainer_binary(sibling: &str) -> PathBuf {
    workspace_binary(sibling, "superflow-trainer")
}

/// The binary `name` (package of the same name) next to `sibling`, built if missing.
pub fn workspace_binary(sibling: &str, name: &str) -> PathBuf {
    let dir = PathBuf::from(sibling)
        .parent()
        .map(PathBuf::from)
        .unwrap_or_default();
    let path = dir.join(name);
    if !path.exists() {
        let cargo = std::env::var("CARGO").unwrap_or_else(|_| "cargo".into());
        let status = std::process::Command::new(cargo)
            .args(["build", "-p", name, "--bin", name])
            .current_dir(workspace_root())
            .status();
        assert!(
            status.is_ok_and(|s| s.success()),
            "building {name} for the end-to-end tests failed"
        );
    }
    path
}

/// Both sample drives copied into `dir`, beside a pipeline configuration that reopens a
/// file at every read (`max_open_files = 1`) and keeps no index cache: the drives and
/// the configuration file. [`truncate_drives`] then breaks them under a running service.
pub fn replaceable_drives(dir: &std::path::Path) -> anyhow::Result<(Vec<PathBuf>, PathBuf)> {
    std::fs::create_dir_all(dir)?;
    let mut drives = Vec::new();
    for name in ["street_ros2", "street_foxglove"] {
        let to = dir.join(format!("{name}.mcap"));
        std::fs::copy(superflow_recordings::sample_drive_path(name), &to)
            .with_context(|| format!("copying {name}.mcap"))?;
        drives.push(to);
    }
    let config = dir.join("pipeline.toml");
    std::fs::write(
        &config,
        "[ingest]\nmax_open_files = 1\nindex_cache = \"off\"\n",
    )?;
    Ok((drives, config))
}

/// Replaces each drive by an identical copy, written aside and renamed over it (a new
/// inode and new times, as `rsync` or a dataset re-sync writes files whose content did
/// not change).
pub fn resync_drives(drives: &[PathBuf]) -> anyhow::Result<()> {
    for drive in drives {
        let fresh = drive.with_extension("resync");
        std::fs::copy(drive, &fresh)?;
        std::fs::rename(&fresh, drive)?;
    }
    Ok(())
}

/// Replaces each drive by a copy of its first half, written aside and renamed over it (a
/// new inode, as a dataset re-sync writes files): samples read from them from then on
/// fail, unless the pipeline still holds their data.
pub fn truncate_drives(drives: &[PathBuf]) -> anyhow::Result<()> {
    for drive in drives {
        let bytes = std::fs::read(drive)?;
        let fresh = drive.with_extension("new");
        std::fs::write(&fresh, &bytes[..bytes.len() / 2])?;
        std::fs::rename(&fresh, drive)?;
    }
    Ok(())
}

#[cfg(test)]
mod tests {
    #[test]
    fn the_sample_drive_argument_names_the_committed_ros2_drive() {
        assert_eq!(
            super::workspace_root().join(super::SAMPLE_DRIVE),
            superflow_recordings::sample_drive_path("street_ros2")
        );
    }
}
