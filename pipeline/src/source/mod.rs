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
//!
//! This file holds the file and message types; the work is split by concern: `scan` (the
//! pass over the records), `summary` (the summary section, its framing checked first),
//! `framing` (records framed before mcap reads them), `chunk` (decompressing and splitting
//! one chunk), `cache` (random access), `damage` (what a scan worked around), `facts`
//! (what a scan learned, to be stored, and the fingerprint that says when it still holds)
//! and `handles` (the bounded pool of open files every read goes through).

mod cache;
mod chunk;
mod damage;
mod facts;
mod framing;
mod handles;
mod partial;
mod scan;
mod summary;

pub use cache::{ChunkCache, Decompressed};
pub use chunk::ChunkError;
pub use damage::Damage;
pub use facts::ScannedFile;
pub use framing::FramingError;
pub use handles::{FileIdentity, HandlePool, default_max_open_files, raise_open_file_limit};

use std::collections::{BTreeMap, HashMap};
use std::fs::File;
use std::os::unix::fs::FileExt;
use std::path::{Path, PathBuf};
use std::sync::{Arc, Mutex, OnceLock, PoisonError};

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
    #[error("{path}: chunk at byte {offset}: {source}")]
    Chunk {
        /// The file.
        path: PathBuf,
        /// Offset of the chunk record.
        offset: u64,
        /// What failed.
        source: ChunkError,
    },
    /// The file at this path is no longer the one scanned, nor a copy of it (its size,
    /// header, summary or chunks differ, or it has no summary to compare): its index
    /// would point at the wrong bytes.
    #[error(
        "{path}: the file was replaced on disk by one of other content since it was \
         indexed; its samples are skipped until the dataset is opened again"
    )]
    Replaced {
        /// The file.
        path: PathBuf,
    },
    /// The process ran out of file descriptors opening the file.
    #[error(
        "{path}: too many open files ({source}); lower `[ingest] max_open_files` \
         (now {limit}) in pipeline.toml or raise `ulimit -n`"
    )]
    TooManyOpenFiles {
        /// The file.
        path: PathBuf,
        /// The pool's limit when it happened.
        limit: usize,
        /// The I/O error (EMFILE or ENFILE).
        source: std::io::Error,
    },
}

/// Where a message lives in its file.
#[derive(
    Debug, Clone, Copy, PartialEq, Eq, Hash, PartialOrd, Ord, serde::Serialize, serde::Deserialize,
)]
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
#[derive(Debug, Clone, PartialEq, Eq, serde::Serialize, serde::Deserialize)]
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

impl<'a> MessageRef<'a> {
    /// The message of `header` on `channel`, its bytes `data`, found at `loc`.
    fn new(
        channel: &'a ChannelInfo,
        header: &mcap::records::MessageHeader,
        data: &'a [u8],
        loc: MessageLoc,
    ) -> Self {
        Self {
            channel,
            sequence: header.sequence,
            log_time: header.log_time,
            publish_time: header.publish_time,
            data,
            loc,
        }
    }
}

/// Where a chunk record is in its file.
#[derive(Debug, Clone)]
struct ChunkLoc {
    offset: u64,
    record_len: u64,
}

/// An MCAP file after its scan: header, channels, chunk locations and damage.
#[derive(Debug)]
pub struct McapFile {
    path: PathBuf,
    /// Unique to this opening of the file: what chunk caches key on (a file rewritten at
    /// the same path and opened again never gets the old one's chunks).
    id: u64,
    /// What the file on disk is: it is read through [`HandlePool::global`], which may
    /// close it between reads and checks this on reopening. A file found replaced by a
    /// copy of the same content ([`McapFile::same_content`]) becomes the new identity.
    identity: Mutex<FileIdentity>,
    /// The file's content digest once computed ([`McapFile::content_digest`]).
    content: OnceLock<Option<u128>>,
    /// The handle a scan holds while it reads the file through; `None` afterwards.
    scanning: Option<Arc<File>>,
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
    /// Chunks random access has decompressed.
    decompressed: cache::DecompressCounters,
    /// Chunks random access has checked against their CRC.
    checked: cache::CheckedChunks,
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

    /// The open file, from the scan's own handle or the shared pool (reopened if closed).
    fn handle(&self) -> Result<Arc<File>, SourceError> {
        match &self.scanning {
            Some(file) => Ok(Arc::clone(file)),
            None => HandlePool::global().get(self.id, &self.path, |file, found| {
                self.check_reopened(file, found)
            }),
        }
    }

    /// Whether the file reopened at this path (`found`) may be read as this one: the same
    /// file, or a copy of it with the same content (a re-sync writes new inodes). A file
    /// whose content changed is [`SourceError::Replaced`].
    fn check_reopened(&self, file: &File, found: &FileIdentity) -> Result<(), SourceError> {
        let mut identity = self.identity.lock().unwrap_or_else(PoisonError::into_inner);
        if *found == *identity {
            return Ok(());
        }
        if self.same_content(file, found.len) {
            tracing::info!(file = %self.path.display(), "the file was replaced by a copy of the same content; reading the copy");
            *identity = *found;
            return Ok(());
        }
        Err(SourceError::Replaced {
            path: self.path.clone(),
        })
    }

    fn io(&self, source: std::io::Error) -> SourceError {
        SourceError::Io {
            path: self.path.clone(),
            source,
        }
    }

    /// `f` of the `len` bytes at `offset` (at most [`MAX_RECORD_BYTES`]), read into this
    /// thread's scratch buffer: a chunk's compressed records are only decompressed, and
    /// reusing the buffer spares zeroing a fresh one before each read. Reads
    /// beyond [`SCRATCH_BYTES`] use a buffer of their own, so no thread keeps one huge.
    fn with_bytes_at<T>(
        &self,
        offset: u64,
        len: u64,
        f: impl FnOnce(&[u8]) -> T,
    ) -> Result<T, SourceError> {
        thread_local! {
            static SCRATCH: std::cell::RefCell<Vec<u8>> = const { std::cell::RefCell::new(Vec::new()) };
        }
        let len = usize::try_from(len)
            .unwrap_or(usize::MAX)
            .min(MAX_RECORD_BYTES as usize);
        if len > SCRATCH_BYTES {
            return self
                .read_exact_at(offset, len as u64)
                .map(|bytes| f(&bytes));
        }
        SCRATCH.with(|cell| {
            // `f` cannot reach this buffer again, but a nested read would find it taken:
            // it then reads into a buffer of its own.
            let Ok(mut scratch) = cell.try_borrow_mut() else {
                return self
                    .read_exact_at(offset, len as u64)
                    .map(|bytes| f(&bytes));
            };
            // Grown, never shrunk (below the cap): only new bytes are zeroed.
            if scratch.len() < len {
                scratch.resize(len, 0);
            }
            let buf = &mut scratch[..len];
            self.handle()?
                .read_exact_at(buf, offset)
                .map_err(|e| self.io(e))?;
            Ok(f(buf))
        })
    }

    /// The `len` bytes at `offset` (at most [`MAX_RECORD_BYTES`]) in a buffer of their
    /// own that is not zeroed first: every byte is read into it before it is returned.
    #[allow(unsafe_code)]
    fn read_owned_at(&self, offset: u64, len: u64) -> Result<Vec<u8>, SourceError> {
        use std::os::fd::AsRawFd;
        let len = usize::try_from(len)
            .unwrap_or(usize::MAX)
            .min(MAX_RECORD_BYTES as usize);
        let file = self.handle()?;
        let mut buf = Vec::<u8>::with_capacity(len);
        while buf.len() < len {
            let filled = buf.len();
            let spare = &mut buf.spare_capacity_mut()[..len - filled];
            let at = offset.saturating_add(filled as u64);
            let at = libc::off_t::try_from(at)
                .map_err(|_| self.io(std::io::Error::from(std::io::ErrorKind::InvalidInput)))?;
            // SAFETY: `pread` writes at most `spare.len()` bytes into `spare`, which is
            // this vector's unused capacity, and reads the descriptor `file` keeps open.
            let n = unsafe {
                libc::pread(file.as_raw_fd(), spare.as_mut_ptr().cast(), spare.len(), at)
            };
            match n {
                n if n < 0 => {
                    let e = std::io::Error::last_os_error();
                    if e.kind() != std::io::ErrorKind::Interrupted {
                        return Err(self.io(e));
                    }
                }
                0 => {
                    return Err(self.io(std::io::Error::new(
                        std::io::ErrorKind::UnexpectedEof,
                        "failed to fill whole buffer",
                    )));
                }
                // SAFETY: `pread` initialized the `n` bytes after the length.
                n => unsafe { buf.set_len(filled + n as usize) },
            }
        }
        Ok(buf)
    }

    fn read_exact_at(&self, offset: u64, len: u64) -> Result<Vec<u8>, SourceError> {
        let mut buf = vec![
            0u8;
            usize::try_from(len)
                .unwrap_or(usize::MAX)
                .min(MAX_RECORD_BYTES as usize)
        ];
        self.handle()?
            .read_exact_at(&mut buf, offset)
            .map_err(|e| self.io(e))?;
        Ok(buf)
    }
}

impl Drop for McapFile {
    /// Closes the file (once no reader holds it): its number is never asked for again.
    fn drop(&mut self) {
        HandlePool::global().forget(self.id);
    }
}

/// The largest read [`McapFile::with_bytes_at`] makes in a thread's reused buffer.
const SCRATCH_BYTES: usize = 16 << 20;

#[cfg(test)]
mod tests;
