//! A drive's streams and how they are built from the indexed topics: the frames
//! ([`FrameRef`]), the stream types (LiDAR, cameras with their calibration and class maps,
//! label clouds, SLIC sidecars), the role of every channel and its summary, and the ego
//! and map frames.

use super::discover::{self, IngestConfig, Role};
use super::tf::TransformTree;
use crate::decode::{Dialect, SchemaKind};
use crate::source::ChannelInfo;
use crate::source::MessageLoc;
use serde::{Deserialize, Serialize};
use std::collections::BTreeMap;
use superflow_schemas::Stamp;
use superflow_schemas::sensor::CameraCalibration;

/// A sensor message located in the dataset.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub struct FrameRef {
    /// The sensor's own stamp (`header.stamp` / `timestamp`), never the log time.
    pub stamp: Stamp,
    /// Index of the file in [`Drive::files`](super::Drive::files).
    pub file: u32,
    /// Where the message is in that file.
    pub loc: MessageLoc,
}

/// The LiDAR stream.
#[derive(Debug, Clone, PartialEq)]
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

impl LidarStream {
    /// The sweep whose points time the cameras (`sample::timing`), with its number:
    /// the middle one; `None` without sweeps.
    pub fn timing_sweep(&self) -> Option<(usize, &FrameRef)> {
        let number = self.sweeps.len() / 2;
        self.sweeps.get(number).map(|frame| (number, frame))
    }
}

/// A point-cloud channel of a `<drive>.labels.mcap` sidecar: label clouds parallel to the
/// LiDAR's sweeps (same stamps, same point order), one per sweep. Which one labels the
/// LiDAR is decided when the labels are opened ([`super::labels::DriveLabels::open`]).
#[derive(Debug, Clone, PartialEq)]
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
#[derive(Debug, Clone, PartialEq)]
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
#[derive(Debug, Clone, PartialEq)]
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

/// What the index holds of one topic, over all files of the drive.
#[derive(Debug)]
pub(super) struct TopicData {
    pub channel: ChannelInfo,
    pub kind: Option<(SchemaKind, Dialect)>,
    pub count: u64,
    pub frame_id: Option<String>,
    pub frames: Vec<FrameRef>,
    /// Log time of each of `frames`, until the stamps are checked against them.
    pub frame_logs: Vec<u64>,
    pub calibrations: Vec<CameraCalibration>,
    pub first_log: u64,
    pub last_log: u64,
}

/// Ego frames tried, in order, when the configuration names none.
pub(super) const EGO_FRAMES: [&str; 5] = [
    "base_link",
    "ego",
    "ego_vehicle",
    "vehicle",
    "base_footprint",
];

/// The streams of a drive, assembled from its index.
pub(super) struct Streams {
    pub channels: Vec<ChannelSummary>,
    pub lidar: Option<LidarStream>,
    pub cameras: Vec<CameraStream>,
    pub label_clouds: Vec<LabelCloudStream>,
    pub ego_frame: Option<String>,
    pub map_frame: Option<String>,
}

/// The indexed topics with the role of each.
struct Roles<'a> {
    topics: &'a BTreeMap<String, TopicData>,
    roles: Vec<(String, Role)>,
}

impl Streams {
    /// Assigns roles to the channels of `topics` and builds the streams; `label_topics`
    /// (the point clouds of a labels sidecar) are label clouds.
    pub fn assemble(
        topics: &BTreeMap<String, TopicData>,
        label_topics: &BTreeMap<String, TopicData>,
        tf: &TransformTree,
        config: &IngestConfig,
    ) -> Streams {
        let channels: Vec<&ChannelInfo> = topics.values().map(|t| &t.channel).collect();
        let counts = |topic: &str| topics.get(topic).map_or(0, |t| t.count);
        let roles = Roles {
            topics,
            roles: discover::assign_roles(&channels, &counts, config),
        };
        let ego_frame = config.ego_frame.clone().or_else(|| {
            EGO_FRAMES
                .iter()
                .find(|f| tf.contains(f))
                .map(|f| f.to_string())
        });
        let map_frame = config
            .map_frame
            .clone()
            .or_else(|| ego_frame.as_deref().and_then(|e| tf.root_of(e).ok()));
        let mut channels = roles.channel_summaries();
        channels.extend(label_topics.values().map(|t| summary(t, Role::Labels)));
        channels.sort_by(|a, b| a.topic.cmp(&b.topic));
        Streams {
            channels,
            lidar: roles.lidar(),
            cameras: roles.cameras(),
            label_clouds: label_topics
                .values()
                .map(|t| LabelCloudStream {
                    topic: t.channel.topic.clone(),
                    lidar_topic: t
                        .channel
                        .metadata
                        .get(discover::LABELS_LIDAR_TOPIC_KEY)
                        .cloned(),
                    frames: t.frames.clone(),
                })
                .collect(),
            ego_frame,
            map_frame,
        }
    }
}

impl Roles<'_> {
    fn of(&self, topic: &str) -> Role {
        self.roles
            .iter()
            .find(|(t, _)| t == topic)
            .map_or(Role::Ignored("unknown".into()), |(_, r)| r.clone())
    }

    /// The topics of role `role`.
    fn with(&self, role: Role) -> impl Iterator<Item = &TopicData> {
        self.topics
            .values()
            .filter(move |t| self.of(&t.channel.topic) == role)
    }

    fn channel_summaries(&self) -> Vec<ChannelSummary> {
        self.topics
            .values()
            .map(|t| summary(t, self.of(&t.channel.topic)))
            .collect()
    }

    /// The LiDAR: the last decodable topic of role LiDAR.
    fn lidar(&self) -> Option<LidarStream> {
        self.with(Role::Lidar)
            .filter_map(|t| {
                let (_, dialect) = t.kind?;
                Some(LidarStream {
                    topic: t.channel.topic.clone(),
                    frame_id: t.frame_id.clone().unwrap_or_default(),
                    dialect,
                    sweeps: t.frames.clone(),
                })
            })
            .last()
    }

    /// Every camera, sorted by name.
    fn cameras(&self) -> Vec<CameraStream> {
        let mut cameras: Vec<CameraStream> = self
            .with(Role::Image)
            .filter_map(|t| self.camera(t))
            .collect();
        cameras.sort_by(|a, b| a.name.cmp(&b.name));
        cameras
    }

    /// The camera of image topic `t`, with the calibration of its namespace (else of its
    /// frame) and the class maps of its namespace.
    fn camera(&self, t: &TopicData) -> Option<CameraStream> {
        let (image_kind, dialect) = t.kind?;
        let namespace = discover::camera_namespace(&t.channel.topic);
        let frame_id = t.frame_id.clone().unwrap_or_default();
        let in_namespace =
            |c: &&TopicData| discover::camera_namespace(&c.channel.topic) == namespace;
        let calibration = self.with(Role::Calibration).find(in_namespace).or_else(|| {
            self.with(Role::Calibration).find(|c| {
                c.calibrations
                    .first()
                    .is_some_and(|k| k.frame_id == frame_id)
            })
        });
        let superpixels = self.with(Role::Superpixels).find(in_namespace);
        let slic = self.with(Role::SlicSuperpixels).find(|s| {
            s.channel.metadata.get(discover::SLIC_IMAGE_TOPIC_KEY) == Some(&t.channel.topic)
        });
        Some(CameraStream {
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
            slic: slic.map(|s| SlicStream {
                topic: s.channel.topic.clone(),
                settings: s
                    .channel
                    .metadata
                    .get(discover::SLIC_SETTINGS_KEY)
                    .cloned()
                    .unwrap_or_default(),
                frames: s.frames.clone(),
            }),
        })
    }
}

/// The summary of an indexed topic of role `role`.
fn summary(t: &TopicData, role: Role) -> ChannelSummary {
    let span_nanos = match (t.frames.first(), t.frames.last()) {
        (Some(a), Some(b)) if t.frames.len() > 1 => b.stamp.nanos_since(a.stamp),
        _ => t.last_log.saturating_sub(t.first_log) as i64,
    };
    ChannelSummary {
        topic: t.channel.topic.clone(),
        role,
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
}
