//! Random access: [`McapFile::read_message`] fetches one message by location through a
//! [`ChunkCache`] of a few decompressed chunks (memory stays bounded whatever the file
//! size).
//!
//! Each thread keeps its own cache, and behind them all sits one small shared table of
//! the chunks decompressed last ([`SHARED_CHUNKS_PER_THREAD`] per thread): the parts of
//! one sample run on several threads, and without it each thread would decompress the
//! sample's chunks again. A thread that wants
//! a chunk another is decompressing waits for it instead of decompressing it too.
//!
//! A chunk is decoded whole and checked against its CRC the first time the file is read
//! there; a zstd chunk read again with the same record
//! ([`CheckedChunks`](super::tally::CheckedChunks)) is decoded only up to the messages
//! asked for ([`PartialChunk`]): a sample needs only a part of the bytes of the chunks it
//! touches.

use super::chunk::{ChunkError, ChunkMessages, decode_chunk};
use super::error::SourceError;
use super::file::McapFile;
use super::framing::{MAX_RECORD_BYTES, record_len};
use super::message::{MessageLoc, MessageRef};
use super::partial::PartialChunk;
use super::tally::Decompressed;
use mcap::records::{self, op};
use std::borrow::Cow;
use std::collections::VecDeque;
use std::sync::atomic::{AtomicU64, AtomicUsize, Ordering};
use std::sync::{Arc, Mutex, OnceLock};

/// A few decompressed chunks, most recent last, for random access.
#[derive(Debug)]
pub struct ChunkCache {
    capacity: usize,
    pub(super) entries: VecDeque<(u64, CacheKey, Arc<Held>)>,
}

/// What a cache entry holds: a chunk decoded whole (or one message outside chunks), or a
/// zstd chunk decoded as far as it has been read ([`PartialChunk`]).
#[derive(Debug)]
pub(super) enum Held {
    Whole(ChunkMessages),
    Partial(PartialChunk),
}

impl Held {
    /// Bytes held.
    fn byte_len(&self) -> usize {
        match self {
            Held::Whole(messages) => messages.byte_len(),
            Held::Partial(chunk) => chunk.byte_len(),
        }
    }

    /// Message `index`: header and payload (`None` if there is no such message);
    /// `decoded` counts the bytes a partial chunk decodes for it.
    fn get(
        &self,
        index: usize,
        decoded: &AtomicU64,
    ) -> Result<Option<(records::MessageHeader, &[u8])>, ChunkError> {
        match self {
            Held::Whole(messages) => Ok(messages.get(index).map(|(h, data)| (*h, data))),
            Held::Partial(chunk) => chunk.get(index, decoded),
        }
    }
}

/// Chunks the shared table keeps per thread of the pool, the oldest leaving first:
/// enough for the threads building one sample to meet on its chunks, too few to keep a
/// drive's chunks from one sample to the next (samples come in shuffled order; a real
/// dataset is far larger than any cache, and the bench must not look better than that).
const SHARED_CHUNKS_PER_THREAD: usize = 4;

/// Decompressed bytes the shared table keeps at most (chunks of the usual 0.5–4 MiB
/// leave by number first; larger ones by size).
const SHARED_BYTES: usize = 64 << 20;

/// Chunks the shared table keeps per open block of the `blocks` order: the samples of a
/// block come back to the chunks of the frames they share (the other cameras of a frame
/// are in the chunk its first sample decompressed).
const SHARED_CHUNKS_PER_BLOCK: usize = 4;

/// Bytes the shared table may hold per open block.
const SHARED_BYTES_PER_BLOCK: usize = 8 << 20;

/// Blocks served side by side ([`keep_chunks_for_blocks`]); 0 under the `global` order.
static OPEN_BLOCKS: AtomicUsize = AtomicUsize::new(0);

/// Sizes the shared table for `open` blocks served side by side (the `blocks` order):
/// [`SHARED_CHUNKS_PER_BLOCK`] chunks and [`SHARED_BYTES_PER_BLOCK`] each, when that is
/// more than the table holds for the threads.
pub fn keep_chunks_for_blocks(open: usize) {
    OPEN_BLOCKS.fetch_max(open, Ordering::Relaxed);
}

/// A chunk in the shared table: set once by the thread that decompresses it (`None` if
/// that failed: each thread then reads it itself and reports its own error).
type SharedSlot = Arc<OnceLock<Option<Arc<Held>>>>;

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
    let blocks = OPEN_BLOCKS.load(Ordering::Relaxed);
    let most = (SHARED_CHUNKS_PER_THREAD * rayon::current_num_threads().max(1))
        .max(SHARED_CHUNKS_PER_BLOCK * blocks);
    let most_bytes = SHARED_BYTES.max(SHARED_BYTES_PER_BLOCK * blocks);
    while table.len() > 1 && (table.len() > most || held > most_bytes) {
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
        let (_, _, held) = cache.entries.back().ok_or_else(missing)?;
        let (header, data) = held
            .get(index, &self.decompressed.bytes)
            .map_err(|source| SourceError::Chunk {
                path: self.path.clone(),
                offset: match key {
                    CacheKey::Chunk(chunk) => {
                        self.chunks.get(chunk as usize).map_or(0, |c| c.offset)
                    }
                    CacheKey::Direct(offset) => offset,
                },
                source,
            })?
            .ok_or_else(missing)?;
        let channel = self.channels.get(&header.channel_id).ok_or_else(missing)?;
        Ok(MessageRef::new(channel, &header, data, loc))
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
    fn load_shared(&self, key: CacheKey) -> Result<Arc<Held>, LoadError> {
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
    fn load(&self, key: CacheKey) -> Result<Held, LoadError> {
        match key {
            CacheKey::Direct(offset) => {
                let mut head = [0u8; 9];
                self.read_into(&mut head, offset)
                    .map_err(LoadError::Source)?;
                let body_len = record_len(&head);
                if head[0] != op::MESSAGE || body_len > MAX_RECORD_BYTES {
                    return Err(LoadError::Missing);
                }
                let body = self
                    .read_exact_at(offset.saturating_add(9), body_len)
                    .map_err(LoadError::Source)?;
                match mcap::parse_record(op::MESSAGE, &body) {
                    Ok(records::Record::Message { header, .. }) => {
                        Ok(Held::Whole(ChunkMessages::single(header, body)))
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
                let body_len = loc
                    .record_len
                    .checked_sub(9)
                    .ok_or_else(|| chunk_error(ChunkError::NotAChunk))?;
                let at = loc.offset.saturating_add(9);
                // A chunk checked before is most likely decoded on demand, keeping its
                // compressed bytes: read it into a buffer of its own, which the decoder
                // then keeps, instead of the scratch buffer it would be copied out of.
                let held = if self.checked.contains(chunk) {
                    let body = self
                        .read_owned_at(at, body_len)
                        .map_err(LoadError::Source)?;
                    self.chunk_from(chunk, Body::Owned(body))
                } else {
                    self.with_bytes_at(at, body_len, |body| {
                        self.chunk_from(chunk, Body::Borrowed(body))
                    })
                    .map_err(LoadError::Source)?
                };
                let held = held.map_err(chunk_error)?;
                self.decompressed.chunks.fetch_add(1, Ordering::Relaxed);
                Ok(held)
            }
        }
    }
}

/// A chunk record's bytes as read: in the thread's scratch buffer, or in a buffer of
/// their own that a chunk decoded on demand can keep.
enum Body<'a> {
    Borrowed(&'a [u8]),
    Owned(Vec<u8>),
}

impl McapFile {
    /// Chunk number `chunk` from its record's `body`: decoded on demand when it was
    /// checked before with this very record, else decoded whole and checked.
    fn chunk_from(&self, chunk: u32, body: Body<'_>) -> Result<Held, ChunkError> {
        let bytes: &[u8] = match &body {
            Body::Borrowed(bytes) => bytes,
            Body::Owned(bytes) => bytes,
        };
        let Ok(records::Record::Chunk { header, data }) = mcap::parse_record(op::CHUNK, bytes)
        else {
            return Err(ChunkError::NotAChunk);
        };
        // Only zstd chunks with a CRC: LZ4 decodes several times faster, and a chunk
        // without a CRC is decoded whole every time so that damage anywhere in it
        // rejects all of it.
        let on_demand = header.compression == "zstd" && header.uncompressed_crc != 0;
        // Over the whole record: header fields and compressed bytes.
        let fingerprint = on_demand.then(|| crc32fast::hash(bytes));
        if let Some(fingerprint) = fingerprint
            && self.checked.holds(chunk, fingerprint)
        {
            // Where the compressed bytes, borrowed from the record as parsed, lie in it.
            let inside = match &data {
                Cow::Borrowed(slice) => (slice.as_ptr() as usize)
                    .checked_sub(bytes.as_ptr() as usize)
                    .map(|start| start..start + slice.len())
                    .filter(|range| range.end <= bytes.len()),
                Cow::Owned(_) => None,
            };
            let size = header.uncompressed_size;
            let partial = match body {
                Body::Owned(record) if inside.is_some() => {
                    PartialChunk::within(size, record, inside.unwrap_or(0..0))?
                }
                _ => {
                    let len = data.len();
                    PartialChunk::within(size, data.into_owned(), 0..len)?
                }
            };
            return Ok(Held::Partial(partial));
        }
        let decoded = decode_chunk(&header, &data)?;
        if let Some(fingerprint) = fingerprint {
            self.checked.insert(chunk, fingerprint);
        }
        self.decompressed
            .bytes
            .fetch_add(header.uncompressed_size, Ordering::Relaxed);
        Ok(Held::Whole(decoded.messages))
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
