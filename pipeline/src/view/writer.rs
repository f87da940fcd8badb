//! The MCAP writer of every view file: Foxglove's protobuf schemas (from the `foxglove`
//! crate's descriptors, so Foxglove recognises each message with no plugin), channels
//! declared on first use, zstd chunks, metadata records.

use foxglove::messages::{FrameTransform, Quaternion, Timestamp, Vector3};
use nalgebra::Isometry3;
use std::collections::{BTreeMap, HashMap};
use std::fs::File;
use std::io::BufWriter;
use std::path::{Path, PathBuf};
use superflow_schemas::Stamp;

/// Writing a view file failed.
#[derive(Debug, thiserror::Error)]
pub enum ViewError {
    /// The file could not be written.
    #[error("{path}: {source}")]
    Io {
        /// The file.
        path: PathBuf,
        /// What failed.
        #[source]
        source: std::io::Error,
    },
    /// The MCAP writer failed.
    #[error("{path}: {source}")]
    Mcap {
        /// The file.
        path: PathBuf,
        /// What failed.
        #[source]
        source: mcap::McapError,
    },
    /// An image could not be encoded as PNG.
    #[error("{path}: {camera} at {stamp}: {source}")]
    Png {
        /// The file.
        path: PathBuf,
        /// The camera.
        camera: String,
        /// The frame's stamp.
        stamp: Stamp,
        /// What failed.
        #[source]
        source: png::EncodingError,
    },
    /// A stamp Foxglove's `Timestamp` cannot hold (before 1970 or past 2106).
    #[error("{path}: stamp {stamp} is out of the range of Foxglove's timestamps")]
    Stamp {
        /// The file.
        path: PathBuf,
        /// The stamp.
        stamp: Stamp,
    },
    /// A Foxglove message type without a schema (a build of the `foxglove` crate without
    /// its descriptors).
    #[error("the Foxglove message type {0} has no schema in this build")]
    NoSchema(&'static str),
    /// Columns of a cloud of unequal lengths.
    #[error("{path}: field `{field}` of `{topic}` has {got} values for {points} points")]
    FieldLength {
        /// The file.
        path: PathBuf,
        /// The topic.
        topic: String,
        /// The field.
        field: String,
        /// Its values.
        got: usize,
        /// The points.
        points: usize,
    },
}

/// An MCAP file of Foxglove messages: [`write`](Self::write) them, then
/// [`finish`](Self::finish).
pub struct ViewWriter {
    path: PathBuf,
    writer: mcap::Writer<BufWriter<File>>,
    schemas: HashMap<&'static str, u16>,
    channels: HashMap<String, u16>,
    messages: u64,
}

impl std::fmt::Debug for ViewWriter {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.debug_struct("ViewWriter")
            .field("path", &self.path)
            .field("messages", &self.messages)
            .finish_non_exhaustive()
    }
}

impl ViewWriter {
    /// Creates `path` (replacing a file there); `library` names the writer in the header.
    pub fn create(path: &Path, library: &str) -> Result<Self, ViewError> {
        let file = File::create(path).map_err(|source| ViewError::Io {
            path: path.to_path_buf(),
            source,
        })?;
        let writer = mcap::WriteOptions::new()
            .profile("")
            .library(library)
            .compression(Some(mcap::Compression::Zstd))
            .create(BufWriter::new(file))
            .map_err(|source| ViewError::Mcap {
                path: path.to_path_buf(),
                source,
            })?;
        Ok(Self {
            path: path.to_path_buf(),
            writer,
            schemas: HashMap::new(),
            channels: HashMap::new(),
            messages: 0,
        })
    }

    /// The file.
    pub fn path(&self) -> &Path {
        &self.path
    }

    /// Messages written so far.
    pub fn messages(&self) -> u64 {
        self.messages
    }

    fn mcap_error(&self, source: mcap::McapError) -> ViewError {
        ViewError::Mcap {
            path: self.path.clone(),
            source,
        }
    }

    /// `stamp` as Foxglove's `Timestamp`.
    pub fn timestamp(&self, stamp: Stamp) -> Result<Timestamp, ViewError> {
        let (sec, nanosec) = stamp.to_sec_nanosec();
        u32::try_from(sec)
            .ok()
            .and_then(|sec| Timestamp::new_checked(sec, nanosec))
            .ok_or(ViewError::Stamp {
                path: self.path.clone(),
                stamp,
            })
    }

    /// The channel of `topic` for message type `T`, declared on first use.
    fn channel<T: foxglove::Encode>(&mut self, topic: &str) -> Result<u16, ViewError> {
        if let Some(id) = self.channels.get(topic) {
            return Ok(*id);
        }
        let type_name = std::any::type_name::<T>();
        let schema_id = match self.schemas.get(type_name) {
            Some(id) => *id,
            None => {
                let schema = T::get_schema().ok_or(ViewError::NoSchema(type_name))?;
                let id = self
                    .writer
                    .add_schema(&schema.name, &schema.encoding, &schema.data)
                    .map_err(|e| self.mcap_error(e))?;
                self.schemas.insert(type_name, id);
                id
            }
        };
        let id = self
            .writer
            .add_channel(schema_id, topic, "protobuf", &BTreeMap::new())
            .map_err(|e| self.mcap_error(e))?;
        self.channels.insert(topic.to_string(), id);
        Ok(id)
    }

    /// Writes `message` on `topic`, logged at `stamp`.
    pub fn write<T: foxglove::Encode + prost::Message>(
        &mut self,
        topic: &str,
        stamp: Stamp,
        message: &T,
    ) -> Result<(), ViewError> {
        let channel_id = self.channel::<T>(topic)?;
        let time = u64::try_from(stamp.nanos()).unwrap_or(0);
        self.writer
            .write_to_known_channel(
                &mcap::records::MessageHeader {
                    channel_id,
                    sequence: 0,
                    log_time: time,
                    publish_time: time,
                },
                &message.encode_to_vec(),
            )
            .map_err(|e| self.mcap_error(e))?;
        self.messages += 1;
        Ok(())
    }

    /// Writes a metadata record `name` of `entries`.
    pub fn metadata(
        &mut self,
        name: &str,
        entries: BTreeMap<String, String>,
    ) -> Result<(), ViewError> {
        self.writer
            .write_metadata(&mcap::records::Metadata {
                name: name.to_string(),
                metadata: entries,
            })
            .map_err(|e| self.mcap_error(e))
    }

    /// A field-length error of `topic` in this file.
    pub(super) fn field_length(
        &self,
        topic: &str,
        field: &str,
        got: usize,
        points: usize,
    ) -> ViewError {
        ViewError::FieldLength {
            path: self.path.clone(),
            topic: topic.to_string(),
            field: field.to_string(),
            got,
            points,
        }
    }

    /// Writes the summary and index and closes the file; returns the messages written.
    pub fn finish(mut self) -> Result<u64, ViewError> {
        self.writer.finish().map_err(|e| self.mcap_error(e))?;
        Ok(self.messages)
    }
}

/// `parent_from_child` as a Foxglove transform at `ts`.
pub fn frame_transform(
    ts: Timestamp,
    parent: &str,
    child: &str,
    parent_from_child: &Isometry3<f64>,
) -> FrameTransform {
    let t = parent_from_child.translation.vector;
    let q = parent_from_child.rotation.quaternion();
    FrameTransform {
        timestamp: Some(ts),
        parent_frame_id: parent.to_string(),
        child_frame_id: child.to_string(),
        translation: Some(Vector3 {
            x: t.x,
            y: t.y,
            z: t.z,
        }),
        rotation: Some(Quaternion {
            x: q.i,
            y: q.j,
            z: q.k,
            w: q.w,
        }),
    }
}
