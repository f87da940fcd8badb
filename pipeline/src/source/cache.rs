//! Random access: [`McapFile::read_message`] fetches one message by location through a
//! [`ChunkCache`] of a few decompressed chunks (memory stays bounded whatever the file
//! size).

use super::chunk::{ChunkError, ChunkMessages, decode_chunk};
use super::framing::record_len;
use super::{MAX_RECORD_BYTES, McapFile, MessageLoc, MessageRef, SourceError};
use mcap::records::{self, op};
use std::collections::VecDeque;
use std::os::unix::fs::FileExt;
use std::path::PathBuf;
use std::sync::Arc;

/// A few decompressed chunks, most recent last, for random access.
#[derive(Debug)]
pub struct ChunkCache {
    capacity: usize,
    pub(super) entries: VecDeque<(PathBuf, CacheKey, Arc<ChunkMessages>)>,
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

impl McapFile {
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
        let (header, data) = messages.get(index).ok_or_else(missing)?;
        let channel = self.channels.get(&header.channel_id).ok_or_else(missing)?;
        Ok(MessageRef::new(channel, header, data, loc))
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
                    Ok(records::Record::Message { header, .. }) => {
                        Ok(ChunkMessages::single(header, body))
                    }
                    _ => Err(LoadError::Missing),
                }
            }
            CacheKey::Chunk(chunk) => {
                let loc = self.chunks.get(chunk as usize).ok_or(LoadError::Missing)?;
                let body = self
                    .read_exact_at(loc.offset + 9, loc.record_len - 9)
                    .map_err(LoadError::Source)?;
                let chunk_error = |source: ChunkError| {
                    LoadError::Source(SourceError::Chunk {
                        path: self.path.clone(),
                        offset: loc.offset,
                        source,
                    })
                };
                let Ok(records::Record::Chunk { header, data }) =
                    mcap::parse_record(op::CHUNK, &body)
                else {
                    return Err(chunk_error(ChunkError::NotAChunk));
                };
                let decoded = decode_chunk(&header, &data).map_err(chunk_error)?;
                Ok(decoded.messages)
            }
        }
    }
}

/// What a cache entry holds: a chunk by number, or one message outside chunks by offset.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub(super) enum CacheKey {
    Chunk(u32),
    Direct(u64),
}

/// Why `McapFile::load` failed.
enum LoadError {
    /// The file could not deliver it.
    Source(SourceError),
    /// No such message or chunk.
    Missing,
}
