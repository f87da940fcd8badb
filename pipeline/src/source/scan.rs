//! [`McapFile::scan`]: the one pass over a file, record by record, holding at most one
//! chunk in memory. Damage (truncation, corrupt records, bad chunks) is noted and worked
//! around; the summary's chunk index tells where to resume after a corrupt record.

use super::chunk::decode_chunk;
use super::damage::Damage;
use super::error::SourceError;
use super::file::{ChunkLoc, McapFile};
use super::framing::record_len;
use super::framing::{MAGIC, MAX_RECORD_BYTES};
use super::handles::{FileIdentity, HandlePool};
use super::message::{ChannelInfo, MessageLoc, MessageRef, SchemaInfo};
use super::remote::RemoteObject;
use mcap::records::{self, ChunkHeader, op};
use std::collections::{BTreeMap, HashMap};
use std::fs::File;
use std::os::unix::fs::FileExt;
use std::path::Path;
use std::sync::Arc;

/// What the scan finds at a position of the data section.
enum Next {
    /// A whole record: its opcode and body length.
    Record { opcode: u8, body_len: u64 },
    /// A corrupt record (noted); the scan goes on at this offset.
    ResumeAt(u64),
    /// Nothing more can be read (noted).
    End,
}

impl McapFile {
    /// Scans `path` once, calling `visit` for every readable message in file order.
    pub fn scan(path: &Path, visit: impl FnMut(MessageRef<'_>)) -> Result<McapFile, SourceError> {
        Self::scan_with_progress(path, visit, |_, _| {})
    }

    /// [`McapFile::scan`], reporting `(bytes read, file size)` after every record.
    pub fn scan_with_progress(
        path: &Path,
        visit: impl FnMut(MessageRef<'_>),
        progress: impl FnMut(u64, u64),
    ) -> Result<McapFile, SourceError> {
        Self::open(path)?.scan_with_progress_opened(visit, progress)
    }

    /// The scan of a file [`open`](Self::open) has opened, as
    /// [`scan_with_progress`](Self::scan_with_progress) makes it.
    pub fn scan_with_progress_opened(
        mut self,
        mut visit: impl FnMut(MessageRef<'_>),
        mut progress: impl FnMut(u64, u64),
    ) -> Result<McapFile, SourceError> {
        let scanned = self.scan_opened(&mut visit, &mut progress);
        self.end_scan();
        scanned.map(|()| self)
    }

    /// The scan of a file [`open`](Self::open) has opened.
    fn scan_opened(
        &mut self,
        visit: &mut impl FnMut(MessageRef<'_>),
        progress: &mut impl FnMut(u64, u64),
    ) -> Result<(), SourceError> {
        let this = self;
        if this.remote.is_some() {
            // A local file's magic was checked on opening; an object's is read here,
            // with the first bytes the scan reads anyway.
            let mut magic = [0u8; 8];
            if this.len >= 8 {
                // A read that fails is its own error (a store that refuses, a replaced
                // object), not a verdict on the bytes.
                this.read_into(&mut magic, 0)?;
            }
            if this.len < 8 || &magic != MAGIC {
                return Err(SourceError::NotMcap {
                    path: this.path.clone(),
                });
            }
        }
        let summary = this.checked_summary();
        let resume_points = match &summary {
            Ok(summary) => this.take_summary(summary),
            Err(_) => Vec::new(),
        };
        this.scan_records(&resume_points, visit, progress)?;
        match &summary {
            Ok(summary) => this.count_missing_messages(summary),
            Err(e) => this.damage.push(Damage::NoSummary {
                reason: e.to_string(),
            }),
        }
        Ok(())
    }

    /// Opens `path` through the pool after checking its magic; nothing else read yet.
    /// The file holds its handle until it is scanned or [restored](Self::restore).
    /// An object URL ([`is_remote`](super::is_remote)) opens the object as listed (or
    /// after one HEAD), reading nothing: its magic is checked when it is scanned.
    pub fn open(path: &Path) -> Result<McapFile, SourceError> {
        static OPENED: std::sync::atomic::AtomicU64 = std::sync::atomic::AtomicU64::new(0);
        let id = OPENED.fetch_add(1, std::sync::atomic::Ordering::Relaxed);
        if super::remote::is_remote(path) {
            let object = RemoteObject::open(path)?;
            object.set_sequential(true);
            let identity = FileIdentity {
                len: object.size(),
                ..FileIdentity::default()
            };
            let mut file = McapFile::new(path, id, identity, None);
            file.remote = Some(Arc::new(object));
            return Ok(file);
        }
        let pool = HandlePool::global();
        let (file, identity) = pool.open_new(id, path)?;
        let len = identity.len;
        let mut magic = [0u8; 8];
        if len < 8 || file.read_exact_at(&mut magic, 0).is_err() || &magic != MAGIC {
            pool.forget(id);
            return Err(SourceError::NotMcap {
                path: path.to_path_buf(),
            });
        }
        Ok(McapFile::new(path, id, identity, Some(file)))
    }

    fn new(path: &Path, id: u64, identity: FileIdentity, scanning: Option<Arc<File>>) -> Self {
        McapFile {
            path: path.to_path_buf(),
            id,
            identity: std::sync::Mutex::new(identity),
            content: std::sync::OnceLock::new(),
            scanning,
            remote: None,
            len: identity.len,
            profile: String::new(),
            library: String::new(),
            schemas: HashMap::new(),
            channels: BTreeMap::new(),
            chunks: Vec::new(),
            damage: Vec::new(),
            message_counts: BTreeMap::new(),
            decompressed: Default::default(),
            checked: Default::default(),
        }
    }

    /// Reads the data section record by record, from after the magic to the footer (or
    /// as far as it can), resuming after a corrupt record at the next of `resume_points`.
    fn scan_records(
        &mut self,
        resume_points: &[u64],
        visit: &mut impl FnMut(MessageRef<'_>),
        progress: &mut impl FnMut(u64, u64),
    ) -> Result<(), SourceError> {
        let mut pos = 8u64;
        loop {
            let (opcode, body_len) = match self.next_record(pos, resume_points)? {
                Next::Record { opcode, body_len } => (opcode, body_len),
                Next::ResumeAt(next) => {
                    pos = next;
                    continue;
                }
                Next::End => return Ok(()),
            };
            let next = pos + 9 + body_len;
            progress(next, self.len);
            match opcode {
                op::FOOTER | op::DATA_END => return Ok(()),
                op::HEADER | op::SCHEMA | op::CHANNEL | op::MESSAGE | op::CHUNK => {
                    self.read_record(pos, opcode, body_len, visit)?
                }
                _ => {} // indexes, attachments, metadata, statistics: not needed here
            }
            pos = next;
        }
    }

    /// Checks the record header at `pos`: a plausible opcode and a body within the file.
    /// Otherwise notes the damage and says where to go on, if anywhere.
    fn next_record(&mut self, pos: u64, resume_points: &[u64]) -> Result<Next, SourceError> {
        let len = self.len;
        if pos == len {
            self.damage.push(Damage::Truncated {
                offset: pos,
                reason: "no footer".into(),
            });
            return Ok(Next::End);
        }
        if pos + 9 > len {
            self.damage.push(Damage::Truncated {
                offset: pos,
                reason: format!(
                    "{} stray bytes where a record header was expected",
                    len - pos
                ),
            });
            return Ok(Next::End);
        }
        let mut head = [0u8; 9];
        self.read_into(&mut head, pos)?;
        let opcode = head[0];
        let body_len = record_len(&head);
        let plausible =
            (op::HEADER..=op::DATA_END).contains(&opcode) && body_len <= MAX_RECORD_BYTES;
        if plausible && pos + 9 + body_len <= len {
            return Ok(Next::Record { opcode, body_len });
        }
        let reason = if plausible {
            format!("record of {body_len} bytes runs past the end of the file ({len} bytes)")
        } else {
            format!("opcode {opcode:#04x} with length {body_len}")
        };
        let resume = resume_points.iter().copied().find(|o| *o > pos);
        if plausible && resume.is_none() {
            self.damage.push(Damage::Truncated {
                offset: pos,
                reason,
            });
            return Ok(Next::End);
        }
        self.damage.push(Damage::BadRecord {
            offset: pos,
            reason,
            resumed_at: resume,
        });
        Ok(resume.map_or(Next::End, Next::ResumeAt))
    }

    /// Reads and takes in the record at `pos` (header, schema, channel, message, chunk).
    fn read_record(
        &mut self,
        pos: u64,
        opcode: u8,
        body_len: u64,
        visit: &mut impl FnMut(MessageRef<'_>),
    ) -> Result<(), SourceError> {
        let body = self.read_exact_at(pos + 9, body_len)?;
        match mcap::parse_record(opcode, &body) {
            Ok(records::Record::Header(h)) => {
                self.profile = h.profile;
                self.library = h.library;
            }
            Ok(records::Record::Schema { header, data }) => {
                self.add_schema(header.id, &header.name, &header.encoding, &data)
            }
            Ok(records::Record::Channel(c)) => self.add_channel(
                c.id,
                c.schema_id,
                &c.topic,
                &c.message_encoding,
                &c.metadata,
            ),
            Ok(records::Record::Message { header, data }) => {
                self.deliver(header, &data, MessageLoc::Direct { offset: pos }, visit);
            }
            Ok(records::Record::Chunk { header, data }) => {
                self.read_chunk(pos, body_len, &header, &data, visit)
            }
            Ok(_) => {}
            Err(e) => self.damage.push(Damage::BadRecord {
                offset: pos,
                reason: e.to_string(),
                resumed_at: Some(pos + 9 + body_len),
            }),
        }
        Ok(())
    }

    /// Registers the chunk record at `pos` and takes in its records, or notes it as bad.
    fn read_chunk(
        &mut self,
        pos: u64,
        body_len: u64,
        header: &ChunkHeader,
        records: &[u8],
        visit: &mut impl FnMut(MessageRef<'_>),
    ) {
        let chunk = self.chunks.len() as u32;
        self.chunks.push(ChunkLoc {
            offset: pos,
            record_len: 9 + body_len,
        });
        let decoded = match decode_chunk(header, records) {
            Ok(decoded) => decoded,
            Err(e) => {
                self.damage.push(Damage::BadChunk {
                    offset: pos,
                    reason: e.to_string(),
                });
                return;
            }
        };
        for (id, name, encoding, data) in decoded.schemas {
            self.add_schema(id, &name, &encoding, &data);
        }
        for c in decoded.channels {
            self.add_channel(
                c.id,
                c.schema_id,
                &c.topic,
                &c.message_encoding,
                &c.metadata,
            );
        }
        for (index, (header, data)) in decoded.messages.iter().enumerate() {
            let loc = MessageLoc::Chunk {
                chunk,
                index: index as u32,
            };
            self.deliver(*header, data, loc, visit);
        }
    }

    pub(super) fn add_schema(&mut self, id: u16, name: &str, encoding: &str, data: &[u8]) {
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

    pub(super) fn add_channel(
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
        visit(MessageRef::new(channel, &header, data, loc));
    }
}
