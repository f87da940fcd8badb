//! One chunk decompressed and split into records, rejected whole if anything in it fails
//! (CRC, decompression, a record), so corrupt bytes never reach a decoder.

use super::MAX_RECORD_BYTES;
use super::framing::{FramingError, check_framing};
use mcap::records::{self, ChunkHeader, op};

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
    /// mcap rejected the chunk or a record in it (CRC, decompression, parsing).
    #[error(transparent)]
    Mcap(#[from] mcap::McapError),
}

/// The messages of one decompressed chunk: channel id, header, payload.
pub(super) type ChunkMessages = Vec<(u16, records::MessageHeader, Vec<u8>)>;

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

/// Decompresses a chunk and splits it into records. `header` and `records` are the
/// parsed chunk record, `body` its whole body (after opcode and length).
///
/// Two checks that mcap's `ChunkReader` lacks (the fuzz target `mcap_drive` found both):
/// no record inside a chunk is longer than the chunk's uncompressed size (the chunk is
/// read by a linear reader with that record length limit; `ChunkReader` sized its buffer
/// from a corrupt length before decompressing and asked for exabytes), and the records
/// of an uncompressed chunk are framed within it (mcap subtracts each record's length
/// from what remains unchecked: an overflow panic in debug builds).
pub(super) fn decode_chunk(
    header: &ChunkHeader,
    records: &[u8],
    body: &[u8],
) -> Result<DecodedChunk, ChunkError> {
    use mcap::sans_io::{LinearReadEvent, LinearReader, LinearReaderOptions};
    if header.uncompressed_size > MAX_RECORD_BYTES {
        return Err(ChunkError::ImplausibleSize {
            size: header.uncompressed_size,
        });
    }
    if header.compression.is_empty() {
        check_framing(records, |_| true).map_err(|source| ChunkError::Framing {
            records_len: records.len(),
            source,
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
    let mut chunk = DecodedChunk::default();
    while let Some(event) = reader.next_event() {
        match event? {
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
            LinearReadEvent::Record { data, opcode } => match mcap::parse_record(opcode, data)? {
                records::Record::Message { header, data } => {
                    chunk
                        .messages
                        .push((header.channel_id, header, data.into_owned()))
                }
                records::Record::Schema { header, data } => {
                    chunk
                        .schemas
                        .push((header.id, header.name, header.encoding, data.into_owned()))
                }
                records::Record::Channel(c) => chunk.channels.push(c),
                _ => {}
            },
        }
    }
    Ok(chunk)
}
