//! Reading MCAP files with bounded memory.
//!
//! [`McapFile::scan`] makes one pass over a file, record by record, holding at most one
//! chunk in memory: it registers schemas and channels, hands every message to a visitor
//! together with its [`MessageLoc`], and notes damage (truncation, bad chunk CRCs,
//! undecodable records) instead of failing: a damaged region costs only the messages in
//! it. When the file has a summary, its chunk index is used to resynchronize after a
//! corrupt record and its statistics to count what was lost.
//!
//! [`McapFile::read_message`] later fetches one message by location through a
//! [`ChunkCache`] of a few decompressed chunks.

use mcap::records::{self, ChunkHeader, op};
use std::collections::{BTreeMap, HashMap, VecDeque};
use std::fs::File;
use std::os::unix::fs::FileExt;
use std::path::{Path, PathBuf};
use std::sync::Arc;

/// The 8 magic bytes at both ends of an MCAP file.
pub const MAGIC: &[u8; 8] = b"\x89MCAP0\r\n";
/// Largest chunk (uncompressed) or record accepted; a larger size is taken for corruption.
pub const MAX_RECORD_BYTES: u64 = 1 << 30;

/// A file that cannot be read at all.
#[derive(Debug, thiserror::Error)]
pub enum SourceError {
    /// Opening or reading failed.
    #[error("{path}: {source}")]
    Io {
        /// The file.
        path: PathBuf,
        /// The I/O error.
        source: std::io::Error,
    },
    /// The file does not start with the MCAP magic.
    #[error("{path}: not an MCAP file (bad magic bytes)")]
    NotMcap {
        /// The file.
        path: PathBuf,
    },
    /// A message location that this file does not have.
    #[error("{path}: no message at {loc:?}")]
    NoSuchMessage {
        /// The file.
        path: PathBuf,
        /// The location asked for.
        loc: MessageLoc,
    },
    /// A chunk that read fine during the scan fails now (file changed?).
    #[error("{path}: chunk at byte {offset}: {reason}")]
    Chunk {
        /// The file.
        path: PathBuf,
        /// Offset of the chunk record.
        offset: u64,
        /// What failed.
        reason: String,
    },
}

/// Where a message lives in its file.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Hash, PartialOrd, Ord)]
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
#[derive(Debug, Clone, PartialEq, Eq)]
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

/// Something wrong with a file that the scan worked around.
#[derive(Debug, Clone, PartialEq, Eq)]
pub enum Damage {
    /// The file ends early (no footer, or a record that runs past the end).
    Truncated {
        /// Byte offset where reading stopped.
        offset: u64,
        /// What was found there.
        reason: String,
    },
    /// The file has no summary section (or it is unreadable): no index to cross-check.
    NoSummary {
        /// Why.
        reason: String,
    },
    /// A chunk whose content could not be used (CRC mismatch, decompression failure).
    BadChunk {
        /// Offset of the chunk record.
        offset: u64,
        /// What failed.
        reason: String,
    },
    /// A record that could not be parsed; the scan resumed at `resumed_at` if possible.
    BadRecord {
        /// Offset of the record.
        offset: u64,
        /// What failed.
        reason: String,
        /// Where the scan resumed (the next indexed chunk), if anywhere.
        resumed_at: Option<u64>,
    },
    /// Fewer messages on a channel than the summary's statistics state.
    MissingMessages {
        /// The topic.
        topic: String,
        /// Per the statistics.
        expected: u64,
        /// Actually read.
        found: u64,
    },
}

impl std::fmt::Display for Damage {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        match self {
            Damage::Truncated { offset, reason } => {
                write!(f, "truncated at byte {offset}: {reason}")
            }
            Damage::NoSummary { reason } => write!(f, "no usable summary: {reason}"),
            Damage::BadChunk { offset, reason } => {
                write!(f, "chunk at byte {offset} skipped: {reason}")
            }
            Damage::BadRecord {
                offset,
                reason,
                resumed_at,
            } => {
                write!(f, "corrupt record at byte {offset}: {reason}")?;
                match resumed_at {
                    Some(at) => write!(f, "; resumed at the next indexed chunk, byte {at}"),
                    None => write!(f, "; nothing after it could be read"),
                }
            }
            Damage::MissingMessages {
                topic,
                expected,
                found,
            } => write!(f, "{topic}: {found} of {expected} messages readable"),
        }
    }
}

#[derive(Debug, Clone)]
struct ChunkLoc {
    offset: u64,
    record_len: u64,
}

/// An MCAP file after its scan: header, channels, chunk locations and damage.
#[derive(Debug)]
pub struct McapFile {
    path: PathBuf,
    file: File,
    len: u64,
    /// Header profile (`ros2`, `""`, ...).
    pub profile: String,
    /// Header library.
    pub library: String,
    schemas: HashMap<u16, Arc<SchemaInfo>>,
    channels: BTreeMap<u16, Arc<ChannelInfo>>,
    chunks: Vec<ChunkLoc>,
    /// What the scan had to work around.
    pub damage: Vec<Damage>,
    /// Messages read per channel id.
    pub message_counts: BTreeMap<u16, u64>,
}

/// The messages of one decompressed chunk: channel id, header, payload.
type ChunkMessages = Vec<(u16, records::MessageHeader, Vec<u8>)>;

struct Decoded {
    messages: ChunkMessages,
}

/// A few decompressed chunks, most recent last, for random access.
#[derive(Debug)]
pub struct ChunkCache {
    capacity: usize,
    entries: VecDeque<(PathBuf, CacheKey, Arc<ChunkMessages>)>,
}

impl ChunkCache {
    /// A cache holding at most `capacity` decompressed chunks (at least 1).
    pub fn new(capacity: usize) -> Self {
        Self {
            capacity: capacity.max(1),
            entries: VecDeque::new(),
        }
    }
}

impl std::fmt::Debug for Decoded {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        write!(f, "{} messages", self.messages.len())
    }
}

impl McapFile {
    /// The file's path.
    pub fn path(&self) -> &Path {
        &self.path
    }

    /// File size in bytes.
    pub fn len(&self) -> u64 {
        self.len
    }

    /// Whether the file is empty.
    pub fn is_empty(&self) -> bool {
        self.len == 0
    }

    /// Every channel, by id.
    pub fn channels(&self) -> impl Iterator<Item = &Arc<ChannelInfo>> {
        self.channels.values()
    }

    /// One channel.
    pub fn channel(&self, id: u16) -> Option<&Arc<ChannelInfo>> {
        self.channels.get(&id)
    }

    fn io(&self, source: std::io::Error) -> SourceError {
        SourceError::Io {
            path: self.path.clone(),
            source,
        }
    }

    fn read_exact_at(&self, offset: u64, len: u64) -> Result<Vec<u8>, SourceError> {
        let mut buf = vec![
            0u8;
            usize::try_from(len)
                .unwrap_or(usize::MAX)
                .min(MAX_RECORD_BYTES as usize)
        ];
        self.file
            .read_exact_at(&mut buf, offset)
            .map_err(|e| self.io(e))?;
        Ok(buf)
    }

    /// Scans `path` once, calling `visit` for every readable message in file order.
    pub fn scan(path: &Path, visit: impl FnMut(MessageRef<'_>)) -> Result<McapFile, SourceError> {
        Self::scan_with_progress(path, visit, |_, _| {})
    }

    /// [`McapFile::scan`], reporting `(bytes read, file size)` after every record.
    pub fn scan_with_progress(
        path: &Path,
        mut visit: impl FnMut(MessageRef<'_>),
        mut progress: impl FnMut(u64, u64),
    ) -> Result<McapFile, SourceError> {
        let io = |source| SourceError::Io {
            path: path.to_path_buf(),
            source,
        };
        let file = File::open(path).map_err(io)?;
        let len = file.metadata().map_err(io)?.len();
        let mut magic = [0u8; 8];
        if len < 8 || file.read_exact_at(&mut magic, 0).is_err() || &magic != MAGIC {
            return Err(SourceError::NotMcap {
                path: path.to_path_buf(),
            });
        }
        let mut this = McapFile {
            path: path.to_path_buf(),
            file,
            len,
            profile: String::new(),
            library: String::new(),
            schemas: HashMap::new(),
            channels: BTreeMap::new(),
            chunks: Vec::new(),
            damage: Vec::new(),
            message_counts: BTreeMap::new(),
        };
        let (summary, summary_damage) = match this.check_summary_framing() {
            Ok(()) => (this.read_summary(), None),
            Err(reason) => (None, Some(reason)),
        };
        // Chunk offsets from the summary's index: where to resume after a corrupt record.
        // Only offsets inside the file (a corrupt index pointing past its end made the
        // scan compute `len - pos` with `pos > len`: found by the fuzz target).
        let mut indexed_chunks: Vec<u64> = summary
            .as_ref()
            .map(|s| {
                s.chunk_indexes
                    .iter()
                    .map(|c| c.chunk_start_offset)
                    .filter(|offset| (8..len).contains(offset))
                    .collect()
            })
            .unwrap_or_default();
        indexed_chunks.sort_unstable();
        if let Some(summary) = &summary {
            for schema in summary.schemas.values() {
                this.add_schema(schema.id, &schema.name, &schema.encoding, &schema.data);
            }
            for channel in summary.channels.values() {
                this.add_channel(
                    channel.id,
                    channel.schema.as_ref().map_or(0, |s| s.id),
                    &channel.topic,
                    &channel.message_encoding,
                    &channel.metadata,
                );
            }
        }

        let mut pos = 8u64;
        loop {
            if pos == len {
                this.damage.push(Damage::Truncated {
                    offset: pos,
                    reason: "no footer".into(),
                });
                break;
            }
            if pos + 9 > len {
                this.damage.push(Damage::Truncated {
                    offset: pos,
                    reason: format!(
                        "{} stray bytes where a record header was expected",
                        len - pos
                    ),
                });
                break;
            }
            let mut head = [0u8; 9];
            this.file.read_exact_at(&mut head, pos).map_err(io)?;
            let opcode = head[0];
            let body_len = record_len(&head);
            let body_start = pos + 9;
            let plausible =
                (op::HEADER..=op::DATA_END).contains(&opcode) && body_len <= MAX_RECORD_BYTES;
            if !plausible || body_start + body_len > len {
                let reason = if plausible {
                    format!(
                        "record of {body_len} bytes runs past the end of the file ({len} bytes)"
                    )
                } else {
                    format!("opcode {opcode:#04x} with length {body_len}")
                };
                let resume = indexed_chunks.iter().copied().find(|o| *o > pos);
                if plausible && resume.is_none() {
                    this.damage.push(Damage::Truncated {
                        offset: pos,
                        reason,
                    });
                    break;
                }
                this.damage.push(Damage::BadRecord {
                    offset: pos,
                    reason,
                    resumed_at: resume,
                });
                match resume {
                    Some(next) => {
                        pos = next;
                        continue;
                    }
                    None => break,
                }
            }
            let next = body_start + body_len;
            progress(next, len);
            match opcode {
                op::FOOTER | op::DATA_END => break,
                op::HEADER | op::SCHEMA | op::CHANNEL | op::MESSAGE | op::CHUNK => {
                    let body = this.read_exact_at(body_start, body_len)?;
                    match mcap::parse_record(opcode, &body) {
                        Ok(records::Record::Header(h)) => {
                            this.profile = h.profile;
                            this.library = h.library;
                        }
                        Ok(records::Record::Schema { header, data }) => {
                            this.add_schema(header.id, &header.name, &header.encoding, &data)
                        }
                        Ok(records::Record::Channel(c)) => this.add_channel(
                            c.id,
                            c.schema_id,
                            &c.topic,
                            &c.message_encoding,
                            &c.metadata,
                        ),
                        Ok(records::Record::Message { header, data }) => {
                            this.deliver(
                                header,
                                &data,
                                MessageLoc::Direct { offset: pos },
                                &mut visit,
                            );
                        }
                        Ok(records::Record::Chunk { header, data }) => {
                            let chunk = this.chunks.len() as u32;
                            this.chunks.push(ChunkLoc {
                                offset: pos,
                                record_len: 9 + body_len,
                            });
                            match decode_chunk(&header, &data, &body) {
                                Ok((decoded, schemas, channels)) => {
                                    for (id, name, encoding, data) in schemas {
                                        this.add_schema(id, &name, &encoding, &data);
                                    }
                                    for c in channels {
                                        this.add_channel(
                                            c.id,
                                            c.schema_id,
                                            &c.topic,
                                            &c.message_encoding,
                                            &c.metadata,
                                        );
                                    }
                                    for (index, (_, header, data)) in
                                        decoded.messages.into_iter().enumerate()
                                    {
                                        this.deliver(
                                            header,
                                            &data,
                                            MessageLoc::Chunk {
                                                chunk,
                                                index: index as u32,
                                            },
                                            &mut visit,
                                        );
                                    }
                                }
                                Err(reason) => this.damage.push(Damage::BadChunk {
                                    offset: pos,
                                    reason,
                                }),
                            }
                        }
                        Ok(_) => {}
                        Err(e) => this.damage.push(Damage::BadRecord {
                            offset: pos,
                            reason: e.to_string(),
                            resumed_at: Some(next),
                        }),
                    }
                }
                _ => {} // indexes, attachments, metadata, statistics: not needed here
            }
            pos = next;
        }

        match &summary {
            Some(summary) => {
                if let Some(stats) = &summary.stats {
                    for (id, expected) in &stats.channel_message_counts {
                        let found = this.message_counts.get(id).copied().unwrap_or(0);
                        if found < *expected {
                            let topic = this
                                .channels
                                .get(id)
                                .map_or_else(|| format!("channel {id}"), |c| c.topic.clone());
                            this.damage.push(Damage::MissingMessages {
                                topic,
                                expected: *expected,
                                found,
                            });
                        }
                    }
                }
            }
            None => this.damage.push(Damage::NoSummary {
                reason: summary_damage
                    .unwrap_or_else(|| "the summary section is missing or unreadable".into()),
            }),
        }
        Ok(this)
    }

    /// Checks the framing of the summary section (from the footer's summary start to the
    /// footer) before mcap's `SummaryReader` reads it: every record within the section and
    /// none of a kind that belongs in the data section (a chunk there made mcap overflow a
    /// subtraction: found by the fuzz target). Without a footer or summary there is nothing
    /// to check; the error names the byte offset of the offending record.
    fn check_summary_framing(&self) -> Result<(), String> {
        // Footer: opcode, length, summary start, summary offset start, CRC; then the magic.
        let footer_len = 9 + 20 + 8;
        let Some(footer_start) = self.len.checked_sub(footer_len).filter(|&f| f >= 8) else {
            return Ok(());
        };
        let Ok(footer) = self.read_exact_at(footer_start, footer_len) else {
            return Ok(());
        };
        let mut start = [0u8; 8];
        start.copy_from_slice(&footer[9..17]);
        let summary_start = u64::from_le_bytes(start);
        if footer[0] != op::FOOTER || summary_start == 0 {
            return Ok(());
        }
        if !(8..=footer_start).contains(&summary_start)
            || footer_start - summary_start > MAX_RECORD_BYTES
        {
            return Err(format!(
                "the footer's summary start, byte {summary_start}, is outside the file's data"
            ));
        }
        let section = self
            .read_exact_at(summary_start, footer_start - summary_start)
            .map_err(|e| e.to_string())?;
        check_framing(&section, |_, opcode| match opcode {
            op::HEADER
            | op::FOOTER
            | op::MESSAGE
            | op::CHUNK
            | op::MESSAGE_INDEX
            | op::ATTACHMENT
            | op::METADATA
            | op::DATA_END => Err(format!(
                "a record with opcode {opcode:#04x}, which does not belong there"
            )),
            _ => Ok(()),
        })
        .map_err(|(at, reason)| {
            format!(
                "malformed summary section at byte {}: {reason}",
                summary_start + at as u64
            )
        })
    }

    fn read_summary(&self) -> Option<mcap::Summary> {
        use mcap::sans_io::summary_reader::{
            SummaryReadEvent, SummaryReader, SummaryReaderOptions,
        };
        let mut reader = SummaryReader::new_with_options(
            SummaryReaderOptions::default()
                .with_file_size(self.len)
                .with_record_length_limit(MAX_RECORD_BYTES as usize),
        );
        let mut pos = 0u64;
        while let Some(event) = reader.next_event() {
            match event.ok()? {
                SummaryReadEvent::ReadRequest(need) => {
                    let buf = reader.insert(need);
                    let n = self.file.read_at(buf, pos).ok()?;
                    pos += n as u64;
                    reader.notify_read(n);
                }
                SummaryReadEvent::SeekRequest(to) => {
                    pos = match to {
                        std::io::SeekFrom::Start(p) => p,
                        std::io::SeekFrom::End(d) => self.len.checked_add_signed(d)?,
                        std::io::SeekFrom::Current(d) => pos.checked_add_signed(d)?,
                    };
                    reader.notify_seeked(pos);
                }
            }
        }
        reader.finish()
    }

    fn add_schema(&mut self, id: u16, name: &str, encoding: &str, data: &[u8]) {
        if id == 0 {
            return;
        }
        self.schemas.entry(id).or_insert_with(|| {
            Arc::new(SchemaInfo {
                id,
                name: name.to_string(),
                encoding: encoding.to_string(),
                data: data.to_vec(),
            })
        });
    }

    fn add_channel(
        &mut self,
        id: u16,
        schema_id: u16,
        topic: &str,
        message_encoding: &str,
        metadata: &BTreeMap<String, String>,
    ) {
        let schema = self.schemas.get(&schema_id).cloned();
        self.channels.entry(id).or_insert_with(|| {
            Arc::new(ChannelInfo {
                id,
                topic: topic.to_string(),
                schema,
                message_encoding: message_encoding.to_string(),
                metadata: metadata.clone(),
            })
        });
    }

    fn deliver(
        &mut self,
        header: records::MessageHeader,
        data: &[u8],
        loc: MessageLoc,
        visit: &mut impl FnMut(MessageRef<'_>),
    ) {
        let Some(channel) = self.channels.get(&header.channel_id) else {
            self.damage.push(Damage::BadRecord {
                offset: match loc {
                    MessageLoc::Direct { offset } => offset,
                    MessageLoc::Chunk { chunk, .. } => self.chunks[chunk as usize].offset,
                },
                reason: format!("message on unknown channel id {}", header.channel_id),
                resumed_at: None,
            });
            return;
        };
        *self.message_counts.entry(header.channel_id).or_default() += 1;
        visit(MessageRef {
            channel,
            sequence: header.sequence,
            log_time: header.log_time,
            publish_time: header.publish_time,
            data,
            loc,
        });
    }

    /// Reads the message at `loc` (decompressing its chunk through `cache`).
    pub fn read_message<'c>(
        &'c self,
        loc: MessageLoc,
        cache: &'c mut ChunkCache,
    ) -> Result<MessageRef<'c>, SourceError> {
        let missing = || SourceError::NoSuchMessage {
            path: self.path.clone(),
            loc,
        };
        let (key, index) = match loc {
            MessageLoc::Direct { offset } => (CacheKey::Direct(offset), 0),
            MessageLoc::Chunk { chunk, index } => (CacheKey::Chunk(chunk), index as usize),
        };
        match cache
            .entries
            .iter()
            .position(|(p, k, _)| *k == key && p == &self.path)
        {
            Some(i) => {
                let entry = cache.entries.remove(i).ok_or_else(missing)?;
                cache.entries.push_back(entry);
            }
            None => {
                let messages = self.load(key).map_err(|reason| match reason {
                    LoadError::Source(e) => e,
                    LoadError::Missing => missing(),
                })?;
                cache
                    .entries
                    .push_back((self.path.clone(), key, Arc::new(messages)));
                if cache.entries.len() > cache.capacity {
                    cache.entries.pop_front();
                }
            }
        }
        let (_, _, messages) = cache.entries.back().ok_or_else(missing)?;
        let (channel_id, header, data) = messages.get(index).ok_or_else(missing)?;
        let channel = self.channels.get(channel_id).ok_or_else(missing)?;
        Ok(MessageRef {
            channel,
            sequence: header.sequence,
            log_time: header.log_time,
            publish_time: header.publish_time,
            data,
            loc,
        })
    }

    /// The messages of a chunk, or the one message of a record outside chunks.
    fn load(&self, key: CacheKey) -> Result<ChunkMessages, LoadError> {
        match key {
            CacheKey::Direct(offset) => {
                let mut head = [0u8; 9];
                self.file
                    .read_exact_at(&mut head, offset)
                    .map_err(|e| LoadError::Source(self.io(e)))?;
                let body_len = record_len(&head);
                if head[0] != op::MESSAGE || body_len > MAX_RECORD_BYTES {
                    return Err(LoadError::Missing);
                }
                let body = self
                    .read_exact_at(offset + 9, body_len)
                    .map_err(LoadError::Source)?;
                match mcap::parse_record(op::MESSAGE, &body) {
                    Ok(records::Record::Message { header, data }) => {
                        Ok(vec![(header.channel_id, header, data.into_owned())])
                    }
                    _ => Err(LoadError::Missing),
                }
            }
            CacheKey::Chunk(chunk) => {
                let loc = self.chunks.get(chunk as usize).ok_or(LoadError::Missing)?;
                let body = self
                    .read_exact_at(loc.offset + 9, loc.record_len - 9)
                    .map_err(LoadError::Source)?;
                let chunk_error = |reason: String| {
                    LoadError::Source(SourceError::Chunk {
                        path: self.path.clone(),
                        offset: loc.offset,
                        reason,
                    })
                };
                let Ok(records::Record::Chunk { header, data }) =
                    mcap::parse_record(op::CHUNK, &body)
                else {
                    return Err(chunk_error("not a chunk record".into()));
                };
                let (decoded, _, _) = decode_chunk(&header, &data, &body).map_err(chunk_error)?;
                Ok(decoded.messages)
            }
        }
    }
}

/// What a cache entry holds: a chunk by number, or one message outside chunks by offset.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
enum CacheKey {
    Chunk(u32),
    Direct(u64),
}

enum LoadError {
    Source(SourceError),
    Missing,
}

/// The body length in a record's 9-byte opcode + length prefix.
fn record_len(head: &[u8; 9]) -> u64 {
    u64::from_le_bytes([
        head[1], head[2], head[3], head[4], head[5], head[6], head[7], head[8],
    ])
}

type SchemaRecord = (u16, String, String, Vec<u8>);

/// Checks that `records` is a run of whole records (opcode, length, body), none running
/// past its end, and passes each record's offset and opcode to `each`; an error carries
/// the offset of the offending record. mcap's readers subtract each record's length from
/// what remains unchecked (an overflow panic in debug builds, found by the fuzz target
/// `mcap_drive`), so bytes are framed here before mcap reads them.
fn check_framing(
    records: &[u8],
    mut each: impl FnMut(usize, u8) -> Result<(), String>,
) -> Result<(), (usize, String)> {
    let mut at = 0usize;
    while let Some(rest) = records.get(at..).filter(|r| !r.is_empty()) {
        let Some(&[opcode, l0, l1, l2, l3, l4, l5, l6, l7]) = rest.get(..9) else {
            return Err((
                at,
                format!("{} stray bytes after the last record", rest.len()),
            ));
        };
        let len = u64::from_le_bytes([l0, l1, l2, l3, l4, l5, l6, l7]);
        if len > (rest.len() - 9) as u64 {
            return Err((
                at,
                format!(
                    "record of {len} bytes runs past the end ({} bytes left)",
                    rest.len() - 9
                ),
            ));
        }
        each(at, opcode).map_err(|reason| (at, reason))?;
        at += 9 + len as usize;
    }
    Ok(())
}

/// Decompresses a chunk and splits it into records; the whole chunk is rejected if
/// anything in it fails (CRC, decompression, a record), so corrupt bytes never reach a
/// decoder. `header` and `records` are the parsed chunk record, `body` its whole body
/// (after opcode and length).
///
/// Two checks that mcap's `ChunkReader` lacks (the fuzz target `mcap_drive` found both):
/// no record inside a chunk is longer than the chunk's uncompressed size (the chunk is
/// read by a linear reader with that record length limit; `ChunkReader` sized its buffer
/// from a corrupt length before decompressing and asked for exabytes), and the records
/// of an uncompressed chunk are framed within it (mcap subtracts each record's length
/// from what remains unchecked: an overflow panic in debug builds).
fn decode_chunk(
    header: &ChunkHeader,
    records: &[u8],
    body: &[u8],
) -> Result<(Decoded, Vec<SchemaRecord>, Vec<records::Channel>), String> {
    use mcap::sans_io::{LinearReadEvent, LinearReader, LinearReaderOptions};
    if header.uncompressed_size > MAX_RECORD_BYTES {
        return Err(format!(
            "declared uncompressed size {} is implausible",
            header.uncompressed_size
        ));
    }
    if header.compression.is_empty() {
        check_framing(records, |_, _| Ok(())).map_err(|(at, reason)| {
            format!(
                "{reason} at byte {at} of the chunk's {} bytes of records",
                records.len()
            )
        })?;
    }
    // The limit also bounds the chunk's own header and padding: at least the body length.
    let limit = header
        .uncompressed_size
        .max(body.len() as u64)
        .min(MAX_RECORD_BYTES);
    let mut reader = LinearReader::new_with_options(
        LinearReaderOptions::default()
            .with_skip_start_magic(true)
            .with_skip_end_magic(true)
            .with_validate_chunk_crcs(true)
            .with_record_length_limit(limit as usize),
    );
    // The reader is fed the chunk record: opcode and length, then the body.
    let mut prefix = [0u8; 9];
    prefix[0] = op::CHUNK;
    prefix[1..].copy_from_slice(&(body.len() as u64).to_le_bytes());
    let mut input: [&[u8]; 2] = [&prefix, body];
    let mut messages = Vec::new();
    let mut schemas = Vec::new();
    let mut channels = Vec::new();
    while let Some(event) = reader.next_event() {
        match event.map_err(|e| e.to_string())? {
            LinearReadEvent::ReadRequest(need) => {
                let source = if input[0].is_empty() {
                    &mut input[1]
                } else {
                    &mut input[0]
                };
                let n = need.min(source.len());
                reader.insert(n).copy_from_slice(&source[..n]);
                reader.notify_read(n);
                *source = &source[n..];
            }
            LinearReadEvent::Record { data, opcode } => {
                match mcap::parse_record(opcode, data).map_err(|e| e.to_string())? {
                    records::Record::Message { header, data } => {
                        messages.push((header.channel_id, header, data.into_owned()))
                    }
                    records::Record::Schema { header, data } => {
                        schemas.push((header.id, header.name, header.encoding, data.into_owned()))
                    }
                    records::Record::Channel(c) => channels.push(c),
                    _ => {}
                }
            }
        }
    }
    Ok((Decoded { messages }, schemas, channels))
}

#[cfg(test)]
mod tests {
    use super::*;
    use std::io::Cursor;

    /// Writes `n` messages on two channels; chunked or not.
    fn sample_file(chunked: bool, n: u32) -> Vec<u8> {
        let options = mcap::WriteOptions::new()
            .use_chunks(chunked)
            .chunk_size(Some(64))
            .compression(Some(mcap::Compression::Zstd));
        let mut writer = options.create(Cursor::new(Vec::new())).unwrap();
        let schema = writer.add_schema("test.Msg", "raw", b"bytes").unwrap();
        let a = writer
            .add_channel(schema, "/a", "raw", &BTreeMap::new())
            .unwrap();
        let b = writer
            .add_channel(schema, "/b", "raw", &BTreeMap::new())
            .unwrap();
        for i in 0..n {
            let channel_id = if i % 3 == 0 { b } else { a };
            let header = records::MessageHeader {
                channel_id,
                sequence: i,
                log_time: 1_000 + u64::from(i),
                publish_time: 1_000 + u64::from(i),
            };
            writer
                .write_to_known_channel(&header, format!("message {i}").as_bytes())
                .unwrap();
        }
        writer.finish().unwrap();
        writer.into_inner().into_inner()
    }

    /// Topic, log time, payload and location of a scanned message.
    type Seen = (String, u64, Vec<u8>, MessageLoc);

    /// Scans a file whose only chunk (right after the magic) is damaged: no message
    /// comes out and the chunk is reported bad at byte 8.
    fn scan_rejects_the_chunk(name: &str, bytes: &[u8]) {
        let (file, seen) = scan_bytes(name, bytes);
        assert!(seen.is_empty());
        assert!(
            file.damage
                .iter()
                .any(|d| matches!(d, Damage::BadChunk { offset: 8, .. })),
            "{:?}",
            file.damage
        );
    }

    fn scan_bytes(name: &str, bytes: &[u8]) -> (McapFile, Vec<Seen>) {
        let dir = std::env::temp_dir().join(format!("superflow-source-{}", std::process::id()));
        std::fs::create_dir_all(&dir).unwrap();
        let path = dir.join(name);
        std::fs::write(&path, bytes).unwrap();
        let mut seen = Vec::new();
        let file = McapFile::scan(&path, |m| {
            seen.push((m.channel.topic.clone(), m.log_time, m.data.to_vec(), m.loc))
        })
        .unwrap();
        (file, seen)
    }

    #[test]
    fn scans_and_reads_back_chunked_and_unchunked_files() {
        for chunked in [true, false] {
            let (file, seen) =
                scan_bytes(&format!("plain_{chunked}.mcap"), &sample_file(chunked, 30));
            assert!(file.damage.is_empty(), "{:?}", file.damage);
            assert_eq!(seen.len(), 30);
            assert_eq!(seen[4].0, "/a");
            assert_eq!(seen[6].0, "/b");
            assert_eq!(seen[7].2, b"message 7");
            let counts: Vec<u64> = file.message_counts.values().copied().collect();
            assert_eq!(counts, [20, 10]);
            // Random access in reverse order through a one-chunk cache.
            let mut cache = ChunkCache::new(1);
            for (topic, log_time, data, loc) in seen.iter().rev() {
                let m = file.read_message(*loc, &mut cache).unwrap();
                assert_eq!(
                    (&m.channel.topic, m.log_time, m.data),
                    (topic, *log_time, &data[..])
                );
                assert_eq!(matches!(loc, MessageLoc::Chunk { .. }), chunked);
            }
            assert!(cache.entries.len() <= 1);
            let missing = MessageLoc::Chunk {
                chunk: 999,
                index: 0,
            };
            assert!(file.read_message(missing, &mut cache).is_err());
        }
    }

    /// A zstd frame holding `content` in one stored (raw) block.
    fn zstd_stored(content: &[u8]) -> Vec<u8> {
        let size = u8::try_from(content.len()).unwrap();
        // Magic, single-segment frame with a 1-byte content size, then the block header:
        // last block, type raw, its size.
        let mut frame = vec![0x28, 0xb5, 0x2f, 0xfd, 0x20, size];
        let block = (u32::from(size) << 3) | 1;
        frame.extend_from_slice(&block.to_le_bytes()[..3]);
        frame.extend_from_slice(content);
        frame
    }

    /// A chunk record (opcode, length, body) around `compressed` data.
    fn chunk_record(compression: &str, uncompressed_size: u64, compressed: &[u8]) -> Vec<u8> {
        padded_chunk_record(compression, uncompressed_size, compressed, 0)
    }

    /// [`chunk_record`] with `padding` zero bytes after the compressed data.
    fn padded_chunk_record(
        compression: &str,
        uncompressed_size: u64,
        compressed: &[u8],
        padding: usize,
    ) -> Vec<u8> {
        let mut body = Vec::new();
        body.extend_from_slice(&0u64.to_le_bytes()); // message start time
        body.extend_from_slice(&0u64.to_le_bytes()); // message end time
        body.extend_from_slice(&uncompressed_size.to_le_bytes());
        body.extend_from_slice(&0u32.to_le_bytes()); // CRC: not checked
        body.extend_from_slice(&(compression.len() as u32).to_le_bytes());
        body.extend_from_slice(compression.as_bytes());
        body.extend_from_slice(&(compressed.len() as u64).to_le_bytes());
        body.extend_from_slice(compressed);
        body.resize(body.len() + padding, 0);
        let mut record = vec![op::CHUNK];
        record.extend_from_slice(&(body.len() as u64).to_le_bytes());
        record.extend_from_slice(&body);
        record
    }

    /// Found by the `mcap_drive` fuzz target: a record inside a compressed chunk that
    /// declares an absurd length made mcap's chunk reader allocate that many bytes
    /// before decompressing (the process aborted). Now the chunk is reported as bad.
    #[test]
    fn a_huge_record_length_inside_a_compressed_chunk_is_a_bad_chunk() {
        let mut content = vec![op::MESSAGE];
        content.extend_from_slice(&0x6161_6161_6161_6161u64.to_le_bytes());
        content.extend_from_slice(b"the rest of the chunk");
        for uncompressed_size in [content.len() as u64, MAX_RECORD_BYTES] {
            let mut bytes = MAGIC.to_vec();
            bytes.extend(chunk_record(
                "zstd",
                uncompressed_size,
                &zstd_stored(&content),
            ));
            scan_rejects_the_chunk("huge_record_in_chunk.mcap", &bytes);
        }
        // The same chunk holding a well-formed record (a schema) still reads.
        let schema = b"\x01\x00\x01\x00\x00\x00s\x03\x00\x00\x00raw\x00\x00\x00\x00";
        let mut content = vec![op::SCHEMA];
        content.extend_from_slice(&(schema.len() as u64).to_le_bytes());
        content.extend_from_slice(schema);
        let mut bytes = MAGIC.to_vec();
        bytes.extend(chunk_record(
            "zstd",
            content.len() as u64,
            &zstd_stored(&content),
        ));
        let (file, _) = scan_bytes("sane_chunk.mcap", &bytes);
        assert_eq!(file.chunks.len(), 1);
        assert!(
            !file
                .damage
                .iter()
                .any(|d| matches!(d, Damage::BadChunk { .. })),
            "{:?}",
            file.damage
        );
        assert_eq!(file.schemas.get(&1).map(|s| s.name.as_str()), Some("s"));
    }

    /// Found by the `mcap_drive` fuzz target: a record of an uncompressed chunk longer
    /// than what remains of the chunk made mcap's reader overflow a subtraction (a panic
    /// in debug builds). Now the chunk is reported as bad.
    #[test]
    fn a_record_running_past_an_uncompressed_chunk_is_a_bad_chunk() {
        // A record claiming 100 bytes where 5 remain.
        let mut overlong = vec![op::MESSAGE];
        overlong.extend_from_slice(&100u64.to_le_bytes());
        overlong.extend_from_slice(b"short");
        // An empty record, then 3 stray bytes.
        let mut stray = vec![op::MESSAGE];
        stray.extend_from_slice(&0u64.to_le_bytes());
        stray.extend_from_slice(&[op::MESSAGE, 1, 0]);
        for chunk in [overlong, stray] {
            let mut bytes = MAGIC.to_vec();
            // Padding after the records, as a writer may leave: the overlong record
            // would reach into it.
            bytes.extend(padded_chunk_record("", chunk.len() as u64, &chunk, 128));
            scan_rejects_the_chunk("record_past_chunk.mcap", &bytes);
        }
    }

    /// Found by the `mcap_drive` fuzz target: a summary whose chunk index points past
    /// the end of the file made the scan resume there after a corrupt record and
    /// underflow `len - pos` (a panic in debug builds). Such offsets are ignored now.
    #[test]
    fn a_chunk_index_past_the_end_of_the_file_is_ignored() {
        let bytes = sample_file(true, 12);
        let (file, _) = scan_bytes("index_past_end.mcap", &bytes);
        assert!(file.damage.is_empty(), "{:?}", file.damage);
        // Point every chunk index entry (chunk_start_offset follows the two 8-byte
        // times) far past the end, and corrupt the first chunk record so that the scan
        // looks for a place to resume.
        let mut corrupt = bytes.clone();
        let first_chunk = file.chunks[0].offset as usize;
        let summary_start = file
            .chunks
            .last()
            .map_or(0, |c| (c.offset + c.record_len) as usize);
        let mut at = summary_start;
        while at + 9 <= corrupt.len() {
            let opcode = corrupt[at];
            let len = u64::from_le_bytes(corrupt[at + 1..at + 9].try_into().unwrap()) as usize;
            if opcode == op::CHUNK_INDEX {
                let offset = at + 9 + 16;
                corrupt[offset..offset + 8].copy_from_slice(&(u64::MAX - 4).to_le_bytes());
            }
            if opcode == op::FOOTER {
                // No summary CRC: the edited summary must still be read.
                corrupt[at + 9 + 16..at + 9 + 20].fill(0);
                break;
            }
            at += 9 + len;
        }
        corrupt[first_chunk] = 0xee;
        let (file, _) = scan_bytes("index_past_end.mcap", &corrupt);
        assert!(
            file.damage.iter().any(
                |d| matches!(d, Damage::BadRecord { offset, .. } if *offset == first_chunk as u64)
            ),
            "{:?}",
            file.damage
        );
    }

    /// Found by the `mcap_drive` fuzz target: an uncompressed chunk in the summary
    /// section, holding a record longer than the chunk, made mcap's `SummaryReader`
    /// overflow a subtraction (a panic in debug builds). A summary with a record of a
    /// kind that does not belong there, or one running past the section, is now no
    /// usable summary (named with its byte offset) and the file is scanned linearly.
    #[test]
    fn a_malformed_summary_section_is_no_summary() {
        let bytes = sample_file(false, 6);
        let footer_start = bytes.len() - 37;
        assert_eq!(bytes[footer_start], op::FOOTER);
        let summary_start = u64::from_le_bytes(
            bytes[footer_start + 9..footer_start + 17]
                .try_into()
                .unwrap(),
        );
        // A chunk whose one record claims 100 bytes where 5 remain (padding after it:
        // mcap would read on into it).
        let mut overlong = vec![op::MESSAGE];
        overlong.extend_from_slice(&100u64.to_le_bytes());
        overlong.extend_from_slice(b"short");
        let chunk = padded_chunk_record("", overlong.len() as u64, &overlong, 128);
        // A schema record running past the summary section into the footer.
        let mut schema = vec![op::SCHEMA];
        schema.extend_from_slice(&1000u64.to_le_bytes());
        schema.extend_from_slice(b"short");
        for (summary, what) in [(chunk, "opcode 0x06"), (schema, "runs past the end")] {
            let mut corrupt = bytes[..summary_start as usize].to_vec();
            corrupt.extend_from_slice(&summary);
            corrupt.push(op::FOOTER);
            corrupt.extend_from_slice(&20u64.to_le_bytes());
            corrupt.extend_from_slice(&summary_start.to_le_bytes());
            corrupt.extend_from_slice(&0u64.to_le_bytes()); // no summary offsets
            corrupt.extend_from_slice(&0u32.to_le_bytes()); // no summary CRC
            corrupt.extend_from_slice(MAGIC);
            let (file, seen) = scan_bytes("malformed_summary.mcap", &corrupt);
            assert_eq!(seen.len(), 6, "{:?}", file.damage);
            assert!(
                file.damage.iter().any(|d| matches!(
                    d,
                    Damage::NoSummary { reason }
                        if reason.contains(&format!("byte {summary_start}")) && reason.contains(what)
                )),
                "{:?}",
                file.damage
            );
        }
    }

    #[test]
    fn every_truncation_is_a_report_not_a_panic() {
        let bytes = sample_file(true, 12);
        for cut in (0..bytes.len()).step_by(7) {
            let dir = std::env::temp_dir().join(format!("superflow-cut-{}", std::process::id()));
            std::fs::create_dir_all(&dir).unwrap();
            let path = dir.join("cut.mcap");
            std::fs::write(&path, &bytes[..cut]).unwrap();
            let mut n = 0;
            match McapFile::scan(&path, |_| n += 1) {
                Ok(file) => {
                    assert!(n <= 12);
                    assert!(
                        !file.damage.is_empty(),
                        "a cut file at {cut} must report damage"
                    );
                }
                Err(SourceError::NotMcap { .. }) => assert!(cut < 8),
                Err(e) => panic!("unexpected error at {cut}: {e}"),
            }
        }
    }
}
