//! The persistent index cache: the [`FileIndex`] of every file indexed, stored under the
//! file's fingerprint ([`McapFile::fingerprint`]) so that the next opening of the same
//! file — by this process, the next run, a `--resume`, or another host reading the same
//! dataset — reads it instead of scanning the file; and, beside them, what is measured
//! once per drive from its data (the camera scan moments of `sample::timing`), stored
//! under a key derived from the fingerprints of the drive's files.
//!
//! One entry per file, named by the fingerprint: `<32 hex digits>.sfidx`; one per
//! drive measurement, named by its key with the extension of its [`EntryKind`]
//! (`.sfscan`). An entry is a magic, the entry format version, the writing pipeline's
//! version, the length and xxh3 hash of the payload, and the payload (the bincode of
//! the `FileIndex` or the measurement). Anything else — another version, a truncated or
//! bit-flipped entry, a payload that does not decode — is ignored with one INFO line and
//! the file is scanned (the drive measured) again, its entry then rewritten. Entries
//! are written to a temporary file and renamed into place, so that several processes or
//! hosts filling one cache at once each see either no entry or a whole one. A file's
//! entry holds only what the file's bytes determine (not the drive or the
//! configuration), so one cache serves every configuration; a drive's entries are keyed
//! by whatever else they depend on.

use super::file_index::FileIndex;
use crate::source::McapFile;
use serde::Serialize;
use serde::de::DeserializeOwned;
use std::io::Write;
use std::path::{Path, PathBuf};
use std::sync::atomic::{AtomicBool, Ordering};

/// The version of the entry format and of what a [`FileIndex`] holds: raised whenever
/// either changes (or indexing learns something else from the same bytes), so that no
/// older entry is read as a newer one.
pub const FORMAT_VERSION: u32 = 1;
/// The version of the pipeline writing the entries: a new release scans again, in case
/// its decoding changed without `FORMAT_VERSION` being raised.
const WRITER: &str = env!("CARGO_PKG_VERSION");

/// One kind of entry: its magic, the version of what it holds and its file extension.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub struct EntryKind {
    /// The first bytes of every entry of the kind.
    pub magic: [u8; 8],
    /// The version of the payload: raised whenever what it holds or how it is computed
    /// changes, so that no older entry is read as a newer one.
    pub version: u32,
    /// The entry files' extension, without the dot.
    pub extension: &'static str,
    /// What the entries hold, for log lines (`index`, `camera scan`).
    pub what: &'static str,
}

/// The entries holding a [`FileIndex`].
const FILE_INDEX: EntryKind = EntryKind {
    magic: *b"SFINDEX\0",
    version: FORMAT_VERSION,
    extension: "sfidx",
    what: "index",
};

/// A directory of index entries.
#[derive(Debug, Clone, PartialEq, Eq)]
pub struct IndexCache {
    dir: PathBuf,
}

/// Why an entry was not used.
#[derive(Debug, thiserror::Error)]
pub enum EntryError {
    /// It could not be read.
    #[error("unreadable ({0})")]
    Unreadable(std::io::Error),
    /// It does not begin with its kind's magic.
    #[error("bad magic: not a superflow {0} entry")]
    Magic(&'static str),
    /// It was written in another version of its kind.
    #[error("written in {what} format {found}, this pipeline reads {expected}")]
    Version {
        /// What the entries hold.
        what: &'static str,
        /// The entry's version.
        found: u32,
        /// The version this pipeline reads.
        expected: u32,
    },
    /// It was written by another release.
    #[error("written by superflow-pipeline {0}, this is {WRITER}")]
    Writer(String),
    /// It ends early.
    #[error("truncated: {0}")]
    Truncated(&'static str),
    /// Its payload does not hash to the stored hash.
    #[error("its checksum does not match its content (damaged)")]
    Checksum,
    /// Its payload does not decode.
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
        self.path_of(&FILE_INDEX, fingerprint)
    }

    /// The entry file of `key` among the entries of `kind`.
    pub fn path_of(&self, kind: &EntryKind, key: u128) -> PathBuf {
        self.dir.join(format!("{key:032x}.{}", kind.extension))
    }

    /// The stored index of `file` (fingerprint `fingerprint`), if a usable entry exists.
    pub(super) fn load(&self, file: &McapFile, fingerprint: u128) -> Option<FileIndex> {
        let entry = self.entry_path(fingerprint);
        match self.load_entry::<FileIndex>(&FILE_INDEX, fingerprint) {
            Ok(None) => None,
            Ok(Some(index)) if index.scanned.len() == file.len() => {
                Some(index.moved_to(file.path()))
            }
            Ok(Some(_)) => {
                tracing::info!(file = %file.path().display(), entry = %entry.display(), "index cache entry is of a file of another size; indexing the file again");
                None
            }
            Err(e) => {
                tracing::info!(file = %file.path().display(), entry = %entry.display(), "index cache entry ignored: {e}; indexing the file again");
                None
            }
        }
    }

    /// Stores the index of a file.
    pub(super) fn store(&self, fingerprint: u128, index: &FileIndex) {
        self.store_entry(&FILE_INDEX, fingerprint, index);
    }

    /// The value of the entry `key` of `kind`: `None` when there is none, an error
    /// saying why when there is one that cannot be used (the caller logs it and
    /// computes the value again).
    pub fn load_entry<T: DeserializeOwned>(
        &self,
        kind: &EntryKind,
        key: u128,
    ) -> Result<Option<T>, EntryError> {
        let bytes = match std::fs::read(self.path_of(kind, key)) {
            Ok(bytes) => bytes,
            Err(e) if e.kind() == std::io::ErrorKind::NotFound => return Ok(None),
            Err(e) => return Err(EntryError::Unreadable(e)),
        };
        decode(kind, &bytes).map(Some)
    }

    /// Stores `value` as the entry `key` of `kind`. A cache that cannot be written is
    /// said once per process (WARN) and otherwise ignored: the work goes on without it.
    pub fn store_entry<T: Serialize>(&self, kind: &EntryKind, key: u128, value: &T) {
        if let Err(e) = self.write(kind, key, value) {
            static SAID: AtomicBool = AtomicBool::new(false);
            if !SAID.swap(true, Ordering::Relaxed) {
                tracing::warn!(dir = %self.dir.display(), "the index cache cannot be written ({e}); files will be indexed again at the next start");
            }
        }
    }

    fn write<T: Serialize>(&self, kind: &EntryKind, key: u128, value: &T) -> std::io::Result<()> {
        let payload = bincode::serde::encode_to_vec(value, bincode::config::standard())
            .map_err(std::io::Error::other)?;
        let mut bytes = Vec::with_capacity(payload.len() + 64);
        bytes.extend_from_slice(&kind.magic);
        bytes.extend_from_slice(&kind.version.to_le_bytes());
        bytes.extend_from_slice(&(WRITER.len() as u16).to_le_bytes());
        bytes.extend_from_slice(WRITER.as_bytes());
        bytes.extend_from_slice(&(payload.len() as u64).to_le_bytes());
        bytes.extend_from_slice(&xxhash_rust::xxh3::xxh3_64(&payload).to_le_bytes());
        bytes.extend_from_slice(&payload);
        std::fs::create_dir_all(&self.dir)?;
        let entry = self.path_of(kind, key);
        // Unique per process and thread: two writers never share a temporary file.
        let tmp = self.dir.join(format!(
            ".{key:032x}.{}.{}.{:?}.tmp",
            kind.extension,
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

/// The value an entry of `kind` holds.
fn decode<T: DeserializeOwned>(kind: &EntryKind, bytes: &[u8]) -> Result<T, EntryError> {
    let mut r = Reader(bytes);
    if r.take(kind.magic.len(), "magic")? != kind.magic {
        return Err(EntryError::Magic(kind.what));
    }
    let version = u32::from_le_bytes(r.array("version")?);
    if version != kind.version {
        return Err(EntryError::Version {
            what: kind.what,
            found: version,
            expected: kind.version,
        });
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
    let (value, used) =
        bincode::serde::decode_from_slice::<T, _>(payload, bincode::config::standard())
            .map_err(|e| EntryError::Decode(e.to_string()))?;
    if used != payload.len() || !r.0.is_empty() {
        return Err(EntryError::Decode(format!(
            "bytes left over after the {}",
            kind.what
        )));
    }
    Ok(value)
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
