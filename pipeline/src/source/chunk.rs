//! One chunk decompressed and split into records, rejected whole if anything in it fails
//! (CRC, decompression, a record), so corrupt bytes never reach a decoder. This is how
//! every chunk is read the first time; a zstd chunk that passed is read again, with the
//! same record (header and compressed bytes), only as far as its readers ask (`partial.rs`).

use super::framing::{FramingError, MAX_RECORD_BYTES, check_framing};
use mcap::records::{self, ChunkHeader};
use std::io::Read;
use std::ops::Range;

/// Why a chunk could not be used.
#[derive(Debug, thiserror::Error)]
pub enum ChunkError {
    /// The record at the chunk's offset is not a chunk.
    #[error("not a chunk record")]
    NotAChunk,
    /// An uncompressed size beyond [`MAX_RECORD_BYTES`].
    #[error("declared uncompressed size {size} is implausible")]
    ImplausibleSize {
        /// The declared size.
        size: u64,
    },
    /// The records of an uncompressed chunk are not framed within it.
    #[error("{source} at byte {} of the chunk's {records_len} bytes of records", .source.at())]
    Framing {
        /// Bytes of records in the chunk.
        records_len: usize,
        /// What is wrong.
        source: FramingError,
    },
    /// The records do not decompress to the declared size.
    #[error("{compression} records do not decompress: {source}")]
    Decompress {
        /// The chunk's compression.
        compression: String,
        /// What the decompressor said.
        source: std::io::Error,
    },
    /// An uncompressed chunk holds fewer bytes than it declares.
    #[error("declares {size} bytes of records but holds {have}")]
    Short {
        /// The declared size.
        size: u64,
        /// The bytes there are.
        have: u64,
    },
    /// The decompressed records do not match the chunk's CRC.
    #[error("CRC of the decompressed records is {actual:#010x}, the chunk says {expected:#010x}")]
    Crc {
        /// The chunk's CRC.
        expected: u32,
        /// The records' CRC.
        actual: u32,
    },
    /// A compression other than none, `lz4` or `zstd`.
    #[error("unsupported compression {0:?}")]
    Unsupported(String),
    /// mcap rejected a record in the chunk.
    #[error(transparent)]
    Mcap(#[from] mcap::McapError),
}

/// The messages of one decompressed chunk: its records' bytes, and per message its
/// header and where its payload lies in those bytes (no copy per message).
#[derive(Debug, Default)]
pub(super) struct ChunkMessages {
    /// The bytes the payloads lie in.
    bytes: Vec<u8>,
    /// Header and payload range in `bytes` of each message, in record order.
    messages: Vec<(records::MessageHeader, Range<usize>)>,
}

impl ChunkMessages {
    /// Bytes held.
    pub(super) fn byte_len(&self) -> usize {
        self.bytes.len()
    }

    /// One message outside any chunk, from its record's body.
    pub(super) fn single(header: records::MessageHeader, body: Vec<u8>) -> Self {
        let range = MESSAGE_HEADER_LEN.min(body.len())..body.len();
        Self {
            messages: vec![(header, range)],
            bytes: body,
        }
    }

    /// Message `index`: header and payload.
    pub(super) fn get(&self, index: usize) -> Option<(&records::MessageHeader, &[u8])> {
        let (header, range) = self.messages.get(index)?;
        Some((header, self.bytes.get(range.clone())?))
    }

    /// Every message's header and payload, in record order (the position is the index
    /// [`get`](Self::get) takes).
    pub(super) fn iter(&self) -> impl Iterator<Item = (&records::MessageHeader, &[u8])> {
        self.messages
            .iter()
            .map(|(header, range)| (header, self.bytes.get(range.clone()).unwrap_or_default()))
    }
}

/// The records of one chunk.
#[derive(Debug, Default)]
pub(super) struct DecodedChunk {
    /// Its messages, in order.
    pub messages: ChunkMessages,
    /// Its schema records: id, name, encoding, data.
    pub schemas: Vec<(u16, String, String, Vec<u8>)>,
    /// Its channel records.
    pub channels: Vec<records::Channel>,
}

/// Bytes of a message record's body before its payload: channel id (2), sequence (4),
/// log time (8), publish time (8).
pub(super) const MESSAGE_HEADER_LEN: usize = 22;

/// Decompresses a chunk and splits it into records. `header` and `records` are the
/// parsed chunk record (`records` still compressed).
///
/// The chunk is decompressed in one piece into one buffer of its declared uncompressed
/// size (at most [`MAX_RECORD_BYTES`]; a stream that ends short of it is an error, bytes
/// beyond it are not read, as in mcap's readers), checked against its CRC when it has
/// one, and its records are framed within it before mcap parses any (mcap subtracts
/// each record's length from what remains unchecked: an overflow panic in debug builds,
/// found by the fuzz target `mcap_drive`). Messages stay in that buffer, where mcap's
/// linear reader would copy the compressed bytes into its own buffer, decompress into
/// another, and copy each payload out once more.
pub(super) fn decode_chunk(
    header: &ChunkHeader,
    records: &[u8],
) -> Result<DecodedChunk, ChunkError> {
    if header.uncompressed_size > MAX_RECORD_BYTES {
        return Err(ChunkError::ImplausibleSize {
            size: header.uncompressed_size,
        });
    }
    let size = header.uncompressed_size as usize;
    let checked = header.uncompressed_crc != 0;
    let bytes = decompress(&header.compression, records, size, checked)?;
    if checked {
        let actual = crc32fast::hash(&bytes);
        if actual != header.uncompressed_crc {
            return Err(ChunkError::Crc {
                expected: header.uncompressed_crc,
                actual,
            });
        }
    }
    check_framing(&bytes, |_| true).map_err(|source| ChunkError::Framing {
        records_len: bytes.len(),
        source,
    })?;
    let mut chunk = DecodedChunk::default();
    let mut at = 0usize;
    while at < bytes.len() {
        // Framed above: a whole 9-byte head, then a body within the buffer.
        let opcode = bytes[at];
        let len = u64::from_le_bytes(bytes[at + 1..at + 9].try_into().unwrap_or_default());
        let body = at + 9..at + 9 + len as usize;
        match mcap::parse_record(opcode, &bytes[body.clone()])? {
            records::Record::Message { header, .. } => {
                let payload = body.start + MESSAGE_HEADER_LEN..body.end;
                chunk.messages.messages.push((header, payload));
            }
            records::Record::Schema { header, data } => {
                chunk
                    .schemas
                    .push((header.id, header.name, header.encoding, data.into_owned()))
            }
            records::Record::Channel(c) => chunk.channels.push(c),
            _ => {}
        }
        at = body.end;
    }
    chunk.messages.bytes = bytes;
    Ok(chunk)
}

/// The first `size` bytes `records` decompress to (`compression` as the chunk names it).
/// `checked`: the caller checks the result against the chunk's CRC, so an LZ4 frame's
/// own content checksum (xxHash32 of the same bytes) is not computed a second time.
fn decompress(
    compression: &str,
    records: &[u8],
    size: usize,
    checked: bool,
) -> Result<Vec<u8>, ChunkError> {
    let unreadable = |source: std::io::Error| ChunkError::Decompress {
        compression: compression.to_string(),
        source,
    };
    if compression == "zstd" {
        return zstd_frames(records, size).map_err(unreadable);
    }
    let mut out = vec![0u8; size];
    match compression {
        "" => {
            let body = records.get(..size).ok_or(ChunkError::Short {
                size: size as u64,
                have: records.len() as u64,
            })?;
            out.copy_from_slice(body);
        }
        "lz4" if checked => lz4_frames(records, &mut out).map_err(unreadable)?,
        "lz4" => lz4::Decoder::new(records)
            .and_then(|mut d| d.read_exact(&mut out))
            .map_err(unreadable)?,
        other => return Err(ChunkError::Unsupported(other.to_string())),
    }
    Ok(out)
}

thread_local! {
    /// One zstd decompression context per thread, reused from chunk to chunk.
    static ZSTD: std::cell::RefCell<Option<zstd::bulk::Decompressor<'static>>> =
        const { std::cell::RefCell::new(None) };
}

/// The zstd frames of `src`, decompressed in one call straight into a buffer of `size`
/// bytes (no streaming window to copy out of, no zeroing first); they must fill it
/// exactly.
pub(super) fn zstd_frames(src: &[u8], size: usize) -> std::io::Result<Vec<u8>> {
    let mut out = Vec::with_capacity(size);
    let written = ZSTD.with(|cell| {
        let mut slot = cell.borrow_mut();
        let context = match slot.as_mut() {
            Some(context) => context,
            None => slot.insert(zstd::bulk::Decompressor::new()?),
        };
        context.decompress_to_buffer(src, &mut out)
    })?;
    if written != size {
        return Err(std::io::Error::new(
            std::io::ErrorKind::UnexpectedEof,
            format!("{written} bytes decompressed, {size} declared"),
        ));
    }
    Ok(out)
}

/// Decompresses LZ4 frames from `src` until `out` is full, without computing or checking
/// the frames' content and block checksums (liblz4's `skipChecksums`; the chunk's CRC
/// covers the same bytes). Input that ends, or frames that end, before `out` is full is
/// an error; bytes after it are not read.
///
/// The frames' checksums are skipped because computing them (xxHash32 over every byte)
/// costs more than the LZ4 decoding itself, and checks nothing the CRC does not.
#[allow(unsafe_code)]
pub(super) fn lz4_frames(src: &[u8], out: &mut [u8]) -> std::io::Result<()> {
    use lz4::liblz4::{
        LZ4F_VERSION, LZ4F_createDecompressionContext, LZ4F_decompress,
        LZ4F_freeDecompressionContext, LZ4FDecompressOptions, LZ4FDecompressionContext,
        check_error,
    };

    /// Frees the context however the decoding ends.
    struct Context(LZ4FDecompressionContext);
    impl Drop for Context {
        fn drop(&mut self) {
            // SAFETY: the context was created by LZ4F_createDecompressionContext and is
            // freed once, here.
            unsafe {
                LZ4F_freeDecompressionContext(self.0);
            }
        }
    }

    let mut raw = LZ4FDecompressionContext(std::ptr::null_mut());
    // SAFETY: `raw` is a valid place for the new context's pointer.
    check_error(unsafe { LZ4F_createDecompressionContext(&mut raw, LZ4F_VERSION) })?;
    let context = Context(raw);
    // liblz4 1.10's LZ4F_decompressOptions_t: stableDst, skipChecksums, two reserved.
    let options = LZ4FDecompressOptions {
        stable_dst: 1,
        reserved: [1, 0, 0],
    };
    let (mut read, mut written) = (0usize, 0usize);
    while written < out.len() {
        let mut src_len = src.len() - read;
        let mut dst_len = out.len() - written;
        // SAFETY: the pointers and lengths describe the unread part of `src` and the
        // unwritten part of `out`, both alive and unaliased for the call; liblz4 reads
        // at most `src_len` and writes at most `dst_len` bytes and reports both back.
        check_error(unsafe {
            LZ4F_decompress(
                context.0,
                out.as_mut_ptr().add(written),
                &mut dst_len,
                src.as_ptr().add(read),
                &mut src_len,
                &options,
            )
        })?;
        read += src_len;
        written += dst_len;
        if src_len == 0 && dst_len == 0 {
            return Err(std::io::Error::new(
                std::io::ErrorKind::UnexpectedEof,
                format!("the frames end after {written} of {} bytes", out.len()),
            ));
        }
    }
    Ok(())
}
