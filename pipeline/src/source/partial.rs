//! A zstd chunk decoded only as far as its readers ask, block by block.
//!
//! A sample reads a few messages from each chunk it touches, and the bytes up to the end
//! of the last message it takes are only a part of what whole chunks decompress to. A
//! chunk is decoded whole, and its CRC checked,
//! the first time this process reads it ([`super::cache`]); it is decoded on demand only
//! when read again with the very same record (a CRC-32 of it is kept), so no
//! byte reaches a decoder that was not checked against the chunk's CRC once.
//!
//! zstd's buffer-less streaming API decodes one block (≤ 128 KiB) at a time straight into
//! the chunk's buffer; blocks refer back into the bytes before them, which stay where they
//! are, so decoding resumes where it stopped when a later read needs more.

use super::chunk::{ChunkError, MESSAGE_HEADER_LEN};
use super::framing::{FramingError, MAX_RECORD_BYTES, record_len};
use mcap::records::{self, op};
use std::ops::Range;
use std::sync::Mutex;
use std::sync::atomic::{AtomicU64, Ordering};
use zstd::zstd_safe::zstd_sys;

/// One zstd chunk, decoded as far as it has been read.
pub(super) struct PartialChunk {
    /// Holds the allocation `base` points into (`size` bytes; its length stays 0: the
    /// bytes are written through `base` only).
    _storage: Vec<u8>,
    /// Start of the buffer: the first `Progress::out` bytes are decoded and never written
    /// again; bytes after them are written only while `progress` is locked.
    base: *mut u8,
    /// The chunk's declared uncompressed size.
    size: usize,
    progress: Mutex<Progress>,
}

// SAFETY: the buffer behind `base` is owned by `_storage` and written only by the thread
// holding `progress`, and only past `Progress::out`; slices handed out cover bytes before
// `out` as published under that lock (the lock orders the writes before the reads).
#[allow(unsafe_code)]
unsafe impl Send for PartialChunk {}
// SAFETY: as for `Send`.
#[allow(unsafe_code)]
unsafe impl Sync for PartialChunk {}

impl std::fmt::Debug for PartialChunk {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.debug_struct("PartialChunk")
            .field("size", &self.size)
            .finish_non_exhaustive()
    }
}

/// How far a chunk is decoded.
struct Progress {
    decoder: BlockDecoder,
    /// The chunk record read from the file; its compressed records are
    /// `record[data.clone()]` (kept where they were read, not copied out).
    record: Vec<u8>,
    /// Where the compressed records lie in `record`.
    data: Range<usize>,
    /// Compressed bytes consumed.
    read: usize,
    /// Bytes decoded into the buffer.
    out: usize,
    /// Bytes split into whole records (≤ `out`).
    framed: usize,
    /// Header and payload range of each message framed so far, in record order.
    messages: Vec<(records::MessageHeader, Range<usize>)>,
    /// The last frame has ended (every byte is decoded), or decoding failed.
    finished: bool,
    /// Why decoding failed, for every later read that needs bytes past the failure.
    failed: Option<String>,
}

impl PartialChunk {
    /// A chunk of `size` uncompressed bytes whose zstd frames are `compressed`, nothing
    /// decoded yet.
    #[cfg(test)]
    pub(super) fn new(size: u64, compressed: Vec<u8>) -> Result<Self, ChunkError> {
        let data = 0..compressed.len();
        Self::within(size, compressed, data)
    }

    /// A chunk of `size` uncompressed bytes whose zstd frames are `record[data]` (the
    /// chunk record as read), nothing decoded yet.
    pub(super) fn within(
        size: u64,
        record: Vec<u8>,
        data: Range<usize>,
    ) -> Result<Self, ChunkError> {
        if record.get(data.clone()).is_none() {
            return Err(unreadable(std::io::Error::other(format!(
                "compressed bytes {data:?} outside a record of {} bytes",
                record.len()
            ))));
        }
        if size > MAX_RECORD_BYTES {
            return Err(ChunkError::ImplausibleSize { size });
        }
        let size = size as usize;
        let mut storage = Vec::with_capacity(size);
        let base = storage.as_mut_ptr();
        Ok(Self {
            _storage: storage,
            base,
            size,
            progress: Mutex::new(Progress {
                decoder: BlockDecoder::new().map_err(unreadable)?,
                record,
                data,
                read: 0,
                out: 0,
                framed: 0,
                messages: Vec::new(),
                finished: false,
                failed: None,
            }),
        })
    }

    /// Bytes held (decoded or not).
    pub(super) fn byte_len(&self) -> usize {
        self.size
    }

    /// Message `index`: header and payload, decoding the chunk up to it if need be
    /// (`decoded` counts the bytes this call decodes). `None` if the chunk has fewer
    /// messages.
    #[allow(unsafe_code)]
    pub(super) fn get(
        &self,
        index: usize,
        decoded: &AtomicU64,
    ) -> Result<Option<(records::MessageHeader, &[u8])>, ChunkError> {
        // A panic elsewhere while the lock was held leaves `out` and `messages`
        // consistent: bytes are counted only after they are written.
        let mut progress = self
            .progress
            .lock()
            .unwrap_or_else(|poisoned| poisoned.into_inner());
        while progress.messages.len() <= index && !progress.finished {
            let before = progress.out;
            let step = self.decode_block(&mut progress);
            decoded.fetch_add((progress.out - before) as u64, Ordering::Relaxed);
            if let Err(e) = step.and_then(|()| frame(&mut progress, self.base)) {
                progress.finished = true;
                progress.failed = Some(e.to_string());
                return Err(e);
            }
        }
        let Some((header, range)) = progress.messages.get(index).cloned() else {
            return match &progress.failed {
                Some(why) => Err(unreadable(std::io::Error::other(format!(
                    "an earlier read of this chunk failed: {why}"
                )))),
                None => Ok(None),
            };
        };
        debug_assert!(range.end <= progress.out);
        // SAFETY: `range` lies within the first `out` bytes (framing only takes records
        // that end by `out`), which were written before this lock was taken and are
        // never written again while `self` lives.
        let data = unsafe { std::slice::from_raw_parts(self.base.add(range.start), range.len()) };
        Ok(Some((header, data)))
    }

    /// Decodes the next block (or frame header) after `progress.out`; at the end of the
    /// input, checks that the frames filled the declared size and marks the chunk
    /// finished.
    #[allow(unsafe_code)]
    fn decode_block(&self, progress: &mut Progress) -> Result<(), ChunkError> {
        let Progress {
            decoder,
            record,
            data,
            read,
            out,
            finished,
            ..
        } = progress;
        let compressed = &record[data.clone()];
        loop {
            let mut want = decoder.next_input();
            if want == 0 {
                // Between frames (or before the first).
                if *read == compressed.len() {
                    *finished = true;
                    if *out != self.size {
                        return Err(unreadable(std::io::Error::new(
                            std::io::ErrorKind::UnexpectedEof,
                            format!("{} bytes decompressed, {} declared", *out, self.size),
                        )));
                    }
                    return Ok(());
                }
                decoder.begin().map_err(unreadable)?;
                want = decoder.next_input();
            }
            let src = compressed.get(*read..*read + want).ok_or_else(|| {
                unreadable(std::io::Error::new(
                    std::io::ErrorKind::UnexpectedEof,
                    format!("the frames end inside a block, after {} bytes", *out),
                ))
            })?;
            // SAFETY: `base + out .. base + size` is the unwritten part of the buffer,
            // written by nobody else while the lock is held; zstd writes at most
            // `size - out` bytes there and reads back-references only from the bytes
            // before it, which it wrote itself.
            let written = unsafe { decoder.decode(self.base.add(*out), self.size - *out, src) }
                .map_err(unreadable)?;
            *read += want;
            *out += written;
            if written > 0 || decoder.next_input() == 0 && *read == compressed.len() {
                return Ok(());
            }
        }
    }
}

/// Splits the decoded bytes after `progress.framed` into records, as far as whole
/// records reach, keeping the messages.
#[allow(unsafe_code)]
fn frame(progress: &mut Progress, base: *const u8) -> Result<(), ChunkError> {
    // SAFETY: the first `out` bytes are written and not written again (see `get`).
    let bytes = unsafe { std::slice::from_raw_parts(base, progress.out) };
    while let Some(head) = bytes.get(progress.framed..progress.framed + 9) {
        let at = progress.framed;
        let head: &[u8; 9] = head.try_into().unwrap_or(&[0; 9]);
        let len = record_len(head);
        let body_start = at + 9;
        let Some(body_end) = usize::try_from(len)
            .ok()
            .and_then(|len| body_start.checked_add(len))
        else {
            return Err(past_end(at, len, bytes.len()));
        };
        if body_end > bytes.len() {
            if progress.finished {
                return Err(past_end(at, len, bytes.len()));
            }
            break;
        }
        if head[0] == op::MESSAGE
            && let records::Record::Message { header, .. } =
                mcap::parse_record(op::MESSAGE, &bytes[body_start..body_end])?
        {
            let payload = body_start + MESSAGE_HEADER_LEN..body_end;
            progress.messages.push((header, payload));
        }
        progress.framed = body_end;
    }
    if progress.finished && progress.framed < bytes.len() {
        return Err(ChunkError::Framing {
            records_len: bytes.len(),
            source: FramingError::StrayBytes {
                at: progress.framed,
                left: bytes.len() - progress.framed,
            },
        });
    }
    Ok(())
}

fn past_end(at: usize, len: u64, records_len: usize) -> ChunkError {
    ChunkError::Framing {
        records_len,
        source: FramingError::PastEnd {
            at,
            len,
            left: records_len.saturating_sub(at + 9),
        },
    }
}

fn unreadable(source: std::io::Error) -> ChunkError {
    ChunkError::Decompress {
        compression: "zstd".to_string(),
        source,
    }
}

/// A zstd context in buffer-less streaming mode (`ZSTD_decompressContinue`).
///
/// Contexts are reused: creating one allocates and initialises libzstd's tables and
/// buffers, and a sample opens a chunk decoder for every chunk it reads again. A dropped decoder goes back to
/// [`IDLE_DECODERS`] (up to [`MAX_IDLE_DECODERS`]); [`BlockDecoder::new`] takes one
/// from there and starts a frame on it, which resets whatever state it was left in.
struct BlockDecoder(*mut zstd_sys::ZSTD_DCtx);

/// Contexts of dropped decoders, for the next chunk.
static IDLE_DECODERS: Mutex<Vec<IdleContext>> = Mutex::new(Vec::new());

/// Idle contexts kept at most (each ~100 KiB); more are freed.
const MAX_IDLE_DECODERS: usize = 64;

/// A context no decoder holds.
struct IdleContext(*mut zstd_sys::ZSTD_DCtx);

// SAFETY: an idle context is reachable only through the pool's lock, and libzstd keeps
// no thread-local state for it.
#[allow(unsafe_code)]
unsafe impl Send for IdleContext {}

fn idle_decoders() -> std::sync::MutexGuard<'static, Vec<IdleContext>> {
    // The list is consistent after any panic (single pushes and pops).
    IDLE_DECODERS
        .lock()
        .unwrap_or_else(|poisoned| poisoned.into_inner())
}

// SAFETY: the context is used by one thread at a time (it lives behind the chunk's
// lock) and libzstd keeps no thread-local state for it.
#[allow(unsafe_code)]
unsafe impl Send for BlockDecoder {}

#[allow(unsafe_code)]
impl BlockDecoder {
    fn new() -> std::io::Result<Self> {
        let idle = idle_decoders().pop();
        let context = match idle {
            Some(IdleContext(context)) => context,
            // SAFETY: creates a context or returns null.
            None => unsafe { zstd_sys::ZSTD_createDCtx() },
        };
        if context.is_null() {
            return Err(std::io::Error::other("ZSTD_createDCtx failed"));
        }
        let decoder = Self(context);
        decoder.begin()?;
        Ok(decoder)
    }

    /// Starts a frame.
    fn begin(&self) -> std::io::Result<()> {
        // SAFETY: a live context.
        check(unsafe { zstd_sys::ZSTD_decompressBegin(self.0) }).map(drop)
    }

    /// The exact number of input bytes the next step takes (0: the frame has ended).
    fn next_input(&self) -> usize {
        // SAFETY: a live context.
        unsafe { zstd_sys::ZSTD_nextSrcSizeToDecompress(self.0) }
    }

    /// Decodes `src` (exactly [`next_input`](Self::next_input) bytes) into `dst`;
    /// returns the bytes written.
    ///
    /// # Safety
    /// `dst` must be valid for `capacity` bytes of writes and be preceded, in the same
    /// allocation, by every byte this frame has decoded so far.
    unsafe fn decode(&self, dst: *mut u8, capacity: usize, src: &[u8]) -> std::io::Result<usize> {
        // SAFETY: the caller's promise on `dst`; `src` is a live slice.
        check(unsafe {
            zstd_sys::ZSTD_decompressContinue(
                self.0,
                dst.cast(),
                capacity,
                src.as_ptr().cast(),
                src.len(),
            )
        })
    }
}

impl Drop for BlockDecoder {
    #[allow(unsafe_code)]
    fn drop(&mut self) {
        let mut idle = idle_decoders();
        if idle.len() < MAX_IDLE_DECODERS {
            idle.push(IdleContext(self.0));
            return;
        }
        drop(idle);
        // SAFETY: created by ZSTD_createDCtx, held by this decoder only, freed once, here.
        unsafe {
            zstd_sys::ZSTD_freeDCtx(self.0);
        }
    }
}

/// libzstd's size_t result as a result.
#[allow(unsafe_code)]
fn check(code: usize) -> std::io::Result<usize> {
    // SAFETY: pure functions of the code.
    if unsafe { zstd_sys::ZSTD_isError(code) } == 0 {
        return Ok(code);
    }
    // SAFETY: libzstd returns a static, NUL-terminated string for any code.
    let name = unsafe { std::ffi::CStr::from_ptr(zstd_sys::ZSTD_getErrorName(code)) };
    Err(std::io::Error::new(
        std::io::ErrorKind::InvalidData,
        name.to_string_lossy().into_owned(),
    ))
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::source::chunk::decode_chunk;

    /// A chunk's records: `n` messages of varied sizes on channel 1.
    fn records(n: usize) -> Vec<u8> {
        let mut out = Vec::new();
        for i in 0..n {
            let payload: Vec<u8> = (0..(i * 7919) % 70_000)
                .map(|j| ((i * 31 + j / 13) % 251) as u8)
                .collect();
            let mut body = Vec::new();
            body.extend_from_slice(&1u16.to_le_bytes());
            body.extend_from_slice(&(i as u32).to_le_bytes());
            body.extend_from_slice(&(1000 + i as u64).to_le_bytes());
            body.extend_from_slice(&(2000 + i as u64).to_le_bytes());
            body.extend_from_slice(&payload);
            out.push(op::MESSAGE);
            out.extend_from_slice(&(body.len() as u64).to_le_bytes());
            out.extend_from_slice(&body);
        }
        out
    }

    fn header(records: &[u8], compressed: &[u8]) -> records::ChunkHeader {
        records::ChunkHeader {
            message_start_time: 0,
            message_end_time: 0,
            uncompressed_size: records.len() as u64,
            uncompressed_crc: crc32fast::hash(records),
            compression: "zstd".into(),
            compressed_size: compressed.len() as u64,
        }
    }

    #[test]
    fn messages_read_in_any_order_equal_the_whole_decode() {
        let plain = records(60);
        // Two frames, as a writer that flushes mid-chunk makes them.
        let (a, b) = plain.split_at(plain.len() / 3);
        let mut compressed = zstd::bulk::compress(a, 3).unwrap();
        compressed.extend(zstd::bulk::compress(b, 19).unwrap());
        let whole = decode_chunk(&header(&plain, &compressed), &compressed).unwrap();
        let partial = PartialChunk::new(plain.len() as u64, compressed).unwrap();
        let decoded = AtomicU64::new(0);
        let (first, _) = partial.get(3, &decoded).unwrap().unwrap();
        assert_eq!(first.sequence, 3);
        let after_first = decoded.load(Ordering::Relaxed);
        assert!(
            after_first < plain.len() as u64 / 2,
            "{after_first} of {} bytes decoded for message 3",
            plain.len()
        );
        for index in [40, 2, 59, 0, 17, 58, 41] {
            let (h, data) = partial.get(index, &decoded).unwrap().unwrap();
            let (wh, wdata) = whole.messages.get(index).unwrap();
            assert_eq!((&h, data), (wh, wdata), "message {index}");
        }
        assert!(partial.get(60, &decoded).unwrap().is_none());
        assert_eq!(decoded.load(Ordering::Relaxed), plain.len() as u64);
    }

    #[test]
    fn damage_is_an_error_not_a_panic() {
        let plain = records(20);
        let compressed = zstd::bulk::compress(&plain, 3).unwrap();
        let decoded = AtomicU64::new(0);
        // Cut short: the last messages are missing and reading them says so.
        let short = compressed[..compressed.len() * 2 / 3].to_vec();
        let partial = PartialChunk::new(plain.len() as u64, short).unwrap();
        assert!(partial.get(19, &decoded).is_err());
        let again = partial.get(19, &decoded).unwrap_err().to_string();
        assert!(
            again.contains("an earlier read of this chunk failed"),
            "{again}"
        );
        assert!(partial.get(0, &decoded).unwrap().is_some());
        // A declared size larger than the frames hold.
        let partial = PartialChunk::new(plain.len() as u64 + 5, compressed.clone()).unwrap();
        assert!(partial.get(19, &decoded).unwrap().is_some());
        assert!(partial.get(20, &decoded).is_err());
        // Smaller: zstd has no room for the last block.
        let partial = PartialChunk::new(plain.len() as u64 - 5, compressed.clone()).unwrap();
        assert!(partial.get(19, &decoded).is_err());
        // Garbage.
        let partial = PartialChunk::new(plain.len() as u64, vec![7; 300]).unwrap();
        assert!(partial.get(0, &decoded).is_err());
    }
    /// Decoders go back to the pool wherever their chunk stopped (mid-frame, after an
    /// error): the next chunk decodes from a fresh frame all the same, and compressed
    /// bytes inside a larger record are read where they lie.
    #[test]
    fn a_reused_decoder_starts_afresh_and_reads_inside_the_record() {
        let decoded = AtomicU64::new(0);
        for round in 0..3 {
            let plain = records(30 + round);
            let compressed = zstd::bulk::compress(&plain, 3).unwrap();
            let whole = decode_chunk(&header(&plain, &compressed), &compressed).unwrap();
            // Left mid-frame.
            let stopped = PartialChunk::new(plain.len() as u64, compressed.clone()).unwrap();
            assert!(stopped.get(5, &decoded).unwrap().is_some());
            drop(stopped);
            // Left after an error.
            let garbage = PartialChunk::new(plain.len() as u64, vec![7; 300]).unwrap();
            assert!(garbage.get(0, &decoded).is_err());
            drop(garbage);
            let mut record = vec![0xAB; 41];
            record.extend_from_slice(&compressed);
            record.extend_from_slice(&[0xCD; 17]);
            let data = 41..41 + compressed.len();
            let partial = PartialChunk::within(plain.len() as u64, record, data).unwrap();
            for index in [29, 0, 13] {
                let (h, data) = partial.get(index, &decoded).unwrap().unwrap();
                let (wh, wdata) = whole.messages.get(index).unwrap();
                assert_eq!((&h, data), (wh, wdata), "round {round}, message {index}");
            }
        }
        assert!(PartialChunk::within(10, vec![0; 5], 2..9).is_err());
    }
}
