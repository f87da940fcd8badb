//! [`DriveLabels`]: a drive's labels found ([`DriveLabels::open`]) and read sweep by
//! sweep ([`DriveLabels::read`]), as the folder's documentation describes.

use super::config::LabelConfig;
use super::error::LabelError;
use super::form::LabelForm;
use super::map::LabelMap;
use crate::decode::points::{
    CloudOptions, DecodedCloud, LabelFieldSpec, decode_labels_message, decode_message_with,
    field_names, find_label_field,
};
use crate::drive::discover::LABELS_LIDAR_TOPIC_KEY;
use crate::drive::index::Drive;
use crate::drive::read::{FrameAt, ReadError};
use crate::drive::streams::{LabelCloudStream, LidarStream};
use crate::source::ChunkCache;

/// Sweeps tried, in order, for the field list that tells whether the LiDAR's clouds carry
/// labels (the first readable one decides).
const FIELD_PROBE_SWEEPS: usize = 8;

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
            key: LABELS_LIDAR_TOPIC_KEY,
        })
}
