//! `superflow-pipeline inspect`: what a dataset holds, as text or as stable JSON.
//!
//! The JSON form ([`InspectReport`], `"format": "superflow.inspect/1"`) is a contract:
//! fields are only ever added, and a change of meaning bumps the format string.

use crate::drive::ChannelSummary;
use crate::drive::SkipReport;
use crate::drive::{Dataset, Drive, DriveLabels, LabelConfig, LabelForm, Role};
use crate::fleet::{FleetReport, read_lidar_facts};
use crate::sample::SampleConfig;
use crate::sample::plan::drive_keyframes;
use crate::source::ChunkCache;
use rayon::prelude::*;
use serde::{Deserialize, Serialize};
use std::collections::BTreeMap;
use std::fmt::Write as _;

/// The format identifier of the JSON report.
pub const INSPECT_FORMAT: &str = "superflow.inspect/1";

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

impl InspectReport {
    /// Builds the report of an indexed dataset (without [`DriveReport::labels`]: that
    /// reads every sweep, see [`InspectReport::with_labels`]).
    pub fn new(dataset: &Dataset) -> Self {
        InspectReport {
            format: INSPECT_FORMAT.to_string(),
            drives: dataset.drives.iter().map(DriveReport::new).collect(),
            fleet: None,
        }
    }

    /// This report with the dataset's groups and rigs ([`FleetReport`]), one sweep of
    /// every drive read for its LiDAR's facts; keyframes at the default recipe.
    pub fn with_fleet(mut self, dataset: &Dataset) -> Self {
        let keyframes: Vec<usize> = self.drives.iter().map(|d| d.usable_keyframes).collect();
        self.fleet = Some(FleetReport::new(
            dataset,
            &keyframes,
            &read_lidar_facts(dataset),
        ));
        self
    }

    /// [`InspectReport::new`] with each drive's labels read under `config` (every sweep
    /// of a labelled drive is decoded).
    pub fn with_labels(dataset: &Dataset, config: &LabelConfig) -> Self {
        let mut report = Self::new(dataset);
        for (drive, out) in dataset.drives.iter().zip(&mut report.drives) {
            out.labels = LabelsReport::of(drive, config);
        }
        report
    }

    /// The report for people: the dataset's groups and rigs, then every drive.
    pub fn to_text(&self) -> String {
        let mut parts = Vec::new();
        if let Some(fleet) = &self.fleet {
            parts.push(format!(
                "== dataset: {} drive(s), {} group(s), {} rig(s), {} samples an epoch\n{}\n",
                self.drives.len(),
                fleet.groups.len(),
                fleet.rigs.len(),
                fleet.samples_per_epoch,
                fleet.lines().join("\n")
            ));
        }
        parts.extend(self.drives.iter().enumerate().map(|(i, d)| {
            format!(
                "== drive {} of {}\n{}",
                i + 1,
                self.drives.len(),
                d.to_text()
            )
        }));
        parts.join("\n")
    }
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

impl LabelsReport {
    /// The labels of `drive` under `config`, every sweep read; `None` when the drive has
    /// no labels.
    pub fn of(drive: &Drive, config: &LabelConfig) -> Option<Self> {
        let labels = match DriveLabels::open(drive, config) {
            Ok(labels) => labels?,
            Err(e) => {
                return Some(LabelsReport {
                    sweeps: drive.lidar.as_ref().map_or(0, |l| l.sweeps.len()),
                    first_error: Some(e.to_string()),
                    ..LabelsReport::default()
                });
            }
        };
        #[derive(Default)]
        struct Tally {
            raw: BTreeMap<u32, u64>,
            classes: BTreeMap<u8, u64>,
            labelled: usize,
            errors: Vec<(usize, String)>,
        }
        let tally = (0..labels.sweeps())
            .into_par_iter()
            .fold(
                || (Tally::default(), ChunkCache::new(2)),
                |(mut tally, mut cache), sweep| {
                    match labels.read(sweep, &mut cache) {
                        Ok(read) => {
                            tally.labelled += 1;
                            let raw = read.decoded.cloud.label.unwrap_or_default();
                            for id in raw {
                                *tally.raw.entry(id).or_default() += 1;
                            }
                            for class in read.labels {
                                *tally.classes.entry(class).or_default() += 1;
                            }
                        }
                        Err(e) => tally.errors.push((sweep, e.to_string())),
                    }
                    (tally, cache)
                },
            )
            .map(|(tally, _)| tally)
            .reduce(Tally::default, |mut a, b| {
                for (id, n) in b.raw {
                    *a.raw.entry(id).or_default() += n;
                }
                for (class, n) in b.classes {
                    *a.classes.entry(class).or_default() += n;
                }
                a.labelled += b.labelled;
                a.errors.extend(b.errors);
                a
            });
        let ignore = labels.map().ignore_index();
        Some(LabelsReport {
            form: Some(labels.form().clone()),
            sweeps: labels.sweeps(),
            sweeps_labelled: tally.labelled,
            raw_ids: tally.raw,
            classes: tally
                .classes
                .into_iter()
                .map(|(id, points)| ClassCount {
                    id,
                    name: config
                        .classes
                        .get(usize::from(id))
                        .cloned()
                        .or_else(|| (id == ignore).then(|| "ignore".to_string()))
                        .unwrap_or_default(),
                    points,
                })
                .collect(),
            errors: tally.errors.len(),
            first_error: tally.errors.into_iter().min().map(|(_, e)| e),
        })
    }

    /// The report for people: a few lines.
    fn to_text(&self) -> String {
        let mut out = String::new();
        match &self.form {
            Some(form) => {
                let _ = writeln!(
                    out,
                    "\nlabels: {form}; {} of {} sweeps labelled",
                    self.sweeps_labelled, self.sweeps
                );
            }
            None => {
                let _ = writeln!(out, "\nlabels: not readable");
            }
        }
        if !self.raw_ids.is_empty() {
            let ids: Vec<String> = self
                .raw_ids
                .iter()
                .map(|(id, n)| format!("{id}: {n}"))
                .collect();
            let _ = writeln!(out, "  raw ids (points): {}", ids.join(", "));
        }
        if !self.classes.is_empty() {
            let classes: Vec<String> = self
                .classes
                .iter()
                .map(|c| match c.name.as_str() {
                    "" => format!("{}: {}", c.id, c.points),
                    name => format!("{} {name}: {}", c.id, c.points),
                })
                .collect();
            let _ = writeln!(out, "  training classes (points): {}", classes.join(", "));
        }
        if let Some(e) = &self.first_error {
            let _ = writeln!(out, "  {} sweeps failed; first: {e}", self.errors);
        }
        out
    }
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

impl CameraTimingReport {
    /// The report of `drive` under the default recipe.
    fn of(drive: &Drive) -> Self {
        let (scan, keys) = drive_keyframes(drive, &SampleConfig::default());
        let mut worst: Vec<f64> = keys.iter().map(|(_, w)| *w as f64 * 1e-6).collect();
        worst.sort_by(f64::total_cmp);
        let scan_ms = drive
            .cameras
            .iter()
            .zip(&scan.offsets_nanos)
            .map(|(c, m)| (c.name.clone(), m.iter().map(|n| *n as f64 * 1e-6).collect()))
            .collect();
        let timing = serde_json::to_value(scan.timing)
            .ok()
            .and_then(|v| v.as_str().map(str::to_owned))
            .unwrap_or_default();
        Self {
            scan_ms,
            timing,
            keyframes: keys.len(),
            worst_offset_ms: (!worst.is_empty())
                .then(|| [worst[worst.len() / 2], worst[worst.len() - 1]]),
        }
    }
}

impl DriveReport {
    /// Builds the report of an indexed drive.
    pub fn new(dataset: &Drive) -> Self {
        let dialects: std::collections::BTreeSet<String> = dataset
            .channels
            .iter()
            .filter(|c| !matches!(c.role, Role::Ignored(_)))
            .map(|c| {
                if c.message_encoding == "cdr" {
                    "ros2".to_string()
                } else {
                    "foxglove_protobuf".to_string()
                }
            })
            .collect();
        let dialect = match dialects.len() {
            0 => "unknown".to_string(),
            1 => dialects.into_iter().next().unwrap_or_default(),
            _ => "mixed".to_string(),
        };
        let span = dataset.time_span();
        let frozen = &dataset.frozen_edges;
        DriveReport {
            files: dataset
                .files
                .iter()
                .map(|f| FileReport {
                    path: f.path().display().to_string(),
                    bytes: f.len(),
                    profile: f.profile.clone(),
                    library: f.library.clone(),
                    damage: f.damage.iter().map(|d| d.to_string()).collect(),
                })
                .collect(),
            dialect,
            channels: dataset.channels.clone(),
            lidar_topic: dataset.lidar.as_ref().map(|l| l.topic.clone()),
            lidar_frame: dataset.lidar.as_ref().map(|l| l.frame_id.clone()),
            lidar_sweeps: dataset.lidar.as_ref().map_or(0, |l| l.sweeps.len()),
            cameras: dataset
                .cameras
                .iter()
                .map(|c| {
                    let calibration = c.calibrations.first();
                    CameraReport {
                        name: c.name.clone(),
                        image_topic: c.image_topic.clone(),
                        calibration_topic: c.calibration_topic.clone(),
                        superpixel_topic: c.superpixel_topic.clone(),
                        slic_topic: c.slic.as_ref().map(|s| s.topic.clone()),
                        frame_id: c.frame_id.clone(),
                        images: c.frames.len(),
                        width: calibration.map(|k| k.width),
                        height: calibration.map(|k| k.height),
                        distortion_model: calibration.map(|k| match k.distortion.model_name() {
                            "" => "none".to_string(),
                            name => name.to_string(),
                        }),
                        calibrations: c.calibrations.len(),
                        rate_hz: c.period_nanos().filter(|p| *p > 0).map(|p| 1e9 / p as f64),
                    }
                })
                .collect(),
            map_frame: dataset.map_frame.clone(),
            ego_frame: dataset.ego_frame.clone(),
            frame_tree: dataset
                .tf
                .edges()
                .into_iter()
                .map(|(parent, child, is_static, samples)| {
                    let frozen = frozen.iter().any(|(p, c)| *p == parent && *c == child);
                    FrameEdge {
                        kind: if is_static || frozen {
                            "static"
                        } else {
                            "dynamic"
                        }
                        .to_string(),
                        parent,
                        child,
                        samples,
                    }
                })
                .collect(),
            start_stamp_nanos: span.map(|s| s.0.nanos()),
            end_stamp_nanos: span.map(|s| s.1.nanos()),
            duration_secs: span.map(|(a, b)| b.secs_since(a)),
            usable_keyframes: dataset
                .keyframes(superflow_schemas::time::KEYFRAME_INTERVAL_NANOS)
                .len(),
            camera_timing: CameraTimingReport::of(dataset),
            skipped: dataset.skipped.clone(),
            problems: dataset.check_sensors().err().map(|e| e.to_string()),
            labels: None,
        }
    }

    /// The report for people.
    pub fn to_text(&self) -> String {
        let mut out = String::new();
        for f in &self.files {
            let _ = writeln!(
                out,
                "file {} ({} bytes, profile {:?}, {})",
                f.path, f.bytes, f.profile, f.library
            );
            for d in &f.damage {
                let _ = writeln!(out, "  damage: {d}");
            }
        }
        let _ = writeln!(out, "dialect {}", self.dialect);
        let _ = writeln!(out, "\nchannels");
        for c in &self.channels {
            let role = match &c.role {
                Role::Ignored(why) => format!("ignored ({why})"),
                other => other.name().to_string(),
            };
            let rate = c.rate_hz.map_or("-".to_string(), |r| format!("{r:.1} Hz"));
            let _ = writeln!(
                out,
                "  {:<40} {:<28} {:>6} msgs {:>9}  {}",
                c.topic, c.schema, c.message_count, rate, role
            );
        }
        let _ = writeln!(
            out,
            "\nlidar {} in frame {} ({} sweeps)",
            self.lidar_topic.as_deref().unwrap_or("-"),
            self.lidar_frame.as_deref().unwrap_or("-"),
            self.lidar_sweeps
        );
        let _ = writeln!(out, "\ncameras");
        for c in &self.cameras {
            let _ = writeln!(
                out,
                "  {:<16} {}x{} {:<20} {:>4} images {:>6}  frame {}  calibration {}  superpixels {}",
                c.name,
                c.width.unwrap_or(0),
                c.height.unwrap_or(0),
                c.distortion_model.as_deref().unwrap_or("uncalibrated"),
                c.images,
                c.rate_hz.map_or("-".to_string(), |r| format!("{r:.1} Hz")),
                c.frame_id,
                c.calibration_topic.as_deref().unwrap_or("-"),
                c.superpixel_topic.as_deref().unwrap_or("-"),
            );
            if let Some(slic) = &c.slic_topic {
                let _ = writeln!(out, "  {:<16} SLIC superpixels {slic}", "");
            }
        }
        let _ = writeln!(
            out,
            "\nframe tree (map {}, ego {})",
            self.map_frame.as_deref().unwrap_or("?"),
            self.ego_frame.as_deref().unwrap_or("?")
        );
        for e in &self.frame_tree {
            let _ = writeln!(
                out,
                "  {} -> {} ({}, {} samples)",
                e.parent, e.child, e.kind, e.samples
            );
        }
        if let Some(d) = self.duration_secs {
            let _ = writeln!(
                out,
                "\ntime span {d:.3} s; usable keyframes (0.5 s): {}",
                self.usable_keyframes
            );
        }
        let t = &self.camera_timing;
        if !t.scan_ms.is_empty() {
            let _ = writeln!(
                out,
                "LiDAR scans the cameras at (ms from the sweep stamp, {}):",
                t.timing
            );
            for (camera, moments) in &t.scan_ms {
                let ms: Vec<String> = moments.iter().map(|m| format!("{m:+.1}")).collect();
                let _ = writeln!(out, "  {camera}: {}", ms.join(" and "));
            }
        }
        if let Some([median, max]) = t.worst_offset_ms {
            let _ = writeln!(
                out,
                "keyframes (least camera offset): {}; worst camera offset median {median:.1} ms, max {max:.1} ms",
                t.keyframes
            );
        }
        if let Some(labels) = &self.labels {
            out.push_str(&labels.to_text());
        }
        let _ = writeln!(out, "skipped {} messages", self.skipped.total());
        for (kind, e) in &self.skipped.entries {
            let _ = writeln!(out, "  {kind}: {} (first: {})", e.count, e.first);
        }
        if let Some(p) = &self.problems {
            let _ = writeln!(out, "\nnot trainable: {p}");
        }
        out
    }
}
