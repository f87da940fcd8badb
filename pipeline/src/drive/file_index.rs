//! What indexing learns from one file ([`FileIndex`]): its topics with every sensor
//! frame's stamp and location, its calibrations, its transforms in file order, and what
//! it skipped. It depends on nothing but the file's bytes — not on the drive the file
//! belongs to, its other files or the configuration — so it can be stored
//! ([`super::index_cache`]) and files can be indexed in parallel; [`super::index`] joins
//! the indexes of a drive's files into its [`Drive`](super::Drive).

use super::heads::stamp_and_frame;
use super::skips::{DamageKind, SkipReport};
use crate::decode::{DecodeError, Dialect, SchemaKind, foxglove, ros2, schema_kind};
use crate::source::{McapFile, MessageLoc, MessageRef, ScannedFile, SourceError};
use serde::{Deserialize, Serialize};
use std::collections::BTreeMap;
use std::path::{Path, PathBuf};
use superflow_schemas::Stamp;
use superflow_schemas::sensor::{CameraCalibration, StampedTransform};

/// What indexing learned from one file.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub(super) struct FileIndex {
    /// The file's path when it was indexed: the skip reports name it.
    pub path: PathBuf,
    /// What the scan of the file itself learned (channels, chunks, damage).
    pub scanned: ScannedFile,
    /// Every topic, by name.
    pub topics: BTreeMap<String, TopicFacts>,
    /// Every transform, in file order, with its topic.
    pub transforms: Vec<(String, StampedTransform)>,
    /// Messages skipped and damage worked around.
    pub skipped: SkipReport,
}

/// One topic of one file.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub(super) struct TopicFacts {
    /// The id of the topic's (first) channel in the file.
    pub channel: u16,
    /// Messages on the topic.
    pub count: u64,
    /// The frame of its first frame or calibration.
    pub frame_id: Option<String>,
    /// Sensor frames (point clouds, images): stamp and location, in file order.
    pub frames: Vec<(Stamp, MessageLoc)>,
    /// The log time of each of `frames`.
    pub frame_logs: Vec<u64>,
    /// Calibrations, each differing from the one before.
    pub calibrations: Vec<CameraCalibration>,
    /// First and last log time.
    pub first_log: u64,
    pub last_log: u64,
}

impl FileIndex {
    /// Scans `file` (opened, not yet scanned) and indexes what it holds; `progress`
    /// gets the bytes read so far.
    pub fn scan(
        file: McapFile,
        mut progress: impl FnMut(u64),
    ) -> Result<(McapFile, FileIndex), SourceError> {
        let path = file.path().to_path_buf();
        let _span = tracing::info_span!("index", file = %path.display()).entered();
        let mut scan = Scan {
            path: &path,
            topics: BTreeMap::new(),
            kinds: BTreeMap::new(),
            transforms: Vec::new(),
            skipped: SkipReport::default(),
        };
        let file = file.scan_with_progress_opened(|m| scan.message(m), |done, _| progress(done))?;
        tracing::debug!(
            bytes = file.len(),
            chunks_damaged = file.damage.len(),
            "indexed"
        );
        for damage in &file.damage {
            scan.skipped.add(DamageKind::of(damage).as_str(), || {
                format!("{}: {damage}", path.display())
            });
        }
        let index = FileIndex {
            scanned: file.scanned(),
            topics: scan.topics,
            transforms: scan.transforms,
            skipped: scan.skipped,
            path,
        };
        Ok((file, index))
    }

    /// Checks an index read back from storage against the file it is said to be of (of
    /// `len` bytes): its scan facts ([`ScannedFile::fits`]) and every frame's location.
    pub fn fits(&self, len: u64) -> Result<(), String> {
        self.scanned.fits(len)?;
        let chunks = self.scanned.chunk_count();
        for (name, topic) in &self.topics {
            if topic.frame_logs.len() != topic.frames.len() {
                return Err(format!(
                    "topic {name}: frames and their log times differ in number"
                ));
            }
            for (_, loc) in &topic.frames {
                let inside = match *loc {
                    MessageLoc::Chunk { chunk, .. } => (chunk as usize) < chunks,
                    MessageLoc::Direct { offset } => {
                        offset >= 8 && offset.checked_add(9).is_some_and(|end| end <= len)
                    }
                };
                if !inside {
                    return Err(format!(
                        "topic {name}: a frame at {loc:?} is outside the file"
                    ));
                }
            }
        }
        Ok(())
    }

    /// This index for the same file found at `path`: its skip reports name `path`.
    pub fn moved_to(mut self, path: &Path) -> FileIndex {
        if self.path != path {
            let (old, new) = (self.path.display().to_string(), path.display().to_string());
            for entry in self.skipped.entries.values_mut() {
                entry.first = entry.first.replace(&old, &new);
            }
            self.path = path.to_path_buf();
        }
        self
    }
}

/// A file being indexed.
struct Scan<'a> {
    path: &'a Path,
    topics: BTreeMap<String, TopicFacts>,
    /// What each topic's (first) channel carries.
    kinds: BTreeMap<String, Option<(SchemaKind, Dialect)>>,
    transforms: Vec<(String, StampedTransform)>,
    skipped: SkipReport,
}

impl Scan<'_> {
    /// Counts a message on its topic and indexes what it holds: a sensor frame, a
    /// calibration or transforms.
    fn message(&mut self, m: MessageRef<'_>) {
        let topic_name = &m.channel.topic;
        let topic = self
            .topics
            .entry(topic_name.clone())
            .or_insert_with(|| TopicFacts {
                channel: m.channel.id,
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
        let kind = *self
            .kinds
            .entry(topic_name.clone())
            .or_insert_with(|| schema_kind(m.channel));
        let Some((kind, dialect)) = kind else {
            return;
        };
        let place = Place {
            path: self.path,
            m: &m,
        };
        match kind {
            SchemaKind::PointCloud | SchemaKind::CompressedImage | SchemaKind::RawImage => {
                topic.add_frame(&place, kind, dialect, &mut self.skipped)
            }
            SchemaKind::Calibration => topic.add_calibration(&place, dialect, &mut self.skipped),
            SchemaKind::FrameTransform | SchemaKind::FrameTransforms | SchemaKind::TfMessage => {
                let is_static = topic_name.ends_with("tf_static");
                for transform in decode_transforms(kind, m.data, is_static) {
                    match transform {
                        Ok(t) => self.transforms.push((topic_name.clone(), t)),
                        Err(e) => self
                            .skipped
                            .add(format!("bad transform: {topic_name}"), || {
                                format!("{}: {e}", place.at(None))
                            }),
                    }
                }
            }
        }
    }
}

/// A message being indexed, with its file.
struct Place<'a> {
    path: &'a Path,
    m: &'a MessageRef<'a>,
}

impl Place<'_> {
    /// `file: topic at stamp`, or `file: topic (log time t)` without a stamp.
    fn at(&self, stamp: Option<Stamp>) -> String {
        place(self.path, &self.m.channel.topic, stamp, self.m.log_time)
    }
}

/// `file: topic at stamp`, or `file: topic (log time t)` without a stamp.
pub(super) fn place(path: &Path, topic: &str, stamp: Option<Stamp>, log_time: u64) -> String {
    match stamp {
        Some(s) => format!("{}: {topic} at {s}", path.display()),
        None => format!("{}: {topic} (log time {log_time})", path.display()),
    }
}

impl TopicFacts {
    /// Indexes a LiDAR sweep or camera frame by its sensor stamp.
    fn add_frame(
        &mut self,
        msg: &Place<'_>,
        kind: SchemaKind,
        dialect: Dialect,
        skipped: &mut SkipReport,
    ) {
        let topic = &msg.m.channel.topic;
        match stamp_and_frame(kind, dialect, msg.m.data) {
            Ok((stamp, frame_id)) if stamp.nanos() > 0 => {
                self.frame_id.get_or_insert(frame_id);
                self.frames.push((stamp, msg.m.loc));
                self.frame_logs.push(msg.m.log_time);
            }
            Ok(_) => skipped.add(format!("zero stamp: {topic}"), || msg.at(None)),
            Err(e) => skipped.add(format!("undecodable: {topic}"), || {
                format!("{}: {e}", msg.at(None))
            }),
        }
    }

    /// Keeps a calibration unless it equals the previous one.
    fn add_calibration(&mut self, msg: &Place<'_>, dialect: Dialect, skipped: &mut SkipReport) {
        let decoded = match dialect {
            Dialect::Ros2 => ros2::decode(msg.m.data)
                .map_err(DecodeError::from)
                .and_then(|c| ros2::camera_info(&c)),
            Dialect::FoxgloveProtobuf => foxglove::decode("foxglove.CameraCalibration", msg.m.data)
                .and_then(|c| foxglove::camera_calibration(&c)),
        };
        match decoded {
            Ok(calibration) => {
                self.frame_id.get_or_insert(calibration.frame_id.clone());
                if !self
                    .calibrations
                    .last()
                    .is_some_and(|last| same_calibration(last, &calibration))
                {
                    self.calibrations.push(calibration);
                }
            }
            Err(e) => skipped.add(format!("bad calibration: {}", msg.m.channel.topic), || {
                format!("{}: {e}", msg.at(None))
            }),
        }
    }
}

/// Whether two calibrations are the same (a re-published one is kept once).
pub(super) fn same_calibration(a: &CameraCalibration, b: &CameraCalibration) -> bool {
    a.k == b.k && a.distortion == b.distortion && (a.width, a.height) == (b.width, b.height)
}

/// The transforms of a message of `kind` (a message that does not decode is one error).
fn decode_transforms(
    kind: SchemaKind,
    data: &[u8],
    is_static: bool,
) -> Vec<Result<StampedTransform, DecodeError>> {
    match kind {
        SchemaKind::TfMessage => match ros2::decode::<ros2::TfMessage>(data) {
            Ok(msg) => ros2::transforms(&msg, is_static),
            Err(e) => vec![Err(e.into())],
        },
        SchemaKind::FrameTransform => {
            vec![
                foxglove::decode::<foxglove::FrameTransform>("foxglove.FrameTransform", data)
                    .and_then(|t| foxglove::frame_transform(&t, is_static)),
            ]
        }
        _ => {
            match foxglove::decode::<foxglove::FrameTransforms>("foxglove.FrameTransforms", data) {
                Ok(msg) => msg
                    .transforms
                    .iter()
                    .map(|t| foxglove::frame_transform(t, is_static))
                    .collect(),
                Err(e) => vec![Err(e)],
            }
        }
    }
}
