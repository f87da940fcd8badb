//! The report's model: what `inspect --json` serializes (`superflow.inspect/1`).

use crate::drive::{ChannelSummary, LabelForm, SkipReport};
use crate::fleet::FleetReport;
use serde::{Deserialize, Serialize};
use std::collections::BTreeMap;

/// One file of the dataset.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct FileReport {
    /// Path as given.
    pub path: String,
    /// Size in bytes.
    pub bytes: u64,
    /// MCAP header profile.
    pub profile: String,
    /// MCAP header library.
    pub library: String,
    /// Damage the reader worked around, in words (empty for a healthy file).
    pub damage: Vec<String>,
}

/// One camera.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct CameraReport {
    /// Camera name.
    pub name: String,
    /// Image topic.
    pub image_topic: String,
    /// Calibration topic, if found.
    pub calibration_topic: Option<String>,
    /// Class-map topic, if recorded.
    pub superpixel_topic: Option<String>,
    /// Topic of the SLIC superpixels precomputed by `superflow-pipeline superpixels`.
    #[serde(default)]
    pub slic_topic: Option<String>,
    /// Optical frame.
    pub frame_id: String,
    /// Images.
    pub images: usize,
    /// Width from the calibration.
    pub width: Option<u32>,
    /// Height from the calibration.
    pub height: Option<u32>,
    /// Distortion model (`none`, `plumb_bob`, ...), if calibrated.
    pub distortion_model: Option<String>,
    /// Distinct calibrations recorded.
    pub calibrations: usize,
    /// Image rate.
    pub rate_hz: Option<f64>,
}

/// One edge of the frame tree.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct FrameEdge {
    /// Parent frame.
    pub parent: String,
    /// Child frame.
    pub child: String,
    /// `static` (from `/tf_static` or frozen) or `dynamic`.
    pub kind: String,
    /// Stamped samples.
    pub samples: usize,
}

/// The whole report: one entry per drive.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct InspectReport {
    /// [`INSPECT_FORMAT`].
    pub format: String,
    /// Every drive of the dataset.
    pub drives: Vec<DriveReport>,
    /// The dataset's groups and rigs (with their LiDARs' facts), when asked for
    /// ([`InspectReport::with_fleet`]).
    #[serde(default)]
    pub fleet: Option<FleetReport>,
}

/// What one drive holds.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct DriveReport {
    /// The files.
    pub files: Vec<FileReport>,
    /// `foxglove_protobuf`, `ros2` or `mixed`.
    pub dialect: String,
    /// Every channel with its role.
    pub channels: Vec<ChannelSummary>,
    /// LiDAR topic.
    pub lidar_topic: Option<String>,
    /// LiDAR frame.
    pub lidar_frame: Option<String>,
    /// LiDAR sweeps.
    pub lidar_sweeps: usize,
    /// Cameras.
    pub cameras: Vec<CameraReport>,
    /// Map frame.
    pub map_frame: Option<String>,
    /// Ego frame.
    pub ego_frame: Option<String>,
    /// The frame tree.
    pub frame_tree: Vec<FrameEdge>,
    /// First LiDAR stamp, ns.
    pub start_stamp_nanos: Option<i64>,
    /// Last LiDAR stamp, ns.
    pub end_stamp_nanos: Option<i64>,
    /// Duration, s.
    pub duration_secs: Option<f64>,
    /// Keyframes usable at the default 0.5 s interval.
    pub usable_keyframes: usize,
    /// How camera images meet sweeps under the default recipe (`camera_sync = "scan"`,
    /// `keyframe_choice = "least_camera_offset"`).
    #[serde(default)]
    pub camera_timing: CameraTimingReport,
    /// Skipped messages by kind.
    pub skipped: SkipReport,
    /// Why the dataset cannot be trained on, if it cannot.
    pub problems: Option<String>,
    /// Per-point labels, when the drive has them and the report was asked to read them
    /// (`inspect` does; see [`InspectReport::with_labels`]).
    #[serde(default)]
    pub labels: Option<LabelsReport>,
}

/// A drive's per-point labels: where they are and what they hold.
#[derive(Debug, Clone, Default, PartialEq, Serialize, Deserialize)]
pub struct LabelsReport {
    /// Where they are; `None` when they could not be located (see `first_error`).
    pub form: Option<LabelForm>,
    /// LiDAR sweeps.
    pub sweeps: usize,
    /// Sweeps whose labels read.
    pub sweeps_labelled: usize,
    /// Points of those sweeps per raw id (after `label_mask`).
    pub raw_ids: BTreeMap<u32, u64>,
    /// Points of those sweeps per training class, with its name when `[labels] classes`
    /// names it (`ignore` for `ignore_index`).
    pub classes: Vec<ClassCount>,
    /// Sweeps whose labels did not read.
    pub errors: usize,
    /// The first of those errors (or why the labels could not be located).
    pub first_error: Option<String>,
}

/// Points of one training class.
#[derive(Debug, Clone, PartialEq, Eq, Serialize, Deserialize)]
pub struct ClassCount {
    /// The class id.
    pub id: u8,
    /// Its name from `[labels] classes`, `ignore`, or empty.
    pub name: String,
    /// Points.
    pub points: u64,
}

/// When the LiDAR scans each camera, and how far the keyframes' images are from those
/// moments (see `sample::timing`).
#[derive(Debug, Clone, Default, PartialEq, Serialize, Deserialize)]
pub struct CameraTimingReport {
    /// Per camera, the scan moments relative to the sweep stamp, ms.
    pub scan_ms: Vec<(String, Vec<f64>)>,
    /// How they were found: `point_time`, `point_order` or `stamp`.
    pub timing: String,
    /// Keyframes of the default recipe's plan.
    pub keyframes: usize,
    /// Median and largest worst-camera offset of those keyframes, ms.
    pub worst_offset_ms: Option<[f64; 2]>,
}
