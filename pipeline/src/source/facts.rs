//! What a scan learned about a file, in a form that can be stored ([`ScannedFile`]), and
//! the fingerprint ([`McapFile::fingerprint`]) that says whether stored facts still
//! describe the file: a file opened again with the same fingerprint gets its facts back
//! ([`McapFile::restore`]) instead of a scan.

use super::damage::Damage;
use super::error::SourceError;
use super::file::{ChunkLoc, McapFile};
use super::framing::MAGIC;
use super::message::SchemaInfo;
use mcap::records::op;
use serde::{Deserialize, Serialize};
use std::collections::BTreeMap;
use std::fs::File;
use std::os::unix::fs::{FileExt, MetadataExt};
use xxhash_rust::xxh3::Xxh3;

/// Footer: opcode, length, summary start, summary offset start, CRC; then the magic.
const FOOTER_LEN: u64 = 9 + 20 + 8;
/// A header record or summary section larger than this is not fingerprinted (nor cached).
const MAX_FINGERPRINTED: u64 = 256 << 20;
/// The fixed start of a chunk record: opcode, length, start and end times, uncompressed
/// size and CRC.
const CHUNK_HEAD_LEN: u64 = 9 + 8 + 8 + 8 + 4;

/// The facts of a scanned [`McapFile`] that a later opening of the same file can reuse.
#[derive(Debug, Clone, PartialEq, Eq, Serialize, Deserialize)]
pub struct ScannedFile {
    len: u64,
    profile: String,
    library: String,
    schemas: Vec<SchemaInfo>,
    channels: Vec<ChannelFacts>,
    /// Chunk records: offset and length.
    chunks: Vec<(u64, u64)>,
    damage: Vec<Damage>,
    message_counts: BTreeMap<u16, u64>,
}

/// A channel with its schema by id (the schema itself is stored once, in `schemas`).
#[derive(Debug, Clone, PartialEq, Eq, Serialize, Deserialize)]
struct ChannelFacts {
    id: u16,
    schema_id: u16,
    topic: String,
    message_encoding: String,
    metadata: BTreeMap<String, String>,
}

impl ScannedFile {
    /// The size of the file scanned.
    pub fn len(&self) -> u64 {
        self.len
    }

    /// Whether the file scanned was empty.
    pub fn is_empty(&self) -> bool {
        self.len == 0
    }

    /// The number of chunk records.
    pub fn chunk_count(&self) -> usize {
        self.chunks.len()
    }

    /// Checks facts read back from storage against the file they are said to describe
    /// (of `len` bytes): every chunk a whole record inside the file, every channel's
    /// schema present. An error says what does not fit.
    pub fn fits(&self, len: u64) -> Result<(), String> {
        if self.len != len {
            return Err(format!(
                "it is of a file of {} bytes, this one has {len}",
                self.len
            ));
        }
        for &(offset, record_len) in &self.chunks {
            let end = offset.checked_add(record_len);
            if offset < 8 || record_len < CHUNK_HEAD_LEN || end.is_none_or(|end| end > len) {
                return Err(format!(
                    "a chunk of {record_len} bytes at byte {offset} does not fit the file"
                ));
            }
        }
        for c in &self.channels {
            if c.schema_id != 0 && !self.schemas.iter().any(|s| s.id == c.schema_id) {
                return Err(format!("channel {} has no schema {}", c.id, c.schema_id));
            }
        }
        Ok(())
    }
}

impl McapFile {
    /// What the scan learned, to be stored.
    pub fn scanned(&self) -> ScannedFile {
        let mut schemas: Vec<SchemaInfo> = self.schemas.values().map(|s| (**s).clone()).collect();
        schemas.sort_by_key(|s| s.id);
        ScannedFile {
            len: self.len,
            profile: self.profile.clone(),
            library: self.library.clone(),
            schemas,
            channels: self
                .channels
                .values()
                .map(|c| ChannelFacts {
                    id: c.id,
                    schema_id: c.schema.as_ref().map_or(0, |s| s.id),
                    topic: c.topic.clone(),
                    message_encoding: c.message_encoding.clone(),
                    metadata: c.metadata.clone(),
                })
                .collect(),
            chunks: self
                .chunks
                .iter()
                .map(|c| (c.offset, c.record_len))
                .collect(),
            damage: self.damage.clone(),
            message_counts: self.message_counts.clone(),
        }
    }

    /// This opened, unscanned file with the facts of an earlier scan of the same file (of
    /// the same [fingerprint](Self::fingerprint)).
    pub fn restore(mut self, facts: &ScannedFile) -> McapFile {
        debug_assert_eq!(facts.len, self.len);
        self.profile.clone_from(&facts.profile);
        self.library.clone_from(&facts.library);
        for s in &facts.schemas {
            self.add_schema(s.id, &s.name, &s.encoding, &s.data);
        }
        for c in &facts.channels {
            self.add_channel(
                c.id,
                c.schema_id,
                &c.topic,
                &c.message_encoding,
                &c.metadata,
            );
        }
        self.chunks = facts
            .chunks
            .iter()
            .map(|&(offset, record_len)| ChunkLoc { offset, record_len })
            .collect();
        self.damage.clone_from(&facts.damage);
        self.message_counts.clone_from(&facts.message_counts);
        self.end_scan();
        self
    }

    /// A fingerprint of the file that a rewrite cannot keep: a 128-bit hash of its size,
    /// inode, modification and status-change times and its [content
    /// digest](Self::content_digest). Hard links of a file share it, and so do the hosts
    /// that mount one shared file system; a copy of the file does not (it is indexed once
    /// more), so that a damaged copy — whose chunk heads and summary may still be the
    /// original's — is never taken for it. `None` for a file without a usable footer and
    /// summary (a recording cut short, or written without a summary): its content has no
    /// cheap fingerprint, so it is scanned at every opening.
    ///
    /// An object in a store is fingerprinted by its URL, ETag and size, read from its
    /// listing: no byte of it is read, so a warm start costs the listing alone. An
    /// object without an ETag has no fingerprint.
    pub fn fingerprint(&self) -> Result<Option<u128>, SourceError> {
        if let Some(object) = &self.remote {
            let (url, etag, size) = object.version();
            let Some(etag) = etag else {
                return Ok(None);
            };
            let mut hash = Xxh3::new();
            hash.update(b"object\0");
            hash.update(url.as_os_str().as_encoded_bytes());
            hash.update(b"\0");
            hash.update(etag.as_bytes());
            hash.update(&size.to_le_bytes());
            return Ok(Some(hash.digest128()));
        }
        let Some(content) = self.content_digest()? else {
            return Ok(None);
        };
        let meta = self.handle()?.metadata().map_err(|e| self.io(e))?;
        let mut hash = Xxh3::new();
        for word in [
            self.len as i64,
            meta.ino() as i64,
            meta.mtime(),
            meta.mtime_nsec(),
            meta.ctime(),
            meta.ctime_nsec(),
        ] {
            hash.update(&word.to_le_bytes());
        }
        hash.update(&content.to_le_bytes());
        Ok(Some(hash.digest128()))
    }

    /// A 128-bit hash of what the file's bytes say about themselves: its header record,
    /// summary section and footer, and the head of every chunk the summary indexes (sizes
    /// and the CRC of its content). A copy of the file shares it; a rewrite with other
    /// content does not. Computed once per opening, when the file is indexed (the file on
    /// disk may be replaced later; [`same_content`](Self::same_content) compares the new
    /// one with it). `None` for a file without a usable footer and summary.
    pub fn content_digest(&self) -> Result<Option<u128>, SourceError> {
        if let Some(digest) = self.content.get() {
            return Ok(*digest);
        }
        if self.remote.is_some() {
            // An object is never compared by content: its ETag pins every read.
            return Ok(*self.content.get_or_init(|| None));
        }
        let digest =
            content_digest_of(self.handle()?.as_ref(), self.len).map_err(|e| self.io(e))?;
        Ok(*self.content.get_or_init(|| digest))
    }

    /// Whether `file`, now at this file's path, holds what this file held when opened:
    /// the same [content digest](Self::content_digest). `false` for a file without one.
    pub(super) fn same_content(&self, file: &File, len: u64) -> bool {
        // Only a digest taken before: the original may be gone by now.
        let Some(Some(original)) = self.content.get().copied() else {
            return false;
        };
        len == self.len && content_digest_of(file, len).is_ok_and(|d| d == Some(original))
    }
}

/// [`McapFile::content_digest`] of the `len` bytes of `file`.
fn content_digest_of(file: &File, len: u64) -> std::io::Result<Option<u128>> {
    let read = |offset: u64, n: u64| -> std::io::Result<Vec<u8>> {
        let mut buf = vec![0u8; n as usize];
        file.read_exact_at(&mut buf, offset)?;
        Ok(buf)
    };
    let Some(footer_start) = len.checked_sub(FOOTER_LEN).filter(|&f| f >= 8 + 9) else {
        return Ok(None);
    };
    let footer = read(footer_start, FOOTER_LEN)?;
    let summary_start = u64_at(&footer, 9);
    if footer[0] != op::FOOTER
        || &footer[29..] != MAGIC
        || summary_start < 8 + 9
        || summary_start >= footer_start
        || footer_start - summary_start > MAX_FINGERPRINTED
    {
        return Ok(None);
    }
    let head = read(8, 9)?;
    let header_len = u64_at(&head, 1);
    if head[0] != op::HEADER || header_len > MAX_FINGERPRINTED || 17 + header_len > len {
        return Ok(None);
    }
    let mut hash = Xxh3::new();
    hash.update(&read(0, 17 + header_len)?);
    let summary = read(summary_start, footer_start - summary_start)?;
    hash.update(&summary);
    hash.update(&footer);
    // Chunk heads, from the chunk indexes of the summary (records: opcode, length, body).
    let mut pos = 0usize;
    while let Some(body_len) = summary.get(pos + 1..pos + 9).map(|b| u64_at(b, 0)) {
        let body = pos + 9..(pos + 9).saturating_add(body_len as usize);
        let Some(record) = summary.get(body.clone()) else {
            return Ok(None);
        };
        if summary[pos] == op::CHUNK_INDEX && record.len() >= 24 {
            let chunk_start = u64_at(record, 16);
            if chunk_start.saturating_add(CHUNK_HEAD_LEN) > summary_start {
                return Ok(None);
            }
            hash.update(&read(chunk_start, CHUNK_HEAD_LEN)?);
        }
        pos = body.end;
    }
    Ok(Some(hash.digest128()))
}

fn u64_at(bytes: &[u8], at: usize) -> u64 {
    let mut b = [0u8; 8];
    b.copy_from_slice(&bytes[at..at + 8]);
    u64::from_le_bytes(b)
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn stored_chunks_must_be_whole_records_inside_the_file() {
        let facts = |chunks: Vec<(u64, u64)>| ScannedFile {
            len: 10_000,
            profile: String::new(),
            library: String::new(),
            schemas: Vec::new(),
            channels: Vec::new(),
            chunks,
            damage: Vec::new(),
            message_counts: BTreeMap::new(),
        };
        assert!(facts(vec![(8, 100), (108, 9_892)]).fits(10_000).is_ok());
        assert!(facts(vec![(8, 100)]).fits(10_001).is_err(), "another size");
        for bad in [(8, 5), (8, 0), (0, 100), (9_950, 100), (u64::MAX - 3, 100)] {
            let err = facts(vec![bad]).fits(10_000).unwrap_err();
            assert!(err.contains("does not fit"), "{bad:?}: {err}");
        }
    }
}
