//! The persistent index cache: the [`FileIndex`] of every file indexed, stored under the
//! file's fingerprint ([`McapFile::fingerprint`]) so that the next opening of the same
//! file — by this process, the next run, a `--resume`, or another host reading the same
//! dataset — reads it instead of scanning the file.
//!
//! One entry per file, named by the fingerprint: `<32 hex digits>.sfidx`. An entry is a
//! magic, the entry format version, the writing pipeline's version, the length and
//! xxh3 hash of the payload, and the payload (the bincode of the `FileIndex`). Anything
//! else — another version, a truncated or bit-flipped entry, a payload that does not
//! decode — is ignored with one INFO line and the file is scanned again (its entry then
//! rewritten). Entries are written to a temporary file and renamed into place, so that
//! several processes or hosts filling one cache at once each see either no entry or a
//! whole one. The cache holds only what the file's bytes determine (not the drive or the
//! configuration), so one cache serves every configuration.

use super::file_index::FileIndex;
use crate::source::McapFile;
use std::io::Write;
use std::path::{Path, PathBuf};
use std::sync::atomic::{AtomicBool, Ordering};

/// The first bytes of every entry.
const MAGIC: &[u8; 8] = b"SFINDEX\0";
/// The version of the entry format and of what a [`FileIndex`] holds: raised whenever
/// either changes (or indexing learns something else from the same bytes), so that no
/// older entry is read as a newer one.
pub const FORMAT_VERSION: u32 = 1;
/// The version of the pipeline writing the entries: a new release scans again, in case
/// its decoding changed without `FORMAT_VERSION` being raised.
const WRITER: &str = env!("CARGO_PKG_VERSION");

/// A directory of index entries.
#[derive(Debug, Clone, PartialEq, Eq)]
pub struct IndexCache {
    dir: PathBuf,
}

/// Why an entry was not used.
#[derive(Debug, thiserror::Error)]
enum EntryError {
    #[error("not an index entry (bad magic)")]
    Magic,
    #[error("written in index format {0}, this pipeline reads {FORMAT_VERSION}")]
    Version(u32),
    #[error("written by superflow-pipeline {0}, this is {WRITER}")]
    Writer(String),
    #[error("truncated: {0}")]
    Truncated(&'static str),
    #[error("its checksum does not match its content (damaged)")]
    Checksum,
    #[error("its content does not decode: {0}")]
    Decode(String),
}

impl IndexCache {
    /// A cache in `dir` (made when the first entry is written).
    pub fn new(dir: impl Into<PathBuf>) -> Self {
        Self { dir: dir.into() }
    }

    /// The per-user default: `$XDG_CACHE_HOME/superflow/index` (`~/.cache/...`), so
    /// that datasets on read-only mounts are cached too. `None` without a home.
    pub fn user_default() -> Option<Self> {
        dirs::cache_dir().map(|d| Self::new(d.join("superflow").join("index")))
    }

    /// The directory.
    pub fn dir(&self) -> &Path {
        &self.dir
    }

    /// The entry file of a fingerprint.
    pub fn entry_path(&self, fingerprint: u128) -> PathBuf {
        self.dir.join(format!("{fingerprint:032x}.sfidx"))
    }

    /// The stored index of `file` (fingerprint `fingerprint`), if a usable entry exists.
    pub(super) fn load(&self, file: &McapFile, fingerprint: u128) -> Option<FileIndex> {
        let entry = self.entry_path(fingerprint);
        let bytes = match std::fs::read(&entry) {
            Ok(bytes) => bytes,
            Err(e) if e.kind() == std::io::ErrorKind::NotFound => return None,
            Err(e) => {
                tracing::info!(file = %file.path().display(), entry = %entry.display(), "index cache entry unreadable ({e}); indexing the file again");
                return None;
            }
        };
        match decode(&bytes) {
            Ok(index) if index.scanned.len() == file.len() => Some(index.moved_to(file.path())),
            Ok(_) => {
                tracing::info!(file = %file.path().display(), entry = %entry.display(), "index cache entry is of a file of another size; indexing the file again");
                None
            }
            Err(e) => {
                tracing::info!(file = %file.path().display(), entry = %entry.display(), "index cache entry ignored: {e}; indexing the file again");
                None
            }
        }
    }

    /// Stores the index of a file. A cache that cannot be written is said once per
    /// process (WARN) and otherwise ignored: indexing goes on without it.
    pub(super) fn store(&self, fingerprint: u128, index: &FileIndex) {
        if let Err(e) = self.write(fingerprint, index) {
            static SAID: AtomicBool = AtomicBool::new(false);
            if !SAID.swap(true, Ordering::Relaxed) {
                tracing::warn!(dir = %self.dir.display(), "the index cache cannot be written ({e}); files will be indexed again at the next start");
            }
        }
    }

    fn write(&self, fingerprint: u128, index: &FileIndex) -> std::io::Result<()> {
        let payload = bincode::serde::encode_to_vec(index, bincode::config::standard())
            .map_err(std::io::Error::other)?;
        let mut bytes = Vec::with_capacity(payload.len() + 64);
        bytes.extend_from_slice(MAGIC);
        bytes.extend_from_slice(&FORMAT_VERSION.to_le_bytes());
        bytes.extend_from_slice(&(WRITER.len() as u16).to_le_bytes());
        bytes.extend_from_slice(WRITER.as_bytes());
        bytes.extend_from_slice(&(payload.len() as u64).to_le_bytes());
        bytes.extend_from_slice(&xxhash_rust::xxh3::xxh3_64(&payload).to_le_bytes());
        bytes.extend_from_slice(&payload);
        std::fs::create_dir_all(&self.dir)?;
        let entry = self.entry_path(fingerprint);
        // Unique per process and thread: two writers never share a temporary file.
        let tmp = self.dir.join(format!(
            ".{fingerprint:032x}.{}.{:?}.tmp",
            std::process::id(),
            std::thread::current().id()
        ));
        let written = std::fs::File::create(&tmp).and_then(|mut f| f.write_all(&bytes));
        match written.and_then(|()| std::fs::rename(&tmp, &entry)) {
            Ok(()) => Ok(()),
            Err(e) => {
                let _ = std::fs::remove_file(&tmp);
                Err(e)
            }
        }
    }
}

/// The index an entry holds.
fn decode(bytes: &[u8]) -> Result<FileIndex, EntryError> {
    let mut r = Reader(bytes);
    if r.take(MAGIC.len(), "magic")? != MAGIC {
        return Err(EntryError::Magic);
    }
    let version = u32::from_le_bytes(r.array("version")?);
    if version != FORMAT_VERSION {
        return Err(EntryError::Version(version));
    }
    let writer_len = u16::from_le_bytes(r.array("writer")?);
    let writer = String::from_utf8_lossy(r.take(usize::from(writer_len), "writer")?).into_owned();
    if writer != WRITER {
        return Err(EntryError::Writer(writer));
    }
    let len = u64::from_le_bytes(r.array("length")?);
    let hash = u64::from_le_bytes(r.array("checksum")?);
    let payload = r.take(usize::try_from(len).unwrap_or(usize::MAX), "payload")?;
    if xxhash_rust::xxh3::xxh3_64(payload) != hash {
        return Err(EntryError::Checksum);
    }
    let (index, used) =
        bincode::serde::decode_from_slice::<FileIndex, _>(payload, bincode::config::standard())
            .map_err(|e| EntryError::Decode(e.to_string()))?;
    if used != payload.len() || !r.0.is_empty() {
        return Err(EntryError::Decode("bytes left over after the index".into()));
    }
    Ok(index)
}

/// The unread rest of an entry.
struct Reader<'a>(&'a [u8]);

impl<'a> Reader<'a> {
    fn take(&mut self, n: usize, what: &'static str) -> Result<&'a [u8], EntryError> {
        if self.0.len() < n {
            return Err(EntryError::Truncated(what));
        }
        let (head, tail) = self.0.split_at(n);
        self.0 = tail;
        Ok(head)
    }

    fn array<const N: usize>(&mut self, what: &'static str) -> Result<[u8; N], EntryError> {
        let mut out = [0u8; N];
        out.copy_from_slice(self.take(N, what)?);
        Ok(out)
    }
}
