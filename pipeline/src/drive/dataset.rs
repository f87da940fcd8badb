//! A dataset: many drives, each one or more MCAP files (a recording split in parts),
//! indexed in one pass per file — every LiDAR sweep and camera frame with its sensor stamp and location,
//! every transform in a [`TransformTree`], every calibration — plus a report of what was
//! skipped and why.

use super::discover::{self, Dialect, IngestConfig, Role, SchemaKind};
use super::tf::TransformTree;
use crate::decode::{foxglove, ros2};
use crate::source::{ChannelInfo, Damage, McapFile, MessageLoc, MessageRef, SourceError};
use serde::{Deserialize, Serialize};
use std::collections::BTreeMap;
use std::path::{Path, PathBuf};
use superflow_schemas::Stamp;
use superflow_schemas::sensor::CameraCalibration;

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

/// Counted skips, one entry per kind, with the first occurrence spelled out.
#[derive(Debug, Clone, Default, PartialEq, Eq, Serialize, Deserialize)]
pub struct SkipReport {
    /// Kind → count and first example (`file: topic at stamp: error`).
    pub entries: BTreeMap<String, SkipEntry>,
}

/// One kind of skip.
#[derive(Debug, Clone, PartialEq, Eq, Serialize, Deserialize)]
pub struct SkipEntry {
    /// How many.
    pub count: u64,
    /// The first one, in words.
    pub first: String,
}

impl SkipReport {
    /// Counts one skip of `kind`; `detail` is kept for the first.
    pub fn add(&mut self, kind: impl Into<String>, detail: impl FnOnce() -> String) {
        self.entries
            .entry(kind.into())
            .and_modify(|e| e.count += 1)
            .or_insert_with(|| SkipEntry {
                count: 1,
                first: detail(),
            });
    }

    /// Total skips.
    pub fn total(&self) -> u64 {
        self.entries.values().map(|e| e.count).sum()
    }
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

#[derive(Debug)]
struct TopicData {
    channel: ChannelInfo,
    kind: Option<(SchemaKind, Dialect)>,
    count: u64,
    frame_id: Option<String>,
    frames: Vec<FrameRef>,
    /// Log time of each of `frames`, until the stamps are checked against them.
    frame_logs: Vec<u64>,
    calibrations: Vec<CameraCalibration>,
    first_log: u64,
    last_log: u64,
}

// Just the stamp and frame of Foxglove sensor messages: prost skips the other fields
// (the point or pixel data) without copying them.
macro_rules! stamp_and_frame {
    ($name:ident, $frame_tag:literal) => {
        #[derive(Clone, PartialEq, prost::Message)]
        struct $name {
            #[prost(message, optional, tag = "1")]
            timestamp: Option<foxglove::Timestamp>,
            #[prost(string, tag = $frame_tag)]
            frame_id: String,
        }
    };
}
stamp_and_frame!(PointCloudHead, "2");
stamp_and_frame!(CompressedImageHead, "4");
stamp_and_frame!(RawImageHead, "7");

/// Just the header of a ROS 2 sensor message (CDR decoding stops after it).
#[derive(Debug, Deserialize)]
struct Ros2Head {
    header: ros2::Header,
}

fn stamp_and_frame(
    kind: SchemaKind,
    dialect: Dialect,
    data: &[u8],
) -> Result<(Stamp, String), String> {
    fn fox<T: prost::Message + Default>(schema: &'static str, data: &[u8]) -> Result<T, String> {
        foxglove::decode::<T>(schema, data).map_err(|e| e.to_string())
    }
    match dialect {
        Dialect::Ros2 => {
            let head: Ros2Head = ros2::decode(data).map_err(|e| e.to_string())?;
            Ok((head.header.stamp.stamp(), head.header.frame_id))
        }
        Dialect::FoxgloveProtobuf => {
            let (schema, timestamp, frame_id) = match kind {
                SchemaKind::PointCloud => {
                    let m: PointCloudHead = fox("foxglove.PointCloud", data)?;
                    ("foxglove.PointCloud", m.timestamp, m.frame_id)
                }
                SchemaKind::CompressedImage => {
                    let m: CompressedImageHead = fox("foxglove.CompressedImage", data)?;
                    ("foxglove.CompressedImage", m.timestamp, m.frame_id)
                }
                SchemaKind::RawImage => {
                    let m: RawImageHead = fox("foxglove.RawImage", data)?;
                    ("foxglove.RawImage", m.timestamp, m.frame_id)
                }
                _ => return Err("not a sensor message".into()),
            };
            let stamp = foxglove::stamp(schema, timestamp.as_ref()).map_err(|e| e.to_string())?;
            Ok((stamp, frame_id))
        }
    }
}

/// Groups the inputs into drives: a rosbag2 directory (it holds `metadata.yaml`) is one
/// drive made of its `.mcap` files in name order; any other directory contributes each
/// of its `.mcap` files as a drive of its own; a file is a drive. A sidecar —
/// `<name>.<tag>.mcap` next to `<name>.mcap`, e.g. `drive.superpixels.mcap` with class
/// maps computed offline — joins the drive of `<name>.mcap` (found next to it even when
/// only the drive is named) instead of being a drive of its own.
pub fn drive_groups(inputs: &[PathBuf]) -> Result<Vec<Vec<PathBuf>>, IngestError> {
    let mut groups: Vec<Vec<PathBuf>> = Vec::new();
    for input in inputs {
        let files = mcap_files(std::slice::from_ref(input))?;
        if input.is_dir() && input.join("metadata.yaml").is_file() {
            groups.push(files);
        } else {
            for file in files {
                if sidecar_base(&file).is_some_and(|base| base.is_file()) {
                    continue; // joins its base drive below
                }
                let mut group = vec![file.clone()];
                group.extend(sidecars_of(&file));
                groups.push(group);
            }
        }
    }
    for group in &mut groups {
        let mut seen = std::collections::BTreeSet::new();
        group.retain(|f| seen.insert(f.clone()));
    }
    Ok(groups)
}

/// `dir/<name>.mcap` for a sidecar `dir/<name>.<tag>.mcap`.
fn sidecar_base(file: &Path) -> Option<PathBuf> {
    let stem = file.file_stem()?.to_str()?; // <name>.<tag>
    let (name, tag) = stem.rsplit_once('.')?;
    (!name.is_empty() && !tag.is_empty()).then(|| file.with_file_name(format!("{name}.mcap")))
}

/// Sidecars next to `file` (`<stem>.<tag>.mcap`), in name order.
fn sidecars_of(file: &Path) -> Vec<PathBuf> {
    let (Some(dir), Some(stem)) = (file.parent(), file.file_stem().and_then(|s| s.to_str())) else {
        return Vec::new();
    };
    let dir = if dir.as_os_str().is_empty() {
        Path::new(".")
    } else {
        dir
    };
    let prefix = format!("{stem}.");
    let mut found: Vec<PathBuf> = std::fs::read_dir(dir)
        .map(|entries| {
            entries
                .filter_map(|e| e.ok().map(|e| e.path()))
                .filter(|p| {
                    p.extension().is_some_and(|e| e == "mcap")
                        && p.file_name()
                            .and_then(|n| n.to_str())
                            .is_some_and(|n| n.starts_with(&prefix) && n.len() > prefix.len() + 5)
                })
                .map(|p| file.with_file_name(p.file_name().unwrap_or_default()))
                .collect()
        })
        .unwrap_or_default();
    found.sort();
    found
}

/// All `.mcap` files named or inside the named directories, sorted per directory.
pub fn mcap_files(inputs: &[PathBuf]) -> Result<Vec<PathBuf>, IngestError> {
    let mut files = Vec::new();
    for input in inputs {
        if input.is_dir() {
            let io = |source| IngestError::Io {
                path: input.clone(),
                source,
            };
            let mut found: Vec<PathBuf> = std::fs::read_dir(input)
                .map_err(io)?
                .filter_map(|e| e.ok().map(|e| e.path()))
                .filter(|p| p.extension().is_some_and(|e| e == "mcap"))
                .collect();
            found.sort();
            files.extend(found);
        } else {
            files.push(input.clone());
        }
    }
    if files.is_empty() {
        return Err(IngestError::NoFiles);
    }
    Ok(files)
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
    /// Indexes the files of one drive, in one pass per file.
    pub fn open(files: &[PathBuf], config: &IngestConfig) -> Result<Drive, IngestError> {
        Self::open_with_progress(files, config, |_, _| {})
    }

    /// [`Drive::open`], reporting `(bytes indexed, bytes of this drive)` as it goes.
    pub fn open_with_progress(
        files: &[PathBuf],
        config: &IngestConfig,
        mut progress: impl FnMut(u64, u64),
    ) -> Result<Drive, IngestError> {
        if files.is_empty() {
            return Err(IngestError::NoFiles);
        }
        let mut topics: BTreeMap<String, TopicData> = BTreeMap::new();
        let mut tf = TransformTree::new((config.tf_tolerance_ms * 1e6) as i64);
        let mut skipped = SkipReport::default();
        let mut opened: Vec<McapFile> = Vec::with_capacity(files.len());
        let total_bytes: u64 = files
            .iter()
            .map(|f| std::fs::metadata(f).map_or(0, |m| m.len()))
            .sum();
        for (file_index, path) in files.iter().enumerate() {
            let mut visit = |m: MessageRef<'_>| {
                index_message(
                    file_index as u32,
                    path,
                    m,
                    &mut topics,
                    &mut tf,
                    &mut skipped,
                )
            };
            let _span = tracing::info_span!("index", file = %path.display()).entered();
            let before: u64 = opened.iter().map(McapFile::len).sum();
            let drive_bytes = total_bytes;
            let file = McapFile::scan_with_progress(path, &mut visit, |d, _| {
                progress(before + d, drive_bytes)
            })?;
            tracing::debug!(
                bytes = file.len(),
                chunks_damaged = file.damage.len(),
                "indexed"
            );
            for damage in &file.damage {
                let kind = match damage {
                    Damage::Truncated { .. } => "file truncated",
                    Damage::NoSummary { .. } => "file without summary",
                    Damage::BadChunk { .. } => "unreadable chunk",
                    Damage::BadRecord { .. } => "corrupt record",
                    Damage::MissingMessages { .. } => "messages lost to damage",
                };
                skipped.add(kind, || format!("{}: {damage}", path.display()));
            }
            opened.push(file);
        }
        let frozen_edges = tf.freeze_constant_edges();
        for t in topics.values_mut() {
            drop_stamps_far_from_log_time(t, files, &mut skipped);
            for repeated in sort_frames(&mut t.frames) {
                skipped.add(format!("repeated stamp: {}", t.channel.topic), || {
                    format!(
                        "{}: {} at {}: repeats the stamp of an earlier message; the first is kept",
                        file_name(files, repeated.file),
                        t.channel.topic,
                        repeated.stamp
                    )
                });
            }
        }

        for (kind, entry) in &skipped.entries {
            let lost = [
                "file truncated",
                "unreadable chunk",
                "corrupt record",
                "messages lost to damage",
            ]
            .contains(&kind.as_str());
            if lost {
                tracing::error!(kind = %kind, count = entry.count, first = %entry.first, "data lost");
            } else {
                tracing::warn!(kind = %kind, count = entry.count, first = %entry.first, "messages skipped");
            }
        }
        let channels: Vec<&ChannelInfo> = topics.values().map(|t| &t.channel).collect();
        let counts = |topic: &str| topics.get(topic).map_or(0, |t| t.count);
        let roles = discover::assign_roles(&channels, &counts, config);
        let role_of = |topic: &str| {
            roles
                .iter()
                .find(|(t, _)| t == topic)
                .map_or(Role::Ignored("unknown".into()), |(_, r)| r.clone())
        };

        let channel_summaries = topics
            .values()
            .map(|t| {
                let span_nanos = match (t.frames.first(), t.frames.last()) {
                    (Some(a), Some(b)) if t.frames.len() > 1 => b.stamp.nanos_since(a.stamp),
                    _ => t.last_log.saturating_sub(t.first_log) as i64,
                };
                ChannelSummary {
                    topic: t.channel.topic.clone(),
                    role: role_of(&t.channel.topic),
                    schema: t.channel.schema_name().to_string(),
                    schema_encoding: t
                        .channel
                        .schema
                        .as_ref()
                        .map_or(String::new(), |s| s.encoding.clone()),
                    message_encoding: t.channel.message_encoding.clone(),
                    message_count: t.count,
                    rate_hz: (span_nanos > 0 && t.count > 1)
                        .then(|| (t.count - 1) as f64 / (span_nanos as f64 * 1e-9)),
                }
            })
            .collect();

        let mut lidar = None;
        for t in topics.values() {
            if role_of(&t.channel.topic) == Role::Lidar
                && let Some((_, dialect)) = t.kind
            {
                lidar = Some(LidarStream {
                    topic: t.channel.topic.clone(),
                    frame_id: t.frame_id.clone().unwrap_or_default(),
                    dialect,
                    sweeps: t.frames.clone(),
                });
            }
        }

        let mut cameras = Vec::new();
        for t in topics.values() {
            if role_of(&t.channel.topic) != Role::Image {
                continue;
            }
            let Some((image_kind, dialect)) = t.kind else {
                continue;
            };
            let namespace = discover::camera_namespace(&t.channel.topic);
            let frame_id = t.frame_id.clone().unwrap_or_default();
            let calibration = topics
                .values()
                .filter(|c| role_of(&c.channel.topic) == Role::Calibration)
                .find(|c| discover::camera_namespace(&c.channel.topic) == namespace)
                .or_else(|| {
                    topics
                        .values()
                        .filter(|c| role_of(&c.channel.topic) == Role::Calibration)
                        .find(|c| {
                            c.calibrations
                                .first()
                                .is_some_and(|k| k.frame_id == frame_id)
                        })
                });
            let superpixels = topics
                .values()
                .filter(|c| role_of(&c.channel.topic) == Role::Superpixels)
                .find(|c| discover::camera_namespace(&c.channel.topic) == namespace);
            cameras.push(CameraStream {
                name: namespace
                    .rsplit('/')
                    .next()
                    .unwrap_or(namespace)
                    .to_string(),
                image_topic: t.channel.topic.clone(),
                image_kind,
                dialect,
                frame_id,
                calibration_topic: calibration.map(|c| c.channel.topic.clone()),
                calibrations: calibration
                    .map(|c| c.calibrations.clone())
                    .unwrap_or_default(),
                frames: t.frames.clone(),
                superpixel_topic: superpixels.map(|s| s.channel.topic.clone()),
                superpixel_kind: superpixels.and_then(|s| s.kind.map(|k| k.0)),
                superpixels: superpixels.map(|s| s.frames.clone()).unwrap_or_default(),
            });
        }
        cameras.sort_by(|a, b| a.name.cmp(&b.name));

        let ego_frame = config.ego_frame.clone().or_else(|| {
            [
                "base_link",
                "ego",
                "ego_vehicle",
                "vehicle",
                "base_footprint",
            ]
            .iter()
            .find(|f| tf.contains(f))
            .map(|f| f.to_string())
        });
        let map_frame = config
            .map_frame
            .clone()
            .or_else(|| ego_frame.as_deref().and_then(|e| tf.root_of(e).ok()));

        Ok(Drive {
            files: opened,
            channels: channel_summaries,
            lidar,
            cameras,
            tf,
            frozen_edges,
            map_frame,
            ego_frame,
            skipped,
            config: config.clone(),
        })
    }

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
                        problems.push(format!("{topic}: frame `{frame}` has no transform to `{ego}`"));
                    }
                }
            }
            _ if self.tf.frames().is_empty() => problems.push(
                "no transforms: no readable /tf or /tf_static message, so no ego pose and no \
                 sensor extrinsics"
                    .to_string(),
            ),
            _ => problems.push(format!(
                "no ego frame (tried base_link, ego, ego_vehicle, vehicle, base_footprint) in the transforms; frames: {}",
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

fn index_message(
    file: u32,
    path: &Path,
    m: MessageRef<'_>,
    topics: &mut BTreeMap<String, TopicData>,
    tf: &mut TransformTree,
    skipped: &mut SkipReport,
) {
    let topic = topics
        .entry(m.channel.topic.clone())
        .or_insert_with(|| TopicData {
            channel: m.channel.clone(),
            kind: discover::schema_kind(m.channel),
            count: 0,
            frame_id: None,
            frames: Vec::new(),
            frame_logs: Vec::new(),
            calibrations: Vec::new(),
            first_log: m.log_time,
            last_log: m.log_time,
        });
    topic.count += 1;
    topic.first_log = topic.first_log.min(m.log_time);
    topic.last_log = topic.last_log.max(m.log_time);
    let Some((kind, dialect)) = topic.kind else {
        return;
    };
    let where_ = |stamp: Option<Stamp>| match stamp {
        Some(s) => format!("{}: {} at {s}", path.display(), m.channel.topic),
        None => format!(
            "{}: {} (log time {})",
            path.display(),
            m.channel.topic,
            m.log_time
        ),
    };
    match kind {
        SchemaKind::PointCloud | SchemaKind::CompressedImage | SchemaKind::RawImage => {
            match stamp_and_frame(kind, dialect, m.data) {
                Ok((stamp, frame_id)) if stamp.nanos() > 0 => {
                    topic.frame_id.get_or_insert(frame_id);
                    topic.frames.push(FrameRef {
                        stamp,
                        file,
                        loc: m.loc,
                    });
                    topic.frame_logs.push(m.log_time);
                }
                Ok(_) => skipped.add(format!("zero stamp: {}", m.channel.topic), || where_(None)),
                Err(e) => skipped.add(format!("undecodable: {}", m.channel.topic), || {
                    format!("{}: {e}", where_(None))
                }),
            }
        }
        SchemaKind::Calibration => {
            let decoded = match dialect {
                Dialect::Ros2 => ros2::decode(m.data)
                    .map_err(crate::decode::DecodeError::from)
                    .and_then(|c| ros2::camera_info(&c)),
                Dialect::FoxgloveProtobuf => foxglove::decode("foxglove.CameraCalibration", m.data)
                    .and_then(|c| foxglove::camera_calibration(&c)),
            };
            match decoded {
                Ok(calibration) => {
                    topic.frame_id.get_or_insert(calibration.frame_id.clone());
                    let same = topic.calibrations.last().is_some_and(|last| {
                        last.k == calibration.k
                            && last.distortion == calibration.distortion
                            && (last.width, last.height) == (calibration.width, calibration.height)
                    });
                    if !same {
                        topic.calibrations.push(calibration);
                    }
                }
                Err(e) => skipped.add(format!("bad calibration: {}", m.channel.topic), || {
                    format!("{}: {e}", where_(None))
                }),
            }
        }
        SchemaKind::FrameTransform | SchemaKind::FrameTransforms | SchemaKind::TfMessage => {
            let is_static = m.channel.topic.ends_with("tf_static");
            let transforms = match kind {
                SchemaKind::TfMessage => match ros2::decode::<ros2::TfMessage>(m.data) {
                    Ok(msg) => ros2::transforms(&msg, is_static),
                    Err(e) => vec![Err(e.into())],
                },
                SchemaKind::FrameTransform => {
                    vec![
                        foxglove::decode::<foxglove::FrameTransform>(
                            "foxglove.FrameTransform",
                            m.data,
                        )
                        .and_then(|t| foxglove::frame_transform(&t, is_static)),
                    ]
                }
                _ => match foxglove::decode::<foxglove::FrameTransforms>(
                    "foxglove.FrameTransforms",
                    m.data,
                ) {
                    Ok(msg) => msg
                        .transforms
                        .iter()
                        .map(|t| foxglove::frame_transform(t, is_static))
                        .collect(),
                    Err(e) => vec![Err(e)],
                },
            };
            for transform in transforms {
                match transform {
                    Ok(t) => {
                        let stamp = t.stamp;
                        if let Err(e) = tf.insert(t) {
                            skipped.add(format!("rejected transform: {}", m.channel.topic), || {
                                format!("{}: {e}", where_(Some(stamp)))
                            });
                        }
                    }
                    Err(e) => skipped.add(format!("bad transform: {}", m.channel.topic), || {
                        format!("{}: {e}", where_(None))
                    }),
                }
            }
        }
    }
}

/// Sorts a topic's frames by stamp and drops repeated stamps; returns the dropped ones.
fn sort_frames(frames: &mut Vec<FrameRef>) -> Vec<FrameRef> {
    frames.sort_by_key(|f| (f.stamp, f.file, f.loc));
    let mut repeated = Vec::new();
    let mut kept: Vec<FrameRef> = Vec::with_capacity(frames.len());
    for f in frames.drain(..) {
        if kept.last().is_some_and(|k| k.stamp == f.stamp) {
            repeated.push(f);
        } else {
            kept.push(f);
        }
    }
    *frames = kept;
    repeated
}

/// How far a sensor stamp may stray from its channel's usual stamp-to-log-time offset.
/// Recorder latency, buffering and the nuScenes converter's keyframe log times stay far
/// below it; a sensor clock that was never synchronised (seconds since boot) or a
/// clock jump does not.
pub const STAMP_LOG_TOLERANCE_NANOS: i64 = 10_000_000_000;

fn file_name(files: &[PathBuf], file: u32) -> String {
    files
        .get(file as usize)
        .map_or_else(|| "?".to_string(), |p| p.display().to_string())
}

/// Drops (and counts, as `stamp far from log time: <topic>`) the frames whose sensor
/// stamp is more than [`STAMP_LOG_TOLERANCE_NANOS`] off the channel's median
/// stamp-to-log-time offset. A channel whose every stamp is offset alike (a replayed bag,
/// an unsynchronised but steady sensor clock) keeps everything.
fn drop_stamps_far_from_log_time(t: &mut TopicData, files: &[PathBuf], skipped: &mut SkipReport) {
    let logs = std::mem::take(&mut t.frame_logs);
    if logs.len() != t.frames.len() || t.frames.is_empty() {
        return;
    }
    let offsets: Vec<i128> = t
        .frames
        .iter()
        .zip(&logs)
        .map(|(f, log)| i128::from(f.stamp.nanos()) - i128::from(*log))
        .collect();
    let mut sorted = offsets.clone();
    sorted.sort_unstable();
    let median = sorted[sorted.len() / 2];
    let mut keep = Vec::with_capacity(t.frames.len());
    for ((frame, log), offset) in t.frames.iter().zip(&logs).zip(&offsets) {
        if (offset - median).abs() <= i128::from(STAMP_LOG_TOLERANCE_NANOS) {
            keep.push(*frame);
            continue;
        }
        skipped.add(
            format!("stamp far from log time: {}", t.channel.topic),
            || {
                format!(
                    "{}: {} at {} (log time {log}): the stamp is {:.3} s off the channel's usual \
                 stamp-to-log-time offset ({:.3} s); the message is skipped",
                    file_name(files, frame.file),
                    t.channel.topic,
                    frame.stamp,
                    (offset - median) as f64 * 1e-9,
                    median as f64 * 1e-9,
                )
            },
        );
    }
    t.frames = keep;
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
}

/// A sensor message that could not be read or decoded, with where it is.
#[derive(Debug, thiserror::Error)]
pub enum ReadError {
    /// The file could not deliver the message.
    #[error(transparent)]
    Source(#[from] SourceError),
    /// The message did not decode.
    #[error("{file}: {topic} at {stamp}: {reason}")]
    Decode {
        /// The file.
        file: String,
        /// The topic.
        topic: String,
        /// The frame's stamp.
        stamp: Stamp,
        /// What failed.
        reason: String,
    },
}

impl Drive {
    /// A [`ReadError::Decode`] naming the file, topic and stamp of `frame`.
    pub(crate) fn decode_error(
        &self,
        frame: &FrameRef,
        topic: &str,
        reason: impl std::fmt::Display,
    ) -> ReadError {
        ReadError::Decode {
            file: self
                .files
                .get(frame.file as usize)
                .map_or_else(|| self.file_list(), |f| f.path().display().to_string()),
            topic: topic.to_string(),
            stamp: frame.stamp,
            reason: reason.to_string(),
        }
    }

    /// Decodes image `frame` of `camera` (its colour image with `Target::Rgb`; pass a
    /// frame of `camera.superpixels` with `Target::Mono` for its class map).
    pub fn read_image(
        &self,
        camera: &CameraStream,
        frame: &FrameRef,
        target: crate::decode::image::Target,
        cache: &mut crate::source::ChunkCache,
    ) -> Result<superflow_schemas::sensor::Image, ReadError> {
        use crate::decode::image;
        let message = self.read_raw(frame, cache)?;
        let topic = message.channel.topic.clone();
        let kind = discover::schema_kind(message.channel);
        let decoded = match kind {
            Some((SchemaKind::CompressedImage, Dialect::Ros2)) => ros2::decode(message.data)
                .map_err(|e| e.to_string())
                .and_then(|m| image::decode_ros2_compressed(&m, target).map_err(|e| e.to_string())),
            Some((SchemaKind::RawImage, Dialect::Ros2)) => ros2::decode(message.data)
                .map_err(|e| e.to_string())
                .and_then(|m| image::decode_ros2_raw(&m, target).map_err(|e| e.to_string())),
            Some((SchemaKind::CompressedImage, Dialect::FoxgloveProtobuf)) => {
                foxglove::decode("foxglove.CompressedImage", message.data)
                    .map_err(|e| e.to_string())
                    .and_then(|m| {
                        image::decode_foxglove_compressed(&m, target).map_err(|e| e.to_string())
                    })
            }
            Some((SchemaKind::RawImage, Dialect::FoxgloveProtobuf)) => {
                foxglove::decode("foxglove.RawImage", message.data)
                    .map_err(|e| e.to_string())
                    .and_then(|m| image::decode_foxglove_raw(&m, target).map_err(|e| e.to_string()))
            }
            _ => Err(format!(
                "schema `{}` is not an image",
                message.channel.schema_name()
            )),
        };
        decoded.map_err(|reason| {
            self.decode_error(frame, &topic, format!("{} ({reason})", camera.name))
        })
    }
}

impl Drive {
    /// Decodes LiDAR sweep `frame` (non-finite points are dropped and counted in the
    /// result).
    pub fn read_sweep(
        &self,
        frame: &FrameRef,
        cache: &mut crate::source::ChunkCache,
    ) -> Result<crate::decode::points::DecodedCloud, ReadError> {
        let message = self.read_raw(frame, cache)?;
        let topic = message.channel.topic.clone();
        crate::decode::points::decode_message(&message, None)
            .map_err(|e| self.decode_error(frame, &topic, e))
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::source::MessageLoc;
    use nalgebra::Isometry3;
    use superflow_schemas::sensor::StampedTransform;

    fn frame(stamp: i64, index: u32) -> FrameRef {
        FrameRef {
            stamp: Stamp::from_nanos(stamp),
            file: 0,
            loc: MessageLoc::Chunk { chunk: 0, index },
        }
    }

    fn topic(frames: &[(i64, u64)]) -> TopicData {
        TopicData {
            channel: ChannelInfo {
                id: 1,
                topic: "/lidar".into(),
                schema: None,
                message_encoding: "cdr".into(),
                metadata: BTreeMap::new(),
            },
            kind: None,
            count: frames.len() as u64,
            frame_id: None,
            frames: frames
                .iter()
                .enumerate()
                .map(|(i, (s, _))| frame(*s, i as u32))
                .collect(),
            frame_logs: frames.iter().map(|(_, l)| *l).collect(),
            calibrations: Vec::new(),
            first_log: 0,
            last_log: 0,
        }
    }

    #[test]
    fn repeated_stamps_are_returned_with_where_they_are() {
        let mut frames = vec![frame(30, 0), frame(10, 1), frame(30, 2), frame(20, 3)];
        let repeated = sort_frames(&mut frames);
        assert_eq!(
            frames.iter().map(|f| f.stamp.nanos()).collect::<Vec<_>>(),
            [10, 20, 30]
        );
        assert_eq!(repeated, [frame(30, 2)]);
    }

    #[test]
    fn a_stamp_far_from_its_log_time_is_skipped_and_counted() {
        let files = [PathBuf::from("drive.mcap")];
        let s = 1_000_000_000i64;
        // Latency 60 ms, one message stamped by a clock since boot, one 1 s late.
        let mut t = topic(&[
            (1_700_000_000 * s, (1_700_000_000 * s + 60_000_000) as u64),
            (1_234 * s, (1_700_000_000 * s + 110_000_000) as u64),
            (
                1_700_000_000 * s + 100_000_000,
                (1_700_000_000 * s + 160_000_000) as u64,
            ),
            (
                1_700_000_000 * s + 150_000_000,
                (1_700_000_001 * s + 210_000_000) as u64,
            ),
        ]);
        let mut skipped = SkipReport::default();
        drop_stamps_far_from_log_time(&mut t, &files, &mut skipped);
        assert_eq!(t.frames.len(), 3);
        assert!(t.frames.iter().all(|f| f.stamp.nanos() > 1_234 * s));
        let entry = &skipped.entries["stamp far from log time: /lidar"];
        assert_eq!(entry.count, 1);
        assert!(
            entry.first.contains("drive.mcap: /lidar at ")
                && entry.first.contains("off the channel's usual"),
            "{}",
            entry.first
        );
    }

    #[test]
    fn a_steady_offset_between_stamps_and_log_times_is_kept() {
        // A replayed bag: stamps from the original drive, log times from today.
        let files = [PathBuf::from("replay.mcap")];
        let mut t = topic(&[
            (1_500_000_000_000_000_000, 1_700_000_000_000_000_000),
            (1_500_000_000_100_000_000, 1_700_000_000_100_000_000),
        ]);
        let mut skipped = SkipReport::default();
        drop_stamps_far_from_log_time(&mut t, &files, &mut skipped);
        assert_eq!(t.frames.len(), 2);
        assert_eq!(skipped.total(), 0);
    }

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
