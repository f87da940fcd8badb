//! Shared helpers of the end-to-end tests: where the sample drives are, their ground
//! truth, and the transforms and calibrations a drive records.

use anyhow::{Context as _, bail};
use std::collections::BTreeMap;
use std::path::PathBuf;
use superflow_pipeline::decode::{foxglove, ros2};
use superflow_pipeline::drive::TransformTree;
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

/// Every transform of the drive in one tree (`/tf`, `/tf_static`), with constant
/// stamped edges (re-published extrinsics) frozen into static ones.
pub fn transform_tree(drive: &SampleDrive) -> anyhow::Result<TransformTree> {
    let mut tree = TransformTree::new(0);
    for message in mcap::MessageStream::new(&drive.bytes)? {
        let message = message?;
        let topic = message.channel.topic.as_str();
        let schema = message.channel.schema.as_ref().map(|s| s.name.as_str());
        let transforms = match (topic, schema) {
            ("/tf" | "/tf_static", Some(ros2::TF_MESSAGE)) => {
                let msg: ros2::TfMessage = ros2::decode(&message.data)?;
                ros2::transforms(&msg, topic == "/tf_static")
            }
            ("/tf", Some("foxglove.FrameTransform")) => {
                let msg: foxglove::FrameTransform =
                    foxglove::decode("foxglove.FrameTransform", &message.data)?;
                vec![foxglove::frame_transform(&msg, false)]
            }
            _ => continue,
        };
        for transform in transforms {
            tree.insert(transform.with_context(|| {
                format!(
                    "{}: {topic} at log time {}",
                    drive.path.display(),
                    message.log_time
                )
            })?)?;
        }
    }
    tree.freeze_constant_edges();
    Ok(tree)
}

/// The first calibration recorded on each calibration topic, by topic.
pub fn calibrations(drive: &SampleDrive) -> anyhow::Result<BTreeMap<String, CameraCalibration>> {
    let mut out = BTreeMap::new();
    for message in mcap::MessageStream::new(&drive.bytes)? {
        let message = message?;
        let topic = message.channel.topic.clone();
        if out.contains_key(&topic) {
            continue;
        }
        let calibration = match message.channel.schema.as_ref().map(|s| s.name.as_str()) {
            Some(ros2::CAMERA_INFO) => ros2::camera_info(&ros2::decode(&message.data)?)?,
            Some("foxglove.CameraCalibration") => foxglove::camera_calibration(&foxglove::decode(
                "foxglove.CameraCalibration",
                &message.data,
            )?)?,
            _ => continue,
        };
        out.insert(topic, calibration);
    }
    if out.is_empty() {
        bail!("{}: no calibration found", drive.path.display());
    }
    Ok(out)
}
