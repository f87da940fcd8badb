//! What random access has done to one opening of a file, kept with its
//! [`McapFile`](super::McapFile): the chunks it decompressed ([`Decompressed`]) and those
//! it checked against their CRC ([`CheckedChunks`]).

use rustc_hash::FxHashMap;
use std::sync::Mutex;
use std::sync::atomic::AtomicU64;

/// What random access has decompressed from one file so far (all threads).
#[derive(Debug, Clone, Copy, Default, PartialEq, Eq)]
pub struct Decompressed {
    /// Chunks decompressed (a chunk served from a cache is not counted again).
    pub chunks: u64,
    /// The bytes decompressed from them: a chunk's whole size the first time, as far as
    /// it was read when read again.
    pub bytes: u64,
}

/// The counters behind [`McapFile::decompressed`](super::McapFile::decompressed).
#[derive(Debug, Default)]
pub(super) struct DecompressCounters {
    pub(super) chunks: AtomicU64,
    pub(super) bytes: AtomicU64,
}

/// The chunks this opening of a file has decoded whole and found to match their CRC,
/// each with a CRC-32 of its record (header and compressed bytes): read again with the
/// same record, a zstd chunk is decoded only as far as it is read
/// ([`PartialChunk`](super::partial::PartialChunk)),
/// since it decodes to the bytes its CRC was checked on.
#[derive(Debug, Default)]
pub(super) struct CheckedChunks(Mutex<FxHashMap<u32, u32>>);

impl CheckedChunks {
    fn lock(&self) -> std::sync::MutexGuard<'_, FxHashMap<u32, u32>> {
        // The map is consistent after any panic (single inserts and reads).
        self.0
            .lock()
            .unwrap_or_else(|poisoned| poisoned.into_inner())
    }

    /// Whether chunk `chunk` was checked with this record (`fingerprint`: a CRC-32 of it).
    pub(super) fn holds(&self, chunk: u32, fingerprint: u32) -> bool {
        self.lock().get(&chunk) == Some(&fingerprint)
    }

    /// Whether chunk `chunk` was checked with any record.
    pub(super) fn contains(&self, chunk: u32) -> bool {
        self.lock().contains_key(&chunk)
    }

    pub(super) fn insert(&self, chunk: u32, fingerprint: u32) {
        self.lock().insert(chunk, fingerprint);
    }
}
