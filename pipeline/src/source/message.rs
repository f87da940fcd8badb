//! The records a scan registers ([`SchemaInfo`], [`ChannelInfo`]) and the messages it
//! hands out ([`MessageRef`]), each found at a [`MessageLoc`].

use std::collections::BTreeMap;
use std::sync::Arc;

/// Where a message lives in its file.
#[derive(
    Debug, Clone, Copy, PartialEq, Eq, Hash, PartialOrd, Ord, serde::Serialize, serde::Deserialize,
)]
pub enum MessageLoc {
    /// The `index`-th message record of chunk number `chunk` (in file order).
    Chunk {
        /// Chunk number.
        chunk: u32,
        /// Message number inside the chunk.
        index: u32,
    },
    /// A message record outside any chunk, at this byte offset.
    Direct {
        /// Offset of the record's opcode.
        offset: u64,
    },
}

/// A schema record.
#[derive(Debug, Clone, PartialEq, Eq, serde::Serialize, serde::Deserialize)]
pub struct SchemaInfo {
    /// Schema id in the file.
    pub id: u16,
    /// Name (`sensor_msgs/msg/PointCloud2`, `foxglove.PointCloud`, ...).
    pub name: String,
    /// Encoding (`ros2msg`, `protobuf`, ...).
    pub encoding: String,
    /// The schema text or descriptor.
    pub data: Vec<u8>,
}

/// A channel record with its schema.
#[derive(Debug, Clone, PartialEq, Eq)]
pub struct ChannelInfo {
    /// Channel id in the file.
    pub id: u16,
    /// Topic.
    pub topic: String,
    /// The schema, if the channel has one.
    pub schema: Option<Arc<SchemaInfo>>,
    /// Message encoding (`cdr`, `protobuf`, `json`, ...).
    pub message_encoding: String,
    /// Channel metadata (rosbag2 QoS profiles, ...).
    pub metadata: BTreeMap<String, String>,
}

impl ChannelInfo {
    /// The schema name, or `""`.
    pub fn schema_name(&self) -> &str {
        self.schema.as_ref().map_or("", |s| s.name.as_str())
    }
}

/// One message handed out by a scan or a read.
#[derive(Debug, Clone, Copy)]
pub struct MessageRef<'a> {
    /// Its channel.
    pub channel: &'a ChannelInfo,
    /// Publisher sequence number.
    pub sequence: u32,
    /// Recorder log time (not the sensor stamp).
    pub log_time: u64,
    /// Publish time.
    pub publish_time: u64,
    /// The serialized message.
    pub data: &'a [u8],
    /// Where it lives.
    pub loc: MessageLoc,
}

impl<'a> MessageRef<'a> {
    /// The message of `header` on `channel`, its bytes `data`, found at `loc`.
    pub(super) fn new(
        channel: &'a ChannelInfo,
        header: &mcap::records::MessageHeader,
        data: &'a [u8],
        loc: MessageLoc,
    ) -> Self {
        Self {
            channel,
            sequence: header.sequence,
            log_time: header.log_time,
            publish_time: header.publish_time,
            data,
            loc,
        }
    }
}
