//! Per-point semantic labels of a drive's LiDAR sweeps — what a linear probe or a
//! segmentation head is trained and scored on (nuScenes-lidarseg, SemanticKITTI converted
//! to MCAP).
//!
//! # Where labels come from ([`LabelForm`])
//!
//! * **A field of the LiDAR cloud** (`foxglove.PointCloud` or `sensor_msgs/msg/PointCloud2`):
//!   `[labels] field`, else the first of `label`, `class`, `semantic`, `semantic_label`,
//!   `lidarseg` (regardless of case) that the first readable sweep has. Any integer type,
//!   or a float holding integers ([`crate::decode::points::LabelFieldSpec`]).
//! * **A sidecar** `<drive>.labels.mcap` next to `<drive>.mcap` (grouped with the drive
//!   like the other sidecars, [`super::files`]): a point cloud per sweep with the sweep's
//!   stamp, its point order and count, and the label field (the configured or a default
//!   name, else its only field). The sidecar's point clouds are never taken for the LiDAR.
//!   Which of them labels the LiDAR: the only one; else the one whose channel metadata
//!   [`LABELS_LIDAR_TOPIC_KEY`](super::discover::LABELS_LIDAR_TOPIC_KEY) names the LiDAR
//!   topic; else the one whose topic starts with the LiDAR topic
//!   (`/lidar_top/points_raw/labels` for `/lidar_top/points_raw`); else it is an error
//!   ([`LabelError::AmbiguousSidecar`]). A sweep is matched with the label cloud of the
//!   same stamp; none, or one with another point count, is an error naming the sidecar,
//!   its topic and the stamp.
//!
//! The field wins when a drive has both.
//!
//! # What a sweep's labels are aligned with
//!
//! [`DriveLabels::read`] gives the labels of sweep `i` of [`Drive::lidar`] — the index the
//! sample builder and [`crate::sample::KeyframeRef::sweep`] use — aligned point for point
//! with what [`Drive::read_sweep`] decodes for that sweep: the points left after the
//! pipeline drops those with a non-finite coordinate (the only points it drops; de-skew
//! moves points without reordering them). A sidecar's labels, which cover every point
//! of the message, are carried through the same dropping
//! ([`crate::decode::points::CloudOptions::kept_indices`]).
//!
//! # Raw ids and training classes ([`LabelConfig`], `[labels]`)
//!
//! A stored value, masked by `label_mask` if set (SemanticKITTI: `0xFFFF`), is the **raw
//! id** ([`PointCloud::label`](superflow_schemas::sensor::PointCloud::label)). The
//! **training class** is a `u8`: `mapping[raw]`, `ignore_index` (255) for a raw id the
//! mapping does not list; without a mapping the raw id itself, and a raw id that is not
//! below the number of `classes` (when given) or 256 is an error
//! ([`LabelError::UnknownId`]).
//!
//! Nothing here runs unless asked: the sample builder never reads labels.
//!
//! ```no_run
//! use superflow_pipeline::drive::labels::{DriveLabels, LabelConfig};
//! use superflow_pipeline::drive::{Dataset, IngestConfig};
//! use superflow_pipeline::source::ChunkCache;
//!
//! let dataset = Dataset::open(&["drive.mcap".into()], &IngestConfig::default())?;
//! let drive = &dataset.drives[0];
//! if let Some(labels) = DriveLabels::open(drive, &LabelConfig::default())? {
//!     let mut cache = ChunkCache::new(2);
//!     let sweep = labels.read(0, &mut cache)?;
//!     assert_eq!(sweep.labels.len(), sweep.decoded.cloud.len());
//! }
//! # Ok::<(), Box<dyn std::error::Error>>(())
//! ```

use super::index::Drive;
use super::read::{FrameAt, ReadError};
use super::streams::{LabelCloudStream, LidarStream};
use crate::decode::points::{
    CloudOptions, DecodedCloud, LabelFieldSpec, PointsError, decode_labels_message,
    decode_message_with, field_names, find_label_field,
};
use crate::source::ChunkCache;
use rustc_hash::FxHashMap;
use serde::{Deserialize, Serialize};
use std::collections::BTreeMap;
use superflow_common::InvalidSetting;
use superflow_schemas::Stamp;

/// Sweeps tried, in order, for the field list that tells whether the LiDAR's clouds carry
/// labels (the first readable one decides).
const FIELD_PROBE_SWEEPS: usize = 8;

/// The `[labels]` section of `pipeline.toml`: how per-point labels are read and turned
/// into training classes.
#[derive(Debug, Clone, PartialEq, Eq, Serialize, Deserialize)]
#[serde(default, deny_unknown_fields)]
pub struct LabelConfig {
    /// The label field, matched regardless of case; by default the first of `label`,
    /// `class`, `semantic`, `semantic_label`, `lidarseg` present (a sidecar's only field
    /// also serves).
    pub field: Option<String>,
    /// Bits of the stored value that are the class (SemanticKITTI: `0xFFFF`, the instance
    /// being in the upper 16 bits); by default the whole value.
    pub label_mask: Option<u32>,
    /// Raw id → training class (nuScenes-lidarseg: its 32 raw classes to the 16 training
    /// classes). Keys are decimal (or `0x` hex) raw ids; a raw id not listed becomes
    /// `ignore_index`. Empty (the default): raw ids are the training classes.
    pub mapping: BTreeMap<String, u8>,
    /// The training class of unlabelled or unmapped points (255).
    pub ignore_index: u8,
    /// Names of the training classes, in id order, for reports; with them, a raw id of at
    /// least their number is an error when there is no mapping. Empty by default.
    pub classes: Vec<String>,
}

impl Default for LabelConfig {
    fn default() -> Self {
        Self {
            field: None,
            label_mask: None,
            mapping: BTreeMap::new(),
            ignore_index: 255,
            classes: Vec::new(),
        }
    }
}

impl LabelConfig {
    /// Checks the settings ([`LabelConfig::label_map`] without the map).
    pub fn validate(&self) -> Result<(), InvalidSetting> {
        self.label_map().map(|_| ())
    }

    /// Which field to read and which bits of it.
    pub fn field_spec(&self) -> LabelFieldSpec {
        LabelFieldSpec {
            name: self.field.clone(),
            mask: self.label_mask,
        }
    }

    /// The checked raw id → training class map: mapping keys are raw ids, a mask is not
    /// 0, `ignore_index` is not a named class, and every mapped class is a named class
    /// (when classes are named) or `ignore_index`.
    pub fn label_map(&self) -> Result<LabelMap, InvalidSetting> {
        if self.field.as_deref().is_some_and(str::is_empty) {
            return Err(InvalidSetting::new(
                "labels.field",
                "\"\"",
                "must name a field",
            ));
        }
        if self.label_mask == Some(0) {
            return Err(InvalidSetting::new(
                "labels.label_mask",
                0,
                "must keep at least one bit",
            ));
        }
        let class_count = self.classes.len();
        if class_count > usize::from(self.ignore_index) {
            return Err(InvalidSetting::new(
                "labels.ignore_index",
                self.ignore_index,
                format!(
                    "must not be a class id: labels.classes names {class_count} classes (0..{class_count})"
                ),
            ));
        }
        let table = (!self.mapping.is_empty())
            .then(|| {
                self.mapping
                    .iter()
                    .map(|(key, &class)| {
                        let setting = format!("labels.mapping.{key}");
                        let raw = parse_raw_id(key).ok_or_else(|| {
                            InvalidSetting::new(
                                &setting,
                                class,
                                "has a key that is not a raw id (a decimal or 0x hex u32)",
                            )
                        })?;
                        if class_count > 0
                            && usize::from(class) >= class_count
                            && class != self.ignore_index
                        {
                            return Err(InvalidSetting::new(
                                setting,
                                class,
                                format!(
                                    "is neither one of the {class_count} labels.classes nor labels.ignore_index ({})",
                                    self.ignore_index
                                ),
                            ));
                        }
                        Ok((raw, class))
                    })
                    .collect::<Result<FxHashMap<u32, u8>, _>>()
            })
            .transpose()?;
        Ok(LabelMap {
            table,
            ignore_index: self.ignore_index,
            class_count,
        })
    }
}

/// A raw id written as a TOML key: decimal or `0x` hex.
fn parse_raw_id(key: &str) -> Option<u32> {
    let key = key.trim();
    match key.strip_prefix("0x").or_else(|| key.strip_prefix("0X")) {
        Some(hex) => u32::from_str_radix(hex, 16).ok(),
        None => key.parse().ok(),
    }
}

/// Raw ids → training classes ([`LabelConfig::label_map`]).
#[derive(Debug, Clone, PartialEq, Eq)]
pub struct LabelMap {
    /// Raw id → class; `None`: the raw id is the class.
    table: Option<FxHashMap<u32, u8>>,
    ignore_index: u8,
    /// Named classes (0: none named).
    class_count: usize,
}

impl LabelMap {
    /// The training class of raw id `raw`: mapped (`ignore_index` when unlisted), or
    /// without a mapping the id itself — `Err(raw)` when it is not below the number of
    /// named classes (or 256).
    #[inline]
    pub fn class_of(&self, raw: u32) -> Result<u8, u32> {
        match &self.table {
            Some(table) => Ok(table.get(&raw).copied().unwrap_or(self.ignore_index)),
            None => u8::try_from(raw)
                .ok()
                .filter(|c| self.class_count == 0 || usize::from(*c) < self.class_count)
                .ok_or(raw),
        }
    }

    /// The training classes of `raw` ids; `Err` with the first id that has none.
    pub fn classes_of(&self, raw: &[u32]) -> Result<Vec<u8>, u32> {
        raw.iter().map(|&r| self.class_of(r)).collect()
    }

    /// The class of unlabelled and unmapped points.
    pub fn ignore_index(&self) -> u8 {
        self.ignore_index
    }

    /// Whether raw ids go through a mapping.
    pub fn has_mapping(&self) -> bool {
        self.table.is_some()
    }

    /// Why a raw id has no class without a mapping, for errors.
    fn limit(&self) -> String {
        if self.class_count > 0 {
            format!(
                "labels.classes names {} classes (ids 0..{})",
                self.class_count, self.class_count
            )
        } else {
            "training classes are u8 ids below 256".to_string()
        }
    }
}

/// Where a drive's labels are.
#[derive(Debug, Clone, PartialEq, Eq, Serialize, Deserialize)]
#[serde(tag = "form", rename_all = "snake_case")]
pub enum LabelForm {
    /// A field of the LiDAR's clouds.
    Field {
        /// The field's name as recorded.
        field: String,
    },
    /// Parallel clouds in a `<drive>.labels.mcap` sidecar.
    Sidecar {
        /// The sidecar file.
        file: String,
        /// Its label-cloud topic.
        topic: String,
    },
}

impl std::fmt::Display for LabelForm {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        match self {
            LabelForm::Field { field } => write!(f, "field `{field}` of the LiDAR clouds"),
            LabelForm::Sidecar { file, topic } => write!(f, "sidecar {file}: {topic}"),
        }
    }
}

/// Why labels cannot be read.
#[derive(Debug, thiserror::Error)]
pub enum LabelError {
    /// The `[labels]` settings are out of range.
    #[error(transparent)]
    Config(#[from] InvalidSetting),
    /// The sweep (or, for a field, its labels) could not be read or decoded.
    #[error(transparent)]
    Read(#[from] ReadError),
    /// A sweep index past the LiDAR's sweeps.
    #[error("{files}: sweep {sweep} requested; the LiDAR has {sweeps} sweeps")]
    NoSweep {
        /// The drive's files.
        files: String,
        /// The index asked for.
        sweep: usize,
        /// Sweeps of the LiDAR.
        sweeps: usize,
    },
    /// A sidecar label cloud did not decode.
    #[error("{at}: {source}")]
    LabelCloud {
        /// Where it is.
        at: FrameAt,
        /// Why (boxed: the error stays small).
        #[source]
        source: Box<PointsError>,
    },
    /// A sweep without a label cloud of its stamp in the sidecar.
    #[error(
        "{file}: {topic} has no label cloud at {stamp}, the stamp of sweep {sweep} of {lidar_topic}"
    )]
    MissingLabelCloud {
        /// The sidecar file.
        file: String,
        /// Its label-cloud topic.
        topic: String,
        /// The sweep's stamp.
        stamp: Stamp,
        /// The sweep's index.
        sweep: usize,
        /// The LiDAR topic.
        lidar_topic: String,
    },
    /// A label cloud whose point count differs from its sweep's.
    #[error(
        "{file}: {topic} at {stamp}: {labels} labels for the {points} points of the sweep on {lidar_topic}"
    )]
    PointCount {
        /// The sidecar file.
        file: String,
        /// Its label-cloud topic.
        topic: String,
        /// The stamp of both.
        stamp: Stamp,
        /// Labels in the label cloud.
        labels: usize,
        /// Points in the sweep's message (dropped ones included).
        points: usize,
        /// The LiDAR topic.
        lidar_topic: String,
    },
    /// A raw id without a training class and no mapping to give it one.
    #[error("{at}: unknown raw id {id} without a mapping ({limit}; set [labels] mapping)")]
    UnknownId {
        /// The labelled message (LiDAR cloud or sidecar label cloud).
        at: FrameAt,
        /// The raw id.
        id: u32,
        /// The limit it breaks, in words.
        limit: String,
    },
    /// Several label clouds in the sidecar and nothing tells which labels the LiDAR.
    #[error(
        "{files}: the labels sidecar has several point clouds ({topics}) and none is named for the LiDAR {lidar_topic} (channel metadata `{key}`) or has a topic starting with it"
    )]
    AmbiguousSidecar {
        /// The drive's files.
        files: String,
        /// The candidates, comma-separated.
        topics: String,
        /// The LiDAR topic.
        lidar_topic: String,
        /// The metadata key that would decide.
        key: &'static str,
    },
}

/// A sweep with its labels.
#[derive(Debug, Clone, PartialEq)]
pub struct LabelledSweep {
    /// The sweep as [`Drive::read_sweep`] decodes it, with
    /// [`PointCloud::label`](superflow_schemas::sensor::PointCloud::label) holding each
    /// point's raw id.
    pub decoded: DecodedCloud,
    /// Each point's training class (see the module documentation).
    pub labels: Vec<u8>,
}

/// The labels of one drive: where they are, and the reading of any sweep's.
#[derive(Debug, Clone)]
pub struct DriveLabels<'d> {
    drive: &'d Drive,
    lidar: &'d LidarStream,
    form: LabelForm,
    /// The sidecar's label clouds (sidecar form only).
    sidecar: Option<&'d LabelCloudStream>,
    spec: LabelFieldSpec,
    map: LabelMap,
}

impl<'d> DriveLabels<'d> {
    /// The labels of `drive`, or `None` when it has none (no LiDAR, no label field in
    /// its first readable sweep and no labels sidecar). Reads one sweep's field list.
    pub fn open(drive: &'d Drive, config: &LabelConfig) -> Result<Option<Self>, LabelError> {
        let map = config.label_map()?;
        let spec = config.field_spec();
        let Some(lidar) = &drive.lidar else {
            return Ok(None);
        };
        let (form, sidecar) = if let Some(field) = lidar_label_field(drive, lidar, &spec) {
            (LabelForm::Field { field }, None)
        } else if let Some(stream) = sidecar_stream(drive, lidar)? {
            let file = stream
                .frames
                .first()
                .and_then(|f| drive.files.get(f.file as usize))
                .map_or_else(|| drive.file_list(), |f| f.path().display().to_string());
            let form = LabelForm::Sidecar {
                file,
                topic: stream.topic.clone(),
            };
            (form, Some(stream))
        } else {
            return Ok(None);
        };
        Ok(Some(Self {
            drive,
            lidar,
            form,
            sidecar,
            spec,
            map,
        }))
    }

    /// Where the labels are.
    pub fn form(&self) -> &LabelForm {
        &self.form
    }

    /// The raw id → training class map.
    pub fn map(&self) -> &LabelMap {
        &self.map
    }

    /// Sweeps of the LiDAR (valid indices of [`DriveLabels::read`]).
    pub fn sweeps(&self) -> usize {
        self.lidar.sweeps.len()
    }

    /// Sweep `sweep` of the drive's LiDAR (its index in [`LidarStream::sweeps`], as the
    /// sample builder counts) decoded as [`Drive::read_sweep`] does, with each kept
    /// point's raw id and training class.
    pub fn read(&self, sweep: usize, cache: &mut ChunkCache) -> Result<LabelledSweep, LabelError> {
        let (drive, lidar) = (self.drive, self.lidar);
        let frame = lidar.sweeps.get(sweep).ok_or_else(|| LabelError::NoSweep {
            files: drive.file_list(),
            sweep,
            sweeps: lidar.sweeps.len(),
        })?;
        let at = drive.frame_at(frame, &lidar.topic);
        let decode = |options: &CloudOptions<'_>, cache: &mut ChunkCache| {
            let message = drive.read_raw(frame, cache).map_err(ReadError::from)?;
            decode_message_with(&message, options).map_err(|source| ReadError::Sweep {
                at: at.clone(),
                source: Box::new(source),
            })
        };
        match (&self.form, self.sidecar) {
            (LabelForm::Sidecar { file, .. }, Some(stream)) => {
                let options = CloudOptions {
                    kept_indices: true,
                    ..CloudOptions::default()
                };
                let decoded = decode(&options, cache)?;
                self.with_sidecar_labels(decoded, sweep, (file, stream), cache)
            }
            _ => {
                let options = CloudOptions {
                    label: Some(&self.spec),
                    ..CloudOptions::default()
                };
                let decoded = decode(&options, cache)?;
                self.labelled(decoded, at)
            }
        }
    }

    /// Sweep `sweep`, `decoded` with its kept points' message indices, labelled from the
    /// sidecar `file`'s label cloud of its stamp in `stream`.
    fn with_sidecar_labels(
        &self,
        mut decoded: DecodedCloud,
        sweep: usize,
        (file, stream): (&str, &LabelCloudStream),
        cache: &mut ChunkCache,
    ) -> Result<LabelledSweep, LabelError> {
        let (drive, lidar) = (self.drive, self.lidar);
        let stamp = decoded.cloud.stamp;
        let at = stream.frames.partition_point(|f| f.stamp < stamp);
        let label_frame = stream
            .frames
            .get(at)
            .filter(|f| f.stamp == stamp)
            .ok_or_else(|| LabelError::MissingLabelCloud {
                file: file.to_string(),
                topic: stream.topic.clone(),
                stamp,
                sweep,
                lidar_topic: lidar.topic.clone(),
            })?;
        let label_at = drive.frame_at(label_frame, &stream.topic);
        let message = drive
            .read_raw(label_frame, cache)
            .map_err(ReadError::from)?;
        let all = decode_labels_message(&message, &self.spec)
            .map_err(|source| LabelError::LabelCloud {
                at: label_at.clone(),
                source: Box::new(source),
            })?
            .labels;
        let points = decoded.cloud.len() + decoded.dropped_non_finite;
        if all.len() != points {
            return Err(LabelError::PointCount {
                file: file.to_string(),
                topic: stream.topic.clone(),
                stamp,
                labels: all.len(),
                points,
                lidar_topic: lidar.topic.clone(),
            });
        }
        let kept = decoded.kept_indices.as_deref().unwrap_or_default();
        // Every kept index is below the message's point count, which `all` matches.
        let raw: Vec<u32> = kept
            .iter()
            .map(|&i| all.get(i as usize).copied().unwrap_or_default())
            .collect();
        decoded.cloud.label = Some(raw);
        self.labelled(decoded, label_at)
    }

    /// [`DriveLabels::read`], only the training classes.
    pub fn training_labels(
        &self,
        sweep: usize,
        cache: &mut ChunkCache,
    ) -> Result<Vec<u8>, LabelError> {
        self.read(sweep, cache).map(|s| s.labels)
    }

    /// The training classes of a decoded sweep whose raw ids are in its cloud; `at` names
    /// the labelled message for errors.
    fn labelled(&self, decoded: DecodedCloud, at: FrameAt) -> Result<LabelledSweep, LabelError> {
        let raw = decoded.cloud.label.as_deref().unwrap_or_default();
        let labels = self
            .map
            .classes_of(raw)
            .map_err(|id| LabelError::UnknownId {
                at,
                id,
                limit: self.map.limit(),
            })?;
        Ok(LabelledSweep { decoded, labels })
    }
}

impl Drive {
    /// Where this drive's labels are under `config`, or `None` when it has none (see
    /// [`DriveLabels::open`]).
    pub fn label_form(&self, config: &LabelConfig) -> Result<Option<LabelForm>, LabelError> {
        Ok(DriveLabels::open(self, config)?.map(|l| l.form))
    }
}

/// The label field of the LiDAR's clouds, from the field list of the first of its first
/// sweeps that reads; `None` when that sweep has none (or none reads).
fn lidar_label_field(drive: &Drive, lidar: &LidarStream, spec: &LabelFieldSpec) -> Option<String> {
    let mut cache = ChunkCache::new(1);
    lidar
        .sweeps
        .iter()
        .take(FIELD_PROBE_SWEEPS)
        .find_map(|frame| {
            let message = drive.read_raw(frame, &mut cache).ok()?;
            field_names(&message).ok()
        })
        .and_then(|names| find_label_field(&names, spec).map(str::to_string))
}

/// The sidecar label clouds that label `lidar` (see the module documentation); `None`
/// without a labels sidecar.
fn sidecar_stream<'d>(
    drive: &'d Drive,
    lidar: &LidarStream,
) -> Result<Option<&'d LabelCloudStream>, LabelError> {
    // Label clouds whose metadata names another LiDAR are not this one's.
    let candidates: Vec<&LabelCloudStream> = drive
        .label_clouds
        .iter()
        .filter(|s| s.lidar_topic.as_ref().is_none_or(|t| *t == lidar.topic))
        .collect();
    if let [only] = candidates.as_slice() {
        return Ok(Some(only));
    }
    if candidates.is_empty() {
        return Ok(None);
    }
    let single = |keep: &dyn Fn(&LabelCloudStream) -> bool| {
        let mut found = candidates.iter().filter(|s| keep(s));
        match (found.next(), found.next()) {
            (Some(s), None) => Some(*s),
            _ => None,
        }
    };
    single(&|s| s.lidar_topic.as_deref() == Some(lidar.topic.as_str()))
        .or_else(|| single(&|s| s.topic.starts_with(&lidar.topic)))
        .map(Some)
        .ok_or_else(|| LabelError::AmbiguousSidecar {
            files: drive.file_list(),
            topics: candidates
                .iter()
                .map(|s| s.topic.as_str())
                .collect::<Vec<_>>()
                .join(", "),
            lidar_topic: lidar.topic.clone(),
            key: super::discover::LABELS_LIDAR_TOPIC_KEY,
        })
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn a_mapping_maps_and_sends_unlisted_ids_to_ignore_index() {
        let config = LabelConfig {
            mapping: BTreeMap::from([
                ("1".to_string(), 0),
                ("0x11".to_string(), 1),
                ("9".to_string(), 255),
            ]),
            classes: vec!["barrier".into(), "vegetation".into()],
            ..LabelConfig::default()
        };
        let map = config.label_map().unwrap();
        assert!(map.has_mapping());
        assert_eq!(
            map.classes_of(&[1, 17, 9, 2, 1000]),
            Ok(vec![0, 1, 255, 255, 255])
        );
        let config = LabelConfig {
            ignore_index: 0,
            ..config
        };
        let e = config.label_map().unwrap_err();
        assert_eq!(e.setting, "labels.ignore_index");
    }

    #[test]
    fn without_a_mapping_raw_ids_are_classes_below_the_named_ones() {
        let map = LabelConfig {
            classes: (0..17).map(|c| format!("class {c}")).collect(),
            ..LabelConfig::default()
        }
        .label_map()
        .unwrap();
        assert_eq!(map.classes_of(&[0, 16, 3]), Ok(vec![0, 16, 3]));
        assert_eq!(map.classes_of(&[0, 17, 3]), Err(17));
        assert!(map.limit().contains("17 classes"), "{}", map.limit());
        let unnamed = LabelConfig::default().label_map().unwrap();
        assert_eq!(unnamed.classes_of(&[255, 31]), Ok(vec![255, 31]));
        assert_eq!(unnamed.class_of(256), Err(256));
    }

    #[test]
    fn bad_settings_name_the_setting() {
        let bad = |config: LabelConfig| config.validate().unwrap_err().setting;
        let mapping = |key: &str, class: u8| LabelConfig {
            mapping: BTreeMap::from([(key.to_string(), class)]),
            classes: vec!["a".into(), "b".into()],
            ..LabelConfig::default()
        };
        assert_eq!(bad(mapping("car", 0)), "labels.mapping.car");
        assert_eq!(bad(mapping("3", 2)), "labels.mapping.3");
        assert!(mapping("3", 255).validate().is_ok());
        assert_eq!(
            bad(LabelConfig {
                label_mask: Some(0),
                ..LabelConfig::default()
            }),
            "labels.label_mask"
        );
        assert_eq!(
            bad(LabelConfig {
                field: Some(String::new()),
                ..LabelConfig::default()
            }),
            "labels.field"
        );
    }
}
