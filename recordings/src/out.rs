//! Collects messages of every channel, then writes them in log-time order into an MCAP.
//! The dialect writers use it, and so do tests that build small files of their own.

use crate::truth::ChannelTruth;
use std::collections::BTreeMap;
use std::io::Cursor;

/// One message waiting to be written.
#[derive(Debug)]
struct Pending {
    channel: usize,
    log_time: u64,
    publish_time: u64,
    data: Vec<u8>,
}

/// A channel declared by a dialect writer.
#[derive(Debug)]
struct ChannelSpec {
    truth: ChannelTruth,
    schema_data: Vec<u8>,
    metadata: BTreeMap<String, String>,
}

/// Messages and channels of one file, written at [`McapOut::finish`].
#[derive(Debug, Default)]
pub struct McapOut {
    channels: Vec<ChannelSpec>,
    messages: Vec<Pending>,
    metadata: Vec<mcap::records::Metadata>,
    chunk_size: Option<u64>,
    unsorted: bool,
}

impl McapOut {
    /// Declares a channel; returns its handle.
    pub fn channel(
        &mut self,
        topic: &str,
        role: &str,
        schema: (&str, &str, &[u8]),
        message_encoding: &str,
        metadata: BTreeMap<String, String>,
    ) -> usize {
        let (schema_name, schema_encoding, schema_data) = schema;
        self.channels.push(ChannelSpec {
            truth: ChannelTruth {
                topic: topic.to_string(),
                schema_name: schema_name.to_string(),
                schema_encoding: schema_encoding.to_string(),
                message_encoding: message_encoding.to_string(),
                message_count: 0,
                role: role.to_string(),
            },
            schema_data: schema_data.to_vec(),
            metadata,
        });
        self.channels.len() - 1
    }

    /// Queues a message.
    pub fn message(&mut self, channel: usize, log_time: i64, publish_time: i64, data: Vec<u8>) {
        self.channels[channel].truth.message_count += 1;
        self.messages.push(Pending {
            channel,
            log_time: log_time as u64,
            publish_time: publish_time as u64,
            data,
        });
    }

    /// Queues a metadata record.
    pub fn metadata(&mut self, name: &str, entries: &[(&str, &str)]) {
        self.metadata.push(mcap::records::Metadata {
            name: name.to_string(),
            metadata: entries
                .iter()
                .map(|(k, v)| (k.to_string(), v.to_string()))
                .collect(),
        });
    }

    /// Sets the chunk size (512 KiB unless set).
    pub fn set_chunk_size(&mut self, bytes: u64) {
        self.chunk_size = Some(bytes);
    }

    /// Whether [`McapOut::finish`] sorts the messages by log time (the default) or writes
    /// them in the order queued (as converters that append blocks do).
    pub fn set_sorted(&mut self, sorted: bool) {
        self.unsorted = !sorted;
    }

    /// Writes everything, messages sorted by log time (ties in the order queued).
    pub fn finish(
        mut self,
        profile: &str,
        compression: Option<mcap::Compression>,
    ) -> crate::error::Result<(Vec<u8>, Vec<ChannelTruth>)> {
        let options = mcap::WriteOptions::new()
            .profile(profile)
            .library(format!(
                "superflow-recordings/{}",
                crate::sample_drive::GENERATOR_VERSION
            ))
            .compression(compression)
            .chunk_size(Some(self.chunk_size.unwrap_or(512 * 1024)));
        let mut writer = options.create(Cursor::new(Vec::new()))?;
        let mut schema_ids: BTreeMap<(String, String), u16> = BTreeMap::new();
        let mut channel_ids = Vec::with_capacity(self.channels.len());
        for spec in &self.channels {
            let key = (
                spec.truth.schema_name.clone(),
                spec.truth.schema_encoding.clone(),
            );
            let schema_id = match schema_ids.get(&key) {
                Some(id) => *id,
                None => {
                    let id = writer.add_schema(&key.0, &key.1, &spec.schema_data)?;
                    schema_ids.insert(key, id);
                    id
                }
            };
            channel_ids.push(writer.add_channel(
                schema_id,
                &spec.truth.topic,
                &spec.truth.message_encoding,
                &spec.metadata,
            )?);
        }
        if !self.unsorted {
            self.messages.sort_by_key(|m| m.log_time);
        }
        let mut sequences = vec![0u32; self.channels.len()];
        for m in &self.messages {
            sequences[m.channel] += 1;
            writer.write_to_known_channel(
                &mcap::records::MessageHeader {
                    channel_id: channel_ids[m.channel],
                    sequence: sequences[m.channel],
                    log_time: m.log_time,
                    publish_time: m.publish_time,
                },
                &m.data,
            )?;
        }
        for record in &self.metadata {
            writer.write_metadata(record)?;
        }
        writer.finish()?;
        let bytes = writer.into_inner().into_inner();
        Ok((bytes, self.channels.into_iter().map(|c| c.truth).collect()))
    }
}
