//! Gathering the report from an indexed dataset: what the index knows, plus the reads a
//! part of the report needs (labels, camera timing, LiDAR facts).

use super::INSPECT_FORMAT;
use super::model::{
    CameraReport, CameraTimingReport, ClassCount, DriveReport, FileReport, FrameEdge,
    InspectReport, LabelsReport,
};
use crate::drive::{Dataset, Drive, DriveLabels, LabelConfig, Role};
use crate::fleet::{FleetReport, read_lidar_facts};
use crate::sample::SampleConfig;
use crate::sample::plan::drive_keyframes;
use crate::source::ChunkCache;
use rayon::prelude::*;
use std::collections::BTreeMap;

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
}
