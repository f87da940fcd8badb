//! Shared helpers of the end-to-end tests: where the sample drives are, their ground
//! truth, the transforms and calibrations a drive records, and ([`bench`]) the
//! measurement code of the benchmarks.

pub mod bench;
pub mod process;

use anyhow::{Context as _, bail};
use std::collections::BTreeMap;
use std::path::PathBuf;
use superflow_pipeline::drive::{Drive, IngestConfig, TransformTree};
use superflow_recordings::Dialect;
use superflow_recordings::truth::GroundTruth;
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

/// Loads `recordings/drives/<drive>.mcap` and its `.truth.json`.
pub fn sample_drive(dialect: Dialect) -> anyhow::Result<SampleDrive> {
    let dir = workspace_root().join("recordings/drives");
    let path = dir.join(format!("{}.mcap", dialect.drive_name()));
    let truth_path = dir.join(format!("{}.truth.json", dialect.drive_name()));
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

/// The `superflow-pipeline` binary next to this package's binaries (built by
/// `cargo test --workspace`; built here if a narrower command skipped it).
pub fn pipeline_binary(sibling: &str) -> PathBuf {
    workspace_binary(sibling, "superflow-pipeline")
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
