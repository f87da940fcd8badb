//! [`McapFile`]: one MCAP file after its scan, and its reads through the shared
//! [`HandlePool`]. What it does is split by concern over the folder's other files: the
//! scan (`scan`, `summary`), random access (`cache`) and the stored facts (`facts`).

use super::damage::Damage;
use super::error::SourceError;
use super::framing::MAX_RECORD_BYTES;
use super::handles::{FileIdentity, HandlePool};
use super::message::{ChannelInfo, SchemaInfo};
use super::remote::RemoteObject;
use super::tally::{CheckedChunks, DecompressCounters};
use std::collections::{BTreeMap, HashMap};
use std::fs::File;
use std::os::unix::fs::FileExt;
use std::path::{Path, PathBuf};
use std::sync::{Arc, Mutex, OnceLock, PoisonError};

/// Where a chunk record is in its file.
#[derive(Debug, Clone)]
pub(super) struct ChunkLoc {
    pub(super) offset: u64,
    pub(super) record_len: u64,
}

/// An MCAP file after its scan: header, channels, chunk locations and damage.
#[derive(Debug)]
pub struct McapFile {
    pub(super) path: PathBuf,
    /// Unique to this opening of the file: what chunk caches key on (a file rewritten at
    /// the same path and opened again never gets the old one's chunks).
    pub(super) id: u64,
    /// What the file on disk is: it is read through [`HandlePool::global`], which may
    /// close it between reads and checks this on reopening. A file found replaced by a
    /// copy of the same content ([`McapFile::same_content`]) becomes the new identity.
    pub(super) identity: Mutex<FileIdentity>,
    /// The file's content digest once computed ([`McapFile::content_digest`]).
    pub(super) content: OnceLock<Option<u128>>,
    /// The handle a scan holds while it reads the file through; `None` afterwards.
    pub(super) scanning: Option<Arc<File>>,
    /// The object a file in an object store is read from (`None`: a local file, read
    /// through the handle pool).
    pub(super) remote: Option<Arc<RemoteObject>>,
    pub(super) len: u64,
    /// Header profile (`ros2`, `""`, ...).
    pub profile: String,
    /// Header library.
    pub library: String,
    pub(super) schemas: HashMap<u16, Arc<SchemaInfo>>,
    pub(super) channels: BTreeMap<u16, Arc<ChannelInfo>>,
    pub(super) chunks: Vec<ChunkLoc>,
    /// What the scan had to work around.
    pub damage: Vec<Damage>,
    /// Messages read per channel id.
    pub message_counts: BTreeMap<u16, u64>,
    /// Chunks random access has decompressed.
    pub(super) decompressed: DecompressCounters,
    /// Chunks random access has checked against their CRC.
    pub(super) checked: CheckedChunks,
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
    pub(super) fn handle(&self) -> Result<Arc<File>, SourceError> {
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

    /// Fills `buf` with the bytes at `offset`: every read of the file's bytes comes
    /// here, from a local file or an object.
    pub(super) fn read_into(&self, buf: &mut [u8], offset: u64) -> Result<(), SourceError> {
        match &self.remote {
            Some(object) => object.read_into(buf, offset),
            None => self
                .handle()?
                .read_exact_at(buf, offset)
                .map_err(|e| self.io(e)),
        }
    }

    /// Ends the scan: the scan's handle closes (later reads go through the pool, which
    /// may close the file between them) and an object stops reading ahead.
    pub(super) fn end_scan(&mut self) {
        self.scanning = None;
        if let Some(object) = &self.remote {
            object.set_sequential(false);
        }
    }

    /// After an index of the file is built: lets go of what its scan read, keeping the
    /// records that hold the messages at `locs` (what is read next) where a read finds
    /// them. Only an object keeps anything; nothing is read.
    pub fn release_scan(&self, locs: impl IntoIterator<Item = super::MessageLoc>) {
        if let Some(object) = &self.remote {
            let keep: Vec<std::ops::Range<u64>> = locs
                .into_iter()
                .filter_map(|loc| self.record_body(loc))
                .collect();
            object.release_scan(&keep);
        }
    }

    /// The body of the record holding the message at `loc`: what a read of its chunk
    /// asks for. `None` for a message outside chunks (read head first, then body).
    fn record_body(&self, loc: super::MessageLoc) -> Option<std::ops::Range<u64>> {
        match loc {
            super::MessageLoc::Chunk { chunk, .. } => {
                let c = self.chunks.get(chunk as usize)?;
                Some(c.offset.saturating_add(9)..c.offset.saturating_add(c.record_len))
            }
            super::MessageLoc::Direct { .. } => None,
        }
    }

    /// Starts reading the records that hold the messages at `locs` (what a sample is
    /// about to read) ahead of their use: an object prefetches them within the prefetch
    /// budget, a local file the pool holds open asks the kernel to read them into the
    /// page cache (a closed one stays closed: opening it would close another).
    pub fn will_read(&self, locs: impl IntoIterator<Item = super::MessageLoc>) {
        let mut ranges: Vec<std::ops::Range<u64>> = locs
            .into_iter()
            .filter_map(|loc| self.record_body(loc))
            .collect();
        ranges.sort_by_key(|r| r.start);
        ranges.dedup();
        match &self.remote {
            Some(object) => super::remote::start_prefetch(object, ranges),
            None => {
                let open = match &self.scanning {
                    Some(file) => Some(Arc::clone(file)),
                    None => HandlePool::global().open_now(self.id),
                };
                let Some(file) = open else { return };
                for r in ranges {
                    advise_will_need(&file, r);
                }
            }
        }
    }

    pub(super) fn io(&self, source: std::io::Error) -> SourceError {
        SourceError::Io {
            path: self.path.clone(),
            source,
        }
    }

    /// `f` of the `len` bytes at `offset` (at most [`MAX_RECORD_BYTES`]), read into this
    /// thread's scratch buffer: a chunk's compressed records are only decompressed, and
    /// reusing the buffer spares zeroing a fresh one before each read. Reads
    /// beyond [`SCRATCH_BYTES`] use a buffer of their own, so no thread keeps one huge.
    pub(super) fn with_bytes_at<T>(
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
            self.read_into(buf, offset)?;
            Ok(f(buf))
        })
    }

    /// The `len` bytes at `offset` (at most [`MAX_RECORD_BYTES`]) in a buffer of their
    /// own that is not zeroed first: every byte is read into it before it is returned.
    #[allow(unsafe_code)]
    pub(super) fn read_owned_at(&self, offset: u64, len: u64) -> Result<Vec<u8>, SourceError> {
        use std::os::fd::AsRawFd;
        let len = usize::try_from(len)
            .unwrap_or(usize::MAX)
            .min(MAX_RECORD_BYTES as usize);
        if self.remote.is_some() {
            // A network read dwarfs zeroing the buffer; this way it can come from the
            // prefetch.
            let mut buf = vec![0u8; len];
            self.read_into(&mut buf, offset)?;
            return Ok(buf);
        }
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

    pub(super) fn read_exact_at(&self, offset: u64, len: u64) -> Result<Vec<u8>, SourceError> {
        let mut buf = vec![
            0u8;
            usize::try_from(len)
                .unwrap_or(usize::MAX)
                .min(MAX_RECORD_BYTES as usize)
        ];
        self.read_into(&mut buf, offset)?;
        Ok(buf)
    }
}

/// Asks the kernel to read `range` of `file` into the page cache now.
#[allow(unsafe_code)]
fn advise_will_need(file: &File, range: std::ops::Range<u64>) {
    use std::os::fd::AsRawFd;
    let (Ok(offset), Ok(len)) = (
        libc::off_t::try_from(range.start),
        libc::off_t::try_from(range.end.saturating_sub(range.start)),
    ) else {
        return;
    };
    // SAFETY: an advisory call on a descriptor `file` keeps open; it touches no memory.
    unsafe {
        libc::posix_fadvise(file.as_raw_fd(), offset, len, libc::POSIX_FADV_WILLNEED);
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
