//! A dataset: many drives, each one or more MCAP files (a recording split in parts),
//! indexed in one pass per file (built in `drive/index.rs`) — every LiDAR sweep and camera frame with
//! its sensor stamp and location, every transform in a [`TransformTree`], every
//! calibration — plus a report of what was skipped and why. This file holds the dataset
//! and drive types, what a drive answers (sensor checks, keyframes) and the reading of
//! one sensor message.

use super::discover::{IngestConfig, Role};
use super::streams::EGO_FRAMES;
use super::tf::TransformTree;
use crate::decode::image::{self, ImageError, Scale, ScaledImage, Target};
use crate::decode::points::{DecodedCloud, PointsError};
use crate::decode::{DecodeError, foxglove, ros2};
use crate::decode::{Dialect, SchemaKind, schema_kind};
use crate::source::{ChunkCache, McapFile, MessageLoc, MessageRef, SourceError};
use serde::{Deserialize, Serialize};
use std::path::PathBuf;
use superflow_schemas::Stamp;
use superflow_schemas::sensor::{CameraCalibration, Image};

use super::inputs::drive_groups;
use super::skips::SkipReport;

/// A sensor message located in the dataset.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub struct FrameRef {
    /// The sensor's own stamp (`header.stamp` / `timestamp`), never the log time.
    pub stamp: Stamp,
    /// Index of the file in [`Dataset::files`].
    pub file: u32,
    /// Where the message is in that file.
    pub loc: MessageLoc,
}

/// The LiDAR stream.
#[derive(Debug, Clone)]
pub struct LidarStream {
    /// Its topic.
    pub topic: String,
    /// Frame of its points.
    pub frame_id: String,
    /// Encoding dialect.
    pub dialect: Dialect,
    /// Every sweep, sorted by stamp.
    pub sweeps: Vec<FrameRef>,
}

/// A point-cloud channel of a `<drive>.labels.mcap` sidecar: label clouds parallel to the
/// LiDAR's sweeps (same stamps, same point order), one per sweep. Which one labels the
/// LiDAR is decided when the labels are opened ([`super::labels::DriveLabels::open`]).
#[derive(Debug, Clone)]
pub struct LabelCloudStream {
    /// Its topic.
    pub topic: String,
    /// The LiDAR topic its channel metadata names
    /// ([`LABELS_LIDAR_TOPIC_KEY`](super::discover::LABELS_LIDAR_TOPIC_KEY)), if any.
    pub lidar_topic: Option<String>,
    /// Every label cloud, sorted by stamp.
    pub frames: Vec<FrameRef>,
}

/// One camera: its image stream, calibration and optional class-map stream.
#[derive(Debug, Clone)]
pub struct CameraStream {
    /// Name (the last segment of its topic namespace, `CAM_FRONT`, `cam_front`).
    pub name: String,
    /// Topic of its images.
    pub image_topic: String,
    /// Compressed or raw images.
    pub image_kind: SchemaKind,
    /// Encoding dialect.
    pub dialect: Dialect,
    /// The optical frame of its images.
    pub frame_id: String,
    /// Topic of its calibration, if found.
    pub calibration_topic: Option<String>,
    /// Distinct calibrations in time order (usually one).
    pub calibrations: Vec<CameraCalibration>,
    /// Every image, sorted by stamp.
    pub frames: Vec<FrameRef>,
    /// Topic of its per-pixel class maps, if recorded.
    pub superpixel_topic: Option<String>,
    /// Compressed or raw class maps.
    pub superpixel_kind: Option<SchemaKind>,
    /// Every class map, sorted by stamp.
    pub superpixels: Vec<FrameRef>,
    /// SLIC superpixels precomputed by `superflow-pipeline superpixels`, if found.
    pub slic: Option<SlicStream>,
}

/// A camera's precomputed SLIC superpixels (a `<drive>.slic.mcap` sidecar).
#[derive(Debug, Clone)]
pub struct SlicStream {
    /// Topic.
    pub topic: String,
    /// The settings they were computed with (see `sample::sidecar::settings_key`).
    pub settings: String,
    /// Every label map, sorted by stamp.
    pub frames: Vec<FrameRef>,
}

impl CameraStream {
    /// The calibration in force at `stamp` (the latest one at or before it, else the first).
    pub fn calibration_at(&self, stamp: Stamp) -> Option<&CameraCalibration> {
        self.calibrations
            .iter()
            .rev()
            .find(|c| c.stamp <= stamp)
            .or(self.calibrations.first())
    }

    /// Median spacing of the images, nanoseconds.
    pub fn period_nanos(&self) -> Option<i64> {
        median_spacing(&self.frames)
    }
}

fn median_spacing(frames: &[FrameRef]) -> Option<i64> {
    let mut gaps: Vec<i64> = frames
        .windows(2)
        .map(|w| w[1].stamp.nanos_since(w[0].stamp))
        .collect();
    if gaps.is_empty() {
        return None;
    }
    gaps.sort_unstable();
    Some(gaps[gaps.len() / 2])
}

/// What a channel holds, over all files of the dataset.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct ChannelSummary {
    /// Topic.
    pub topic: String,
    /// Role assigned by discovery (or the config).
    pub role: Role,
    /// Schema name.
    pub schema: String,
    /// Schema encoding.
    pub schema_encoding: String,
    /// Message encoding.
    pub message_encoding: String,
    /// Messages read.
    pub message_count: u64,
    /// Messages per second over the channel's span (sensor stamps where decoded, else
    /// log times).
    pub rate_hz: Option<f64>,
}

/// Why a dataset cannot be used for training (it can still be inspected).
#[derive(Debug, thiserror::Error)]
pub enum IngestError {
    /// No input files.
    #[error("no MCAP files given")]
    NoFiles,
    /// A file could not be opened or is not MCAP.
    #[error(transparent)]
    Source(#[from] SourceError),
    /// Listing a directory failed.
    #[error("{path}: {source}")]
    Io {
        /// The directory.
        path: PathBuf,
        /// The error.
        source: std::io::Error,
    },
    /// Sensors that training needs are missing.
    #[error("{files}: {problems}")]
    Missing {
        /// The files of the dataset.
        files: String,
        /// What is missing, `; `-separated.
        problems: String,
    },
}

/// Every drive of a dataset.
#[derive(Debug)]
pub struct Dataset {
    /// The drives, in input order.
    pub drives: Vec<Drive>,
}

impl Dataset {
    /// Indexes every drive of `inputs` (files, directories, rosbag2 directories).
    pub fn open(inputs: &[PathBuf], config: &IngestConfig) -> Result<Dataset, IngestError> {
        Self::open_with_progress(inputs, config, |_, _| {})
    }

    /// [`Dataset::open`], reporting `(bytes indexed, total bytes)` as it goes.
    pub fn open_with_progress(
        inputs: &[PathBuf],
        config: &IngestConfig,
        mut progress: impl FnMut(u64, u64),
    ) -> Result<Dataset, IngestError> {
        let groups = drive_groups(inputs)?;
        let total: u64 = groups
            .iter()
            .flatten()
            .map(|f| std::fs::metadata(f).map_or(0, |m| m.len()))
            .sum();
        let mut done = 0u64;
        let mut drives = Vec::with_capacity(groups.len());
        for files in &groups {
            let drive = Drive::open_with_progress(files, config, |d, _| progress(done + d, total))?;
            done += drive.files.iter().map(McapFile::len).sum::<u64>();
            drives.push(drive);
        }
        Ok(Dataset { drives })
    }

    /// Checks every drive ([`Drive::check_sensors`]).
    pub fn check_sensors(&self) -> Result<(), IngestError> {
        self.drives.iter().try_for_each(Drive::check_sensors)
    }
}

/// One drive: one or more MCAP files of the same recording, indexed together.
#[derive(Debug)]
pub struct Drive {
    /// The files, in the order given.
    pub files: Vec<McapFile>,
    /// Every channel with its role, sorted by topic.
    pub channels: Vec<ChannelSummary>,
    /// The LiDAR, if one was found.
    pub lidar: Option<LidarStream>,
    /// Cameras, sorted by name.
    pub cameras: Vec<CameraStream>,
    /// The point clouds of a `<drive>.labels.mcap` sidecar, sorted by topic (empty
    /// without one).
    pub label_clouds: Vec<LabelCloudStream>,
    /// Every transform.
    pub tf: TransformTree,
    /// Stamped edges that never change, treated as static (re-published extrinsics).
    pub frozen_edges: Vec<(String, String)>,
    /// The map frame, if determined.
    pub map_frame: Option<String>,
    /// The ego frame, if determined.
    pub ego_frame: Option<String>,
    /// Messages skipped during indexing, by kind.
    pub skipped: SkipReport,
    /// The configuration used.
    pub config: IngestConfig,
}

impl Drive {
    /// The files' paths, comma-separated (for messages).
    pub fn file_list(&self) -> String {
        self.files
            .iter()
            .map(|f| f.path().display().to_string())
            .collect::<Vec<_>>()
            .join(", ")
    }

    /// Checks that the dataset has what training needs: a LiDAR, at least one camera,
    /// a calibration for every camera, ego and map frames, and the LiDAR and camera
    /// frames in the transform tree.
    pub fn check_sensors(&self) -> Result<(), IngestError> {
        let mut problems = Vec::new();
        match &self.lidar {
            None => problems.push(
                "no LiDAR channel (foxglove.PointCloud or sensor_msgs/msg/PointCloud2)".to_string(),
            ),
            Some(l) if l.sweeps.is_empty() => {
                problems.push(format!("LiDAR {} has no readable sweep", l.topic))
            }
            Some(_) => {}
        }
        if self.cameras.is_empty() {
            problems.push("no camera image channel".into());
        }
        for camera in &self.cameras {
            if camera.calibrations.is_empty() {
                problems.push(format!(
                    "camera {} ({}) has no calibration (no CameraInfo / CameraCalibration in its namespace or frame `{}`)",
                    camera.name, camera.image_topic, camera.frame_id
                ));
            }
        }
        match (&self.ego_frame, &self.map_frame) {
            (Some(ego), Some(_)) if self.ego_poses_missing() => problems.push(format!(
                "no ego poses: no transform places `{ego}` in a map or odom frame (it is the \
                 root of its transform tree; is `/tf` missing?)"
            )),
            (Some(ego), Some(_)) => {
                let sensors = self
                    .lidar
                    .iter()
                    .map(|l| (&l.topic, &l.frame_id))
                    .chain(self.cameras.iter().map(|c| (&c.image_topic, &c.frame_id)));
                for (topic, frame) in sensors {
                    if !self.tf.contains(frame) {
                        problems.push(format!(
                            "{topic}: frame `{frame}` has no transform to `{ego}`"
                        ));
                    }
                }
            }
            _ if self.tf.frames().is_empty() => problems.push(
                "no transforms: no readable /tf or /tf_static message, so no ego pose and no \
                 sensor extrinsics"
                    .to_string(),
            ),
            _ => problems.push(format!(
                "no ego frame (tried {}) in the transforms; frames: {}",
                EGO_FRAMES.join(", "),
                self.tf.frames().join(", ")
            )),
        }
        if problems.is_empty() {
            Ok(())
        } else {
            Err(IngestError::Missing {
                files: self.file_list(),
                problems: problems.join("; "),
            })
        }
    }

    /// Whether the ego frame is its own map: nothing in the transforms moves it (the
    /// ego frame is the root of its tree, e.g. only `/tf_static` was recorded) and no
    /// `map_frame` was configured. Every pose lookup would then answer the identity.
    pub fn ego_poses_missing(&self) -> bool {
        self.config.map_frame.is_none()
            && self
                .ego_frame
                .as_ref()
                .is_some_and(|ego| self.map_frame.as_ref() == Some(ego))
    }

    /// First and last LiDAR stamps.
    pub fn time_span(&self) -> Option<(Stamp, Stamp)> {
        let sweeps = &self.lidar.as_ref()?.sweeps;
        Some((sweeps.first()?.stamp, sweeps.last()?.stamp))
    }

    /// LiDAR sweeps usable as keyframes, at least `interval_nanos` apart: every camera
    /// has an image within half its period, and the ego pose is known at the sweep and
    /// at those images. Returns sweep indices.
    pub fn keyframes(&self, interval_nanos: i64) -> Vec<usize> {
        let (Some(lidar), Some(map), Some(ego)) = (&self.lidar, &self.map_frame, &self.ego_frame)
        else {
            return Vec::new();
        };
        if self.ego_poses_missing() {
            return Vec::new();
        }
        let mut out = Vec::new();
        let mut last: Option<Stamp> = None;
        for (i, sweep) in lidar.sweeps.iter().enumerate() {
            if last.is_some_and(|l| sweep.stamp.nanos_since(l) < interval_nanos) {
                continue;
            }
            let pose_ok = |s: Stamp| self.tf.lookup(map, ego, s).is_ok();
            let cameras_ok = !self.cameras.is_empty()
                && self.cameras.iter().all(|camera| {
                    let half = camera.period_nanos().unwrap_or(0) / 2;
                    !camera.calibrations.is_empty()
                        && nearest(&camera.frames, sweep.stamp).is_some_and(|f| {
                            f.stamp.nanos_since(sweep.stamp).abs() <= half && pose_ok(f.stamp)
                        })
                });
            if cameras_ok && pose_ok(sweep.stamp) {
                out.push(i);
                last = Some(sweep.stamp);
            }
        }
        out
    }
}

/// The frame nearest to `stamp` in a sorted list.
pub fn nearest(frames: &[FrameRef], stamp: Stamp) -> Option<&FrameRef> {
    let at = frames.partition_point(|f| f.stamp < stamp);
    let before = at.checked_sub(1).and_then(|i| frames.get(i));
    let after = frames.get(at);
    match (before, after) {
        (Some(b), Some(a)) => Some(
            if stamp.nanos_since(b.stamp) <= a.stamp.nanos_since(stamp) {
                b
            } else {
                a
            },
        ),
        (b, a) => b.or(a),
    }
}

/// Where a frame is: shown as `file: topic at stamp`.
#[derive(Debug, Clone, PartialEq, Eq)]
pub struct FrameAt {
    /// The file.
    pub file: String,
    /// The topic.
    pub topic: String,
    /// The frame's stamp.
    pub stamp: Stamp,
}

impl std::fmt::Display for FrameAt {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        write!(f, "{}: {} at {}", self.file, self.topic, self.stamp)
    }
}

/// A sensor message that could not be read or decoded, with where it is.
#[derive(Debug, thiserror::Error)]
pub enum ReadError {
    /// The file could not deliver the message.
    #[error(transparent)]
    Source(#[from] SourceError),
    /// An image (or class map) of a camera did not decode.
    #[error("{at}: {camera} ({source})")]
    Image {
        /// Where the image is.
        at: FrameAt,
        /// The camera.
        camera: String,
        /// What failed (boxed: a read error stays small).
        #[source]
        source: Box<ImageReadError>,
    },
    /// A LiDAR sweep did not decode.
    #[error("{at}: {source}")]
    Sweep {
        /// Where the sweep is.
        at: FrameAt,
        /// What failed (boxed: a read error stays small).
        #[source]
        source: Box<PointsError>,
    },
    /// A message decoded but cannot be used.
    #[error("{at}: {reason}")]
    Decode {
        /// Where the message is.
        at: FrameAt,
        /// What is wrong, in words.
        reason: String,
    },
}

/// Why an image message did not decode.
#[derive(Debug, thiserror::Error)]
pub enum ImageReadError {
    /// The message itself did not decode (CDR or protobuf).
    #[error(transparent)]
    Message(#[from] DecodeError),
    /// Its image data did not decode.
    #[error(transparent)]
    Image(#[from] ImageError),
    /// The channel's schema is not an image.
    #[error("schema `{0}` is not an image")]
    NotAnImage(String),
}

impl Drive {
    /// The raw message of a sensor frame (through `cache`, which holds a few
    /// decompressed chunks: memory stays bounded whatever the file size).
    pub fn read_raw<'c>(
        &'c self,
        frame: &FrameRef,
        cache: &'c mut crate::source::ChunkCache,
    ) -> Result<MessageRef<'c>, SourceError> {
        let file =
            self.files
                .get(frame.file as usize)
                .ok_or_else(|| SourceError::NoSuchMessage {
                    path: PathBuf::from(self.file_list()),
                    loc: frame.loc,
                })?;
        file.read_message(frame.loc, cache)
    }

    /// Where `frame` of `topic` is: its file, the topic and its stamp.
    pub fn frame_at(&self, frame: &FrameRef, topic: &str) -> FrameAt {
        FrameAt {
            file: self
                .files
                .get(frame.file as usize)
                .map_or_else(|| self.file_list(), |f| f.path().display().to_string()),
            topic: topic.to_string(),
            stamp: frame.stamp,
        }
    }

    /// A [`ReadError::Decode`] naming the file, topic and stamp of `frame`.
    pub(crate) fn decode_error(
        &self,
        frame: &FrameRef,
        topic: &str,
        reason: impl std::fmt::Display,
    ) -> ReadError {
        ReadError::Decode {
            at: self.frame_at(frame, topic),
            reason: reason.to_string(),
        }
    }

    /// Decodes image `frame` of `camera` (its colour image with `Target::Rgb`; pass a
    /// frame of `camera.superpixels` with `Target::Mono` for its class map).
    pub fn read_image(
        &self,
        camera: &CameraStream,
        frame: &FrameRef,
        target: Target,
        cache: &mut ChunkCache,
    ) -> Result<Image, ReadError> {
        self.read_image_scaled(camera, frame, target, Scale::Full, cache)
            .map(|s| s.image)
    }

    /// [`Drive::read_image`] at a reduced [`Scale`] where the image allows it (a JPEG
    /// colour image), with the stored image's size.
    pub fn read_image_scaled(
        &self,
        camera: &CameraStream,
        frame: &FrameRef,
        target: Target,
        scale: Scale,
        cache: &mut ChunkCache,
    ) -> Result<ScaledImage, ReadError> {
        let message = self.read_raw(frame, cache)?;
        decode_image(&message, target, scale).map_err(|source| ReadError::Image {
            at: self.frame_at(frame, &message.channel.topic),
            camera: camera.name.clone(),
            source: Box::new(source),
        })
    }

    /// Decodes LiDAR sweep `frame` (non-finite points are dropped and counted in the
    /// result).
    pub fn read_sweep(
        &self,
        frame: &FrameRef,
        cache: &mut ChunkCache,
    ) -> Result<DecodedCloud, ReadError> {
        let message = self.read_raw(frame, cache)?;
        crate::decode::points::decode_message(&message, None).map_err(|source| ReadError::Sweep {
            at: self.frame_at(frame, &message.channel.topic),
            source: Box::new(source),
        })
    }
}

/// Decodes an image message of either dialect, compressed or raw.
fn decode_image(
    message: &MessageRef<'_>,
    target: Target,
    scale: Scale,
) -> Result<ScaledImage, ImageReadError> {
    let data = message.data;
    let full = |image: Image| ScaledImage {
        native: (image.width, image.height),
        image,
    };
    Ok(match schema_kind(message.channel) {
        Some((SchemaKind::CompressedImage, Dialect::Ros2)) => {
            let m = ros2::decode(data).map_err(DecodeError::from)?;
            image::decode_ros2_compressed_scaled(&m, target, scale)?
        }
        Some((SchemaKind::RawImage, Dialect::Ros2)) => {
            let m = ros2::decode(data).map_err(DecodeError::from)?;
            full(image::decode_ros2_raw(&m, target)?)
        }
        Some((SchemaKind::CompressedImage, Dialect::FoxgloveProtobuf)) => {
            let m = foxglove::decode("foxglove.CompressedImage", data)?;
            image::decode_foxglove_compressed_scaled(&m, target, scale)?
        }
        Some((SchemaKind::RawImage, Dialect::FoxgloveProtobuf)) => {
            let m = foxglove::decode("foxglove.RawImage", data)?;
            full(image::decode_foxglove_raw(&m, target)?)
        }
        _ => {
            let schema = message.channel.schema_name().to_string();
            return Err(ImageReadError::NotAnImage(schema));
        }
    })
}

#[cfg(test)]
mod tests {
    use super::*;
    use nalgebra::Isometry3;
    use superflow_schemas::sensor::StampedTransform;

    fn drive(tf: TransformTree) -> Drive {
        let ego_frame = ["base_link"]
            .iter()
            .find(|f| tf.contains(f))
            .map(|f| f.to_string());
        let map_frame = ego_frame.as_deref().and_then(|e| tf.root_of(e).ok());
        Drive {
            files: Vec::new(),
            channels: Vec::new(),
            lidar: None,
            cameras: Vec::new(),
            label_clouds: Vec::new(),
            tf,
            frozen_edges: Vec::new(),
            map_frame,
            ego_frame,
            skipped: SkipReport::default(),
            config: IngestConfig::default(),
        }
    }

    #[test]
    fn extrinsics_without_ego_poses_are_not_trainable() {
        let mut tf = TransformTree::new(0);
        tf.insert(StampedTransform {
            stamp: Stamp::from_nanos(1),
            parent_frame: "base_link".into(),
            child_frame: "lidar_top".into(),
            parent_from_child: Isometry3::identity(),
            is_static: true,
        })
        .unwrap_or_else(|e| panic!("{e}"));
        let only_static = drive(tf);
        assert!(only_static.ego_poses_missing());
        let err = only_static
            .check_sensors()
            .err()
            .map(|e| e.to_string())
            .unwrap_or_default();
        assert!(
            err.contains("no ego poses") && err.contains("`base_link`") && err.contains("/tf"),
            "{err}"
        );

        let none = drive(TransformTree::new(0));
        let err = none
            .check_sensors()
            .err()
            .map(|e| e.to_string())
            .unwrap_or_default();
        assert!(err.contains("no transforms"), "{err}");
    }
}
