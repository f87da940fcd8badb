//! One drive ([`Drive`]) and the building of its index ([`Drive::open`]): the index of
//! each file ([`FileIndex`]: every LiDAR sweep and camera frame with its sensor stamp and
//! location, every transform, every calibration), read from the [`IndexCache`] or made
//! by one pass over the file, joined into the drive's: the transforms into its
//! [`TransformTree`], then the frames checked (repeated stamps, stamps far from their log
//! time) and what was skipped logged. A
//! drive then answers sensor checks and keyframes here, and reads one sensor message in
//! [`super::read`].

use super::discover::IngestConfig;
use super::error::IngestError;
use super::file_index::{FileIndex, place, same_calibration};
use super::index_cache::IndexCache;
use super::skips::{DamageKind, SkipReport};
use super::streams::{
    CameraStream, ChannelSummary, EGO_FRAMES, FrameRef, LabelCloudStream, LidarStream, Streams,
    TopicData, nearest,
};
use super::tf::TransformTree;
use crate::decode::{SchemaKind, schema_kind};
use crate::source::{McapFile, SourceError};
use std::collections::BTreeMap;
use std::path::{Path, PathBuf};
use superflow_schemas::Stamp;

/// How far a sensor stamp may stray from its channel's usual stamp-to-log-time offset.
/// Recorder latency, buffering and the nuScenes converter's keyframe log times stay far
/// below it; a sensor clock that was never synchronised (seconds since boot) or a
/// clock jump does not.
pub const STAMP_LOG_TOLERANCE_NANOS: i64 = 10_000_000_000;

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
    /// The fingerprints of the files ([`McapFile::fingerprint`]) hashed together in the
    /// drive's order, when every file has one and the index cache is on: what the
    /// cache's entries of the whole drive (its camera scan) are keyed by.
    pub fingerprint: Option<u128>,
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

/// The index of a drive while the indexes of its files are joined.
struct Index {
    topics: BTreeMap<String, TopicData>,
    /// The point-cloud topics of `<drive>.labels.mcap` sidecars, apart from `topics`: a
    /// label cloud may repeat the LiDAR's topic name.
    label_topics: BTreeMap<String, TopicData>,
    tf: TransformTree,
    skipped: SkipReport,
}

/// How the index of a file was had.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum IndexedBy {
    /// Read from the index cache.
    Cache,
    /// Scanned (and stored in the cache, if there is one).
    Scan,
    /// Scanned, and not cacheable: no footer and summary to fingerprint it by.
    ScanUncacheable,
}

/// One file indexed by [`index_file`].
pub(super) struct IndexedFile {
    pub file: McapFile,
    pub index: FileIndex,
    pub by: IndexedBy,
    /// Its fingerprint, when the index cache is on and it has one.
    pub fingerprint: Option<u128>,
}

/// Opens and indexes one file: from `cache` when it holds the file's index, by a scan
/// otherwise (then stored there). `progress` gets the bytes read so far.
pub(super) fn index_file(
    path: &Path,
    cache: Option<&IndexCache>,
    mut progress: impl FnMut(u64),
) -> Result<IndexedFile, SourceError> {
    let file = McapFile::open(path)?;
    let indexed = |(file, index), by, fingerprint| IndexedFile {
        file,
        index,
        by,
        fingerprint,
    };
    let Some(cache) = cache else {
        // Taken now, so that a copy replacing the file later is known for one.
        file.content_digest()?;
        return Ok(indexed(
            FileIndex::scan(file, progress)?,
            IndexedBy::Scan,
            None,
        ));
    };
    let Some(fingerprint) = file.fingerprint()? else {
        tracing::debug!(file = %path.display(), "no footer and summary to fingerprint: indexed at every opening, not cached");
        return Ok(indexed(
            FileIndex::scan(file, progress)?,
            IndexedBy::ScanUncacheable,
            None,
        ));
    };
    if let Some(index) = cache.load(&file, fingerprint) {
        progress(file.len());
        let file = file.restore(&index.scanned);
        return Ok(indexed((file, index), IndexedBy::Cache, Some(fingerprint)));
    }
    let (file, index) = FileIndex::scan(file, progress)?;
    cache.store(fingerprint, &index);
    Ok(indexed((file, index), IndexedBy::Scan, Some(fingerprint)))
}

/// The fingerprint of a drive from those of its files, in order: `None` when one has
/// none.
fn drive_fingerprint(files: &[Option<u128>]) -> Option<u128> {
    let mut hash = xxhash_rust::xxh3::Xxh3::new();
    hash.update(&(files.len() as u64).to_le_bytes());
    for file in files {
        hash.update(&(*file)?.to_le_bytes());
    }
    Some(hash.digest128())
}

impl Drive {
    /// Indexes the files of one drive, in one pass per file (or from the index cache of
    /// `config`).
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
        crate::source::HandlePool::global().set_limit(config.max_open_files());
        config.configure_remote();
        let cache = config.index_cache();
        if let Some(cache) = &cache {
            cache.prepare()?;
        }
        let total_bytes: u64 = files
            .iter()
            .map(|f| crate::source::size_of(f).unwrap_or(0))
            .sum();
        let mut indexed = Vec::with_capacity(files.len());
        let mut before = 0u64;
        for path in files {
            let file = index_file(path, cache.as_ref(), |done| {
                progress(before + done, total_bytes)
            })?;
            before += file.file.len();
            indexed.push(file);
        }
        if let Some(cache) = &cache {
            cache.upkeep_if_grown();
        }
        Ok(Drive::join(indexed, config))
    }

    /// The drive of these files and their indexes, in the drive's order.
    pub(super) fn join(indexed: Vec<IndexedFile>, config: &IngestConfig) -> Drive {
        let mut index = Index {
            topics: BTreeMap::new(),
            label_topics: BTreeMap::new(),
            tf: TransformTree::new((config.tf_tolerance_ms * 1e6) as i64),
            skipped: SkipReport::default(),
        };
        let mut files = Vec::with_capacity(indexed.len());
        let fingerprints: Vec<Option<u128>> = indexed.iter().map(|f| f.fingerprint).collect();
        for (number, file) in indexed.into_iter().enumerate() {
            index.add_file(number as u32, &file.file, file.index);
            files.push(file.file);
        }
        let paths: Vec<PathBuf> = files.iter().map(|f| f.path().to_path_buf()).collect();
        let frozen_edges = index.tf.freeze_constant_edges();
        index.check_frames(&paths);
        index.log_skips();
        let streams = Streams::assemble(&index.topics, &index.label_topics, &index.tf, config);
        // The plan reads the sweep that times the cameras next: a file in an object store
        // keeps it from its scan, rather than fetch it again.
        let timing = streams.lidar.as_ref().and_then(|l| l.timing_sweep());
        for (number, file) in files.iter().enumerate() {
            let keep = timing.filter(|(_, f)| f.file as usize == number);
            file.release_scan(keep.map(|(_, f)| f.loc));
        }
        Drive {
            files,
            channels: streams.channels,
            lidar: streams.lidar,
            cameras: streams.cameras,
            label_clouds: streams.label_clouds,
            tf: index.tf,
            frozen_edges,
            map_frame: streams.map_frame,
            ego_frame: streams.ego_frame,
            skipped: index.skipped,
            config: config.clone(),
            fingerprint: drive_fingerprint(&fingerprints),
        }
    }
}

impl Index {
    /// Adds the index of file number `number` of the drive: its topics (the point clouds
    /// of a labels sidecar to `label_topics`), its transforms in file order and its skips.
    fn add_file(&mut self, number: u32, file: &McapFile, index: FileIndex) {
        let labels_sidecar = super::files::is_labels_sidecar(file.path());
        for (name, facts) in index.topics {
            let Some(channel) = file.channel(facts.channel) else {
                continue; // a channel is always restored with its file's index
            };
            let kind = schema_kind(channel);
            let topics = match kind {
                Some((SchemaKind::PointCloud, _)) if labels_sidecar => &mut self.label_topics,
                _ => &mut self.topics,
            };
            let topic = topics.entry(name).or_insert_with(|| TopicData {
                channel: (**channel).clone(),
                kind,
                count: 0,
                frame_id: None,
                frames: Vec::new(),
                frame_logs: Vec::new(),
                calibrations: Vec::new(),
                first_log: facts.first_log,
                last_log: facts.last_log,
            });
            topic.count += facts.count;
            topic.first_log = topic.first_log.min(facts.first_log);
            topic.last_log = topic.last_log.max(facts.last_log);
            if let Some(frame_id) = facts.frame_id {
                topic.frame_id.get_or_insert(frame_id);
            }
            topic
                .frames
                .extend(facts.frames.iter().map(|&(stamp, loc)| FrameRef {
                    stamp,
                    file: number,
                    loc,
                }));
            topic.frame_logs.extend(facts.frame_logs);
            for calibration in facts.calibrations {
                if !topic
                    .calibrations
                    .last()
                    .is_some_and(|last| same_calibration(last, &calibration))
                {
                    topic.calibrations.push(calibration);
                }
            }
        }
        for (kind, entry) in index.skipped.entries {
            self.skipped
                .entries
                .entry(kind)
                .and_modify(|e| e.count += entry.count)
                .or_insert(entry);
        }
        for (topic, transform) in index.transforms {
            let stamp = transform.stamp;
            if let Err(e) = self.tf.insert(transform) {
                self.skipped
                    .add(format!("rejected transform: {topic}"), || {
                        format!("{}: {e}", place(file.path(), &topic, Some(stamp), 0))
                    });
            }
        }
    }

    /// Drops each topic's frames whose stamp is far from its log time, then sorts them
    /// and drops repeated stamps (counting both).
    fn check_frames(&mut self, files: &[PathBuf]) {
        for t in self
            .topics
            .values_mut()
            .chain(self.label_topics.values_mut())
        {
            drop_stamps_far_from_log_time(t, files, &mut self.skipped);
            for repeated in sort_frames(&mut t.frames) {
                self.skipped
                    .add(format!("repeated stamp: {}", t.channel.topic), || {
                        format!(
                            "{}: {} at {}: repeats the stamp of an earlier message; the first is kept",
                            file_name(files, repeated.file),
                            t.channel.topic,
                            repeated.stamp
                        )
                    });
            }
        }
    }

    /// Logs every kind of skip: lost data as an error, skipped messages as a warning.
    fn log_skips(&self) {
        for (kind, entry) in &self.skipped.entries {
            if DamageKind::is_data_loss(kind) {
                tracing::error!(kind = %kind, count = entry.count, first = %entry.first, "data lost");
            } else {
                tracing::warn!(kind = %kind, count = entry.count, first = %entry.first, "messages skipped");
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

#[cfg(test)]
mod tests {
    use super::*;
    use crate::source::{ChannelInfo, MessageLoc};
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

    /// A drive of no files with the transform tree `tf` (for the sensor checks).
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
            fingerprint: None,
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
