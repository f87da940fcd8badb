//! Random access: [`McapFile::read_message`] fetches one message by location through a
//! [`ChunkCache`] of a few decompressed chunks (memory stays bounded whatever the file
//! size).
//!
//! Each thread keeps its own cache, and behind them all sits one small shared table of
//! the chunks decompressed last ([`SHARED_CHUNKS_PER_THREAD`] per thread): the parts of
//! one sample run on several threads, and without it each thread decompressed the
//! sample's chunks again (~20 % more chunks on 2 threads than on 1). A thread that wants
//! a chunk another is decompressing waits for it instead of decompressing it too.

use super::chunk::{ChunkError, ChunkMessages, decode_chunk};
use super::framing::record_len;
use super::{MAX_RECORD_BYTES, McapFile, MessageLoc, MessageRef, SourceError};
use mcap::records::{self, op};
use std::collections::VecDeque;
use std::os::unix::fs::FileExt;
use std::sync::atomic::{AtomicU64, Ordering};
use std::sync::{Arc, Mutex, OnceLock};

/// A few decompressed chunks, most recent last, for random access.
#[derive(Debug)]
pub struct ChunkCache {
    capacity: usize,
    pub(super) entries: VecDeque<(u64, CacheKey, Arc<ChunkMessages>)>,
}

/// Chunks the shared table keeps per thread of the pool, the oldest leaving first:
/// enough for the threads building one sample to meet on its chunks, too few to keep a
/// drive's chunks from one sample to the next (samples come in shuffled order; a real
/// dataset is far larger than any cache, and the bench must not look better than that).
const SHARED_CHUNKS_PER_THREAD: usize = 4;

/// Decompressed bytes the shared table keeps at most (chunks of the usual 0.5–4 MiB
/// leave by number first; larger ones by size).
const SHARED_BYTES: usize = 64 << 20;

/// What random access has decompressed from one file so far (all threads).
#[derive(Debug, Clone, Copy, Default, PartialEq, Eq)]
pub struct Decompressed {
    /// Chunks decompressed (a chunk served from a cache is not counted again).
    pub chunks: u64,
    /// Their decompressed bytes.
    pub bytes: u64,
}

/// The counters behind [`McapFile::decompressed`].
#[derive(Debug, Default)]
pub(super) struct DecompressCounters {
    chunks: AtomicU64,
    bytes: AtomicU64,
}

/// A chunk in the shared table: set once by the thread that decompresses it (`None` if
/// that failed: each thread then reads it itself and reports its own error).
type SharedSlot = Arc<OnceLock<Option<Arc<ChunkMessages>>>>;

/// The shared table: (file id, chunk) → slot, most recent last.
static SHARED: Mutex<VecDeque<(u64, CacheKey, SharedSlot)>> = Mutex::new(VecDeque::new());

/// The slot of `(file, key)` in the shared table, made (empty) if it is not there.
fn shared_slot(file: u64, key: CacheKey) -> SharedSlot {
    // A panic elsewhere while the lock was held leaves a table that is still consistent.
    let mut table = SHARED
        .lock()
        .unwrap_or_else(|poisoned| poisoned.into_inner());
    let found = table.iter().position(|(f, k, _)| *f == file && *k == key);
    if let Some(entry) = found.and_then(|i| table.remove(i)) {
        let slot = Arc::clone(&entry.2);
        table.push_back(entry);
        return slot;
    }
    let slot = SharedSlot::default();
    table.push_back((file, key, Arc::clone(&slot)));
    let bytes = |slot: &SharedSlot| {
        slot.get()
            .and_then(Option::as_ref)
            .map_or(0, |messages| messages.byte_len())
    };
    let mut held: usize = table.iter().map(|(_, _, slot)| bytes(slot)).sum();
    let most = SHARED_CHUNKS_PER_THREAD * rayon::current_num_threads().max(1);
    while table.len() > 1 && (table.len() > most || held > SHARED_BYTES) {
        if let Some((_, _, oldest)) = table.pop_front() {
            // Saturating: a slot may be filled (outside the lock) after the count.
            held = held.saturating_sub(bytes(&oldest));
        }
    }
    slot
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
            .position(|(f, k, _)| *k == key && *f == self.id)
        {
            Some(i) => {
                let entry = cache.entries.remove(i).ok_or_else(missing)?;
                cache.entries.push_back(entry);
            }
            None => {
                let messages = self.load_shared(key).map_err(|reason| match reason {
                    LoadError::Source(e) => e,
                    LoadError::Missing => missing(),
                })?;
                cache.entries.push_back((self.id, key, messages));
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

    /// The chunks [`read_message`](Self::read_message) has decompressed from this file so
    /// far, and their bytes (the speed bench divides them by the samples it built).
    pub fn decompressed(&self) -> Decompressed {
        Decompressed {
            chunks: self.decompressed.chunks.load(Ordering::Relaxed),
            bytes: self.decompressed.bytes.load(Ordering::Relaxed),
        }
    }

    /// [`load`](Self::load) through the shared table: a chunk another thread has
    /// decompressed lately (or is decompressing: this thread waits for it) is not
    /// decompressed again.
    fn load_shared(&self, key: CacheKey) -> Result<Arc<ChunkMessages>, LoadError> {
        let slot = shared_slot(self.id, key);
        let mut failed = None;
        let shared = slot.get_or_init(|| match self.load(key) {
            Ok(messages) => Some(Arc::new(messages)),
            Err(e) => {
                failed = Some(e);
                None
            }
        });
        match (shared, failed) {
            (Some(messages), _) => Ok(Arc::clone(messages)),
            (None, Some(e)) => Err(e),
            // Another thread failed on it: read it here, for this thread's own error.
            (None, None) => self.load(key).map(Arc::new),
        }
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
                let chunk_error = |source: ChunkError| {
                    LoadError::Source(SourceError::Chunk {
                        path: self.path.clone(),
                        offset: loc.offset,
                        source,
                    })
                };
                let (header, decoded) = self
                    .with_bytes_at(loc.offset + 9, loc.record_len - 9, |body| {
                        let Ok(records::Record::Chunk { header, data }) =
                            mcap::parse_record(op::CHUNK, body)
                        else {
                            return Err(chunk_error(ChunkError::NotAChunk));
                        };
                        let decoded = decode_chunk(&header, &data).map_err(chunk_error)?;
                        Ok((header, decoded))
                    })
                    .map_err(LoadError::Source)??;
                let counters = &self.decompressed;
                counters.chunks.fetch_add(1, Ordering::Relaxed);
                counters
                    .bytes
                    .fetch_add(header.uncompressed_size, Ordering::Relaxed);
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
