//! The damaged recordings of `recordings/damaged/`: a short drive
//! ([`DriveOptions::short`]) in both dialects, damaged the ways real recordings are
//! (`recordings/LAYOUTS.md`): cut short, a corrupt chunk, a calibration or the
//! `/tf` channel never recorded, sweeps with NaN and infinite points, and wrong sensor
//! stamps. Each is a pure function of the code, like the sample drives; next to each
//! file, `<name>.expected.json` (written by hand, not generated) states what the pipeline
//! must report, and `tests/tests/e2e/bad_inputs.rs` checks both.
//!
//! Byte-level damage (truncation, flipped bytes) is applied to the finished file;
//! message-level damage rewrites the file, message by message, with the writer settings
//! of its dialect.

use crate::dialect::Dialect;
use crate::error::{GenerateError, Result};
use crate::generate::generate_with;
use crate::options::DriveOptions;
use crate::out::McapOut;
use foxglove::messages::{PointCloud, Timestamp};
use prost::Message as _;
use std::collections::BTreeMap;
use superflow_schemas::ros2::{self, CompressedImage, PointCloud2, Ros2Time};

/// One damaged recording.
#[derive(Debug, Clone)]
pub struct DamagedFile {
    /// File name (`<dialect>_<damage>.mcap`).
    pub name: String,
    /// The damage, in words.
    pub damage: String,
    /// The MCAP bytes.
    pub bytes: Vec<u8>,
}

/// A stamp from a sensor clock that was never synchronised: 1234.5678 s after boot.
pub const SINCE_BOOT_NANOS: i64 = 1_234_567_800_000;

/// Every damaged recording, in name order of dialect then damage.
pub fn damaged_recordings() -> Result<Vec<DamagedFile>> {
    let mut out = Vec::new();
    for dialect in Dialect::ALL {
        let drive = generate_with(dialect, &DriveOptions::short())?;
        let parsed = Parsed::read(&drive.mcap)?;
        let d = dialect.name();
        let file = |damage: &str, what: &str, bytes: Vec<u8>| DamagedFile {
            name: format!("{d}_{damage}.mcap"),
            damage: what.to_string(),
            bytes,
        };

        let cut = drive.mcap.len() * 6 / 10;
        out.push(file(
            "truncated",
            &format!(
                "cut at byte {cut} of {} (60 %): no summary",
                drive.mcap.len()
            ),
            drive.mcap[..cut].to_vec(),
        ));

        let mut flipped = drive.mcap.clone();
        let middle = flipped.len() / 2;
        for b in &mut flipped[middle..middle + 64] {
            *b ^= 0x5A;
        }
        out.push(file(
            "flipped_chunk",
            &format!("64 bytes XOR 0x5A at byte {middle} (inside a chunk)"),
            flipped,
        ));

        let (no_calibration, what) = match dialect {
            Dialect::Foxglove => (
                parsed.rewrite(dialect, |topic, _, _| !topic.ends_with("/camera_info")),
                "every /CAM_*/camera_info channel absent",
            ),
            Dialect::Ros2 => (
                parsed.rewrite(dialect, |topic, _, _| topic != "/cam_front/camera_info"),
                "/cam_front/camera_info absent (the other camera keeps its calibration)",
            ),
        };
        out.push(file("no_calibration", what, no_calibration?));

        let what = match dialect {
            Dialect::Foxglove => "/tf absent: no ego pose and no extrinsics",
            Dialect::Ros2 => "/tf absent: no ego pose (/tf_static with the extrinsics is kept)",
        };
        out.push(file(
            "no_tf",
            what,
            parsed.rewrite(dialect, |topic, _, _| topic != "/tf")?,
        ));

        out.push(file(
            "nan_points",
            &nan_points_damage(dialect),
            nan_points(&parsed, dialect)?,
        ));

        let (bytes, what) = wrong_stamps(&parsed, dialect)?;
        out.push(file("wrong_stamps", &what, bytes));
    }
    out.sort_by(|a, b| a.name.cmp(&b.name));
    Ok(out)
}

/// Writes `recordings/damaged/`-style files into `dir`; returns what was written.
pub fn write_damaged(dir: &std::path::Path) -> Result<Vec<DamagedFile>> {
    std::fs::create_dir_all(dir).map_err(|e| GenerateError::io("creating", dir, e))?;
    let files = damaged_recordings()?;
    for f in &files {
        let path = dir.join(&f.name);
        std::fs::write(&path, &f.bytes).map_err(|e| GenerateError::io("writing", &path, e))?;
    }
    Ok(files)
}

/// Index of the LiDAR message among the LiDAR messages, if `topic` is the LiDAR.
fn lidar_topic(dialect: Dialect) -> &'static str {
    match dialect {
        Dialect::Foxglove => "/LIDAR_TOP",
        Dialect::Ros2 => crate::ros2::LIDAR_TOPIC,
    }
}

/// Overwrites coordinate `axis` (0 = x, 2 = z) of the points `which` selects.
fn poison(data: &mut [u8], step: usize, axis: usize, value: f32, which: impl Fn(usize) -> bool) {
    for (i, point) in data.chunks_exact_mut(step).enumerate() {
        if which(i) {
            point[axis * 4..axis * 4 + 4].copy_from_slice(&value.to_le_bytes());
        }
    }
}

/// Which sweeps (in message order) [`nan_points`] poisons, per dialect: `(every 10th
/// point x = NaN, points 0..20 z = +inf, every point NaN)`. The short drive's keyframes
/// are sweeps 0, 10 and 20; keyframe 1's dense cloud adds sweeps 9 and 8, keyframe 2's
/// 19 and 18.
fn poisoned_sweeps(dialect: Dialect) -> (usize, usize, usize) {
    match dialect {
        // NaN in keyframe 0's t+dt frame, inf in keyframe 0 itself, and keyframe 2 (also
        // keyframe 1's t+dt frame) without a single finite point.
        Dialect::Foxglove => (10, 0, 20),
        // NaN as above, inf in keyframe 1's dense cloud, and an empty sweep in keyframe
        // 2's dense cloud.
        Dialect::Ros2 => (10, 9, 19),
    }
}

/// What [`nan_points`] does to `dialect`, in words.
fn nan_points_damage(dialect: Dialect) -> String {
    let (nan, inf, all) = poisoned_sweeps(dialect);
    format!(
        "sweep {nan}: every 10th point has x = NaN; sweep {inf}: points 0..20 have z = +inf; \
         sweep {all}: every point NaN"
    )
}

fn nan_points(parsed: &Parsed, dialect: Dialect) -> Result<Vec<u8>> {
    let lidar = lidar_topic(dialect);
    let mut sweep = 0usize;
    let mut error = None;
    let bytes = parsed.rewrite(dialect, |topic, _, data| {
        if topic != lidar {
            return true;
        }
        let k = sweep;
        sweep += 1;
        let (nan, inf, all) = poisoned_sweeps(dialect);
        let damage = |points: &mut Vec<u8>, step: usize| {
            if k == nan {
                poison(points, step, 0, f32::NAN, |i| i % 10 == 0);
            } else if k == inf {
                poison(points, step, 2, f32::INFINITY, |i| i < 20);
            } else if k == all {
                poison(points, step, 0, f32::NAN, |_| true);
            }
        };
        let edited = match dialect {
            Dialect::Foxglove => PointCloud::decode(data.as_slice())
                .map_err(GenerateError::from)
                .map(|mut cloud| {
                    let mut points = cloud.data.to_vec();
                    damage(&mut points, cloud.point_stride as usize);
                    cloud.data = points.into();
                    cloud.encode_to_vec()
                }),
            Dialect::Ros2 => ros2::decode::<PointCloud2>(data)
                .map_err(GenerateError::from)
                .and_then(|mut cloud| {
                    damage(&mut cloud.data, cloud.point_step as usize);
                    cloud.is_dense = ![nan, inf, all].contains(&k);
                    Ok(ros2::encode(&cloud)?)
                }),
        };
        match edited {
            Ok(e) => *data = e,
            Err(e) => error = Some(e),
        }
        true
    })?;
    match error {
        Some(e) => Err(GenerateError::Damaging {
            doing: "poisoning a sweep",
            topic: lidar.to_string(),
            source: Box::new(e),
        }),
        None => Ok(bytes),
    }
}

fn wrong_stamps(parsed: &Parsed, dialect: Dialect) -> Result<(Vec<u8>, String)> {
    let lidar = lidar_topic(dialect);
    let mut sweep = 0usize;
    let mut image = 0usize;
    let mut previous_image_stamp = None;
    let mut error: Option<(String, GenerateError)> = None;
    let mut edit = |topic: &str, data: &mut Vec<u8>| -> Result<()> {
        match dialect {
            Dialect::Foxglove if topic == lidar => {
                let k = sweep;
                sweep += 1;
                let mut cloud = PointCloud::decode(data.as_slice())?;
                match k {
                    5 => cloud.timestamp = None,
                    13 => {
                        cloud.timestamp = Timestamp::new_checked(
                            (SINCE_BOOT_NANOS / 1_000_000_000) as u32,
                            (SINCE_BOOT_NANOS % 1_000_000_000) as u32,
                        )
                    }
                    _ => return Ok(()),
                }
                *data = cloud.encode_to_vec();
            }
            Dialect::Ros2 if topic == lidar => {
                let k = sweep;
                sweep += 1;
                let mut cloud: PointCloud2 = ros2::decode(data)?;
                cloud.header.stamp = match k {
                    5 | 6 => Ros2Time::default(),
                    13 => Ros2Time::from_nanos(SINCE_BOOT_NANOS).ok_or(
                        GenerateError::StampOutOfRange {
                            format: "ROS 2",
                            stamp: superflow_schemas::Stamp::from_nanos(SINCE_BOOT_NANOS),
                        },
                    )?,
                    _ => return Ok(()),
                };
                *data = ros2::encode(&cloud)?;
            }
            Dialect::Ros2 if topic == "/cam_front/image_raw/compressed" => {
                let k = image;
                image += 1;
                let mut msg: CompressedImage = ros2::decode(data)?;
                if k == 7
                    && let Some(stamp) = previous_image_stamp
                {
                    msg.header.stamp = stamp;
                    *data = ros2::encode(&msg)?;
                }
                previous_image_stamp = Some(msg.header.stamp);
            }
            _ => {}
        }
        Ok(())
    };
    let mut bytes = parsed.rewrite_ordered(
        dialect,
        |topic, _, data| {
            if let Err(e) = edit(topic, data) {
                error.get_or_insert((topic.to_string(), e));
            }
            true
        },
        dialect == Dialect::Foxglove,
    );
    if let Some((topic, e)) = error {
        bytes = Err(GenerateError::Damaging {
            doing: "restamping a message",
            topic,
            source: Box::new(e),
        });
    }
    let what = match dialect {
        Dialect::Foxglove => {
            "sweep 5 without timestamp; sweep 13 stamped by an unsynchronised clock \
             (1234.5678 s since boot); messages written newest first within each 0.5 s \
             block (log times out of order)"
        }
        Dialect::Ros2 => {
            "sweeps 5 and 6 with header.stamp 0; sweep 13 stamped by an unsynchronised \
             clock (1234.5678 s since boot); /cam_front image 7 repeats the stamp of image 6"
        }
    };
    Ok((bytes?, what.to_string()))
}

/// A channel as read back.
#[derive(Debug, Clone)]
struct ChannelRecord {
    id: u16,
    topic: String,
    schema: (String, String, Vec<u8>),
    message_encoding: String,
    metadata: BTreeMap<String, String>,
}

/// A message as read back.
#[derive(Debug, Clone)]
struct MessageRecord {
    channel: u16,
    log_time: u64,
    publish_time: u64,
    data: Vec<u8>,
}

/// An intact MCAP file, record by record.
#[derive(Debug)]
struct Parsed {
    profile: String,
    channels: Vec<ChannelRecord>,
    messages: Vec<MessageRecord>,
    metadata: Vec<mcap::records::Metadata>,
}

impl Parsed {
    fn read(bytes: &[u8]) -> Result<Self> {
        use mcap::records::Record;
        let mut profile = String::new();
        let mut schemas: BTreeMap<u16, (String, String, Vec<u8>)> = BTreeMap::new();
        let mut channels = Vec::new();
        let mut messages = Vec::new();
        let mut metadata = Vec::new();
        for record in mcap::read::ChunkFlattener::new(bytes)? {
            match record? {
                Record::Header(h) => profile = h.profile,
                Record::Schema { header, data } => {
                    schemas.insert(header.id, (header.name, header.encoding, data.into_owned()));
                }
                Record::Channel(c) => channels.push(ChannelRecord {
                    id: c.id,
                    topic: c.topic,
                    schema: schemas
                        .get(&c.schema_id)
                        .cloned()
                        .ok_or(GenerateError::Malformed {
                            what: "channel before its schema",
                            id: c.schema_id,
                        })?,
                    message_encoding: c.message_encoding,
                    metadata: c.metadata,
                }),
                Record::Message { header, data } => messages.push(MessageRecord {
                    channel: header.channel_id,
                    log_time: header.log_time,
                    publish_time: header.publish_time,
                    data: data.into_owned(),
                }),
                Record::Metadata(m) => metadata.push(m),
                _ => {}
            }
        }
        Ok(Self {
            profile,
            channels,
            messages,
            metadata,
        })
    }

    /// The file again with the dialect's writer settings; `keep(topic, log_time, data)`
    /// drops a message by returning false and may edit it. A channel left without
    /// messages is left out, as a recorder that never saw the topic would.
    fn rewrite(
        &self,
        dialect: Dialect,
        keep: impl FnMut(&str, u64, &mut Vec<u8>) -> bool,
    ) -> Result<Vec<u8>> {
        self.rewrite_ordered(dialect, keep, false)
    }

    /// [`Parsed::rewrite`]; with `newest_first_blocks`, the messages of each 0.5 s of
    /// log time are written newest first, so the file is not sorted by log time.
    fn rewrite_ordered(
        &self,
        dialect: Dialect,
        mut keep: impl FnMut(&str, u64, &mut Vec<u8>) -> bool,
        newest_first_blocks: bool,
    ) -> Result<Vec<u8>> {
        let topics: BTreeMap<u16, &ChannelRecord> =
            self.channels.iter().map(|c| (c.id, c)).collect();
        let mut kept: Vec<MessageRecord> = Vec::new();
        for m in &self.messages {
            let topic = &topics
                .get(&m.channel)
                .ok_or(GenerateError::Malformed {
                    what: "message without channel",
                    id: m.channel,
                })?
                .topic;
            let mut m = m.clone();
            if keep(topic, m.log_time, &mut m.data) {
                kept.push(m);
            }
        }
        let mut out = McapOut::default();
        out.set_chunk_size(DriveOptions::short().chunk_size);
        out.set_sorted(!newest_first_blocks);
        let mut handles = BTreeMap::new();
        for c in &self.channels {
            if kept.iter().any(|m| m.channel == c.id) {
                let (name, encoding, data) = &c.schema;
                handles.insert(
                    c.id,
                    out.channel(
                        &c.topic,
                        "",
                        (name, encoding, data),
                        &c.message_encoding,
                        c.metadata.clone(),
                    ),
                );
            }
        }
        if newest_first_blocks {
            // Stable: ties keep their order.
            kept.sort_by_key(|m| (m.log_time / 500_000_000, std::cmp::Reverse(m.log_time)));
        }
        for m in kept {
            out.message(
                handles[&m.channel],
                m.log_time as i64,
                m.publish_time as i64,
                m.data,
            );
        }
        for record in &self.metadata {
            let entries: Vec<(&str, &str)> = record
                .metadata
                .iter()
                .map(|(k, v)| (k.as_str(), v.as_str()))
                .collect();
            out.metadata(&record.name, &entries);
        }
        let compression = match dialect {
            Dialect::Foxglove => mcap::Compression::Lz4,
            Dialect::Ros2 => mcap::Compression::Zstd,
        };
        Ok(out.finish(&self.profile, Some(compression))?.0)
    }
}
