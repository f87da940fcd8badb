//! The persistent index cache: the [`FileIndex`] of every file indexed, stored under the
//! file's fingerprint ([`McapFile::fingerprint`]) so that the next opening of the same
//! file — by this process, the next run, a `--resume`, or another host reading the same
//! dataset — reads it instead of scanning the file; and, beside them, what is measured
//! once per drive from its data (the camera scan moments of `sample::timing`), stored
//! under a key derived from the fingerprints of the drive's files.
//!
//! One entry per file, named by the fingerprint: `<32 hex digits>.sfidx`; one per
//! drive measurement, named by its key with the extension of its [`EntryKind`]
//! (`.sfscan`). `entry` lays out an entry's bytes: they name their kind, the build that
//! wrote them ([`BUILD`], which changes whenever the indexing code does) and their own
//! key. Anything else — another build, a truncated or bit-flipped entry, an entry
//! renamed under another key, a payload that does not decode or does not fit its file —
//! is ignored with one line saying why and the file is scanned (the drive measured)
//! again, its entry then rewritten.
//!
//! The cache trusts nothing it reads (`files`, `access`): a symbolic link, a FIFO, a
//! device or an entry of an untrusted owner is never read; the directory is made `0700`
//! (or the configured mode of a shared cache) and refused when others may write it.
//! Entries are written to exclusively created temporary files of unpredictable names and
//! renamed into place, so that several processes or hosts — or pods whose processes all
//! have PID 1 — filling one cache at once each see either no entry or a whole one.
//! `upkeep` bounds the cache's size (least recently used first) and sweeps the
//! temporary files of writers that died.
//!
//! A file's entry holds only what the file's bytes determine (not the drive or the
//! configuration), so one cache serves every configuration; a drive's entries are keyed
//! by whatever else they depend on.

mod access;
mod entry;
mod files;
mod upkeep;

pub use access::{CacheAccess, CacheError, DEFAULT_MAX_MB, DEFAULT_MODE, uid_of};
pub use entry::{BUILD, EntryError, EntryKind};
pub use upkeep::{STALE_TEMP, Upkeep};

use super::file_index::FileIndex;
use crate::source::McapFile;
use serde::Serialize;
use serde::de::DeserializeOwned;
use std::io::Write;
use std::path::{Path, PathBuf};
use std::sync::atomic::{AtomicBool, AtomicU64, Ordering};

/// The version of what a [`FileIndex`] entry holds: raised whenever it changes in a way
/// the build identity ([`BUILD`]) would not catch (it always does for code in this crate).
pub const FORMAT_VERSION: u32 = 1;

/// The entries holding a [`FileIndex`].
pub const FILE_INDEX: EntryKind = EntryKind {
    magic: *b"SFINDEX\0",
    version: FORMAT_VERSION,
    extension: "sfidx",
    what: "index",
};

/// Entries this process could not store (a read-only or full cache).
static STORE_FAILURES: AtomicU64 = AtomicU64::new(0);
/// Entries this process stored.
static STORED: AtomicU64 = AtomicU64::new(0);

/// How many entries this process failed to store, and how many it stored.
pub fn stores() -> (u64, u64) {
    (
        STORE_FAILURES.load(Ordering::Relaxed),
        STORED.load(Ordering::Relaxed),
    )
}

/// A directory of index entries.
#[derive(Debug, Clone, PartialEq, Eq)]
pub struct IndexCache {
    dir: PathBuf,
    access: CacheAccess,
}

impl IndexCache {
    /// A private cache in `dir` (see [`prepare`](Self::prepare)).
    pub fn new(dir: impl Into<PathBuf>) -> Self {
        Self::with_access(dir, CacheAccess::default())
    }

    /// A cache in `dir` written and bounded as `access` says.
    pub fn with_access(dir: impl Into<PathBuf>, access: CacheAccess) -> Self {
        Self {
            dir: dir.into(),
            access,
        }
    }

    /// The per-user default: `$XDG_CACHE_HOME/superflow/index` (`~/.cache/...`), so
    /// that datasets on read-only mounts are cached too. `None` without a home.
    pub fn user_default(access: CacheAccess) -> Option<Self> {
        dirs::cache_dir().map(|d| Self::with_access(d.join("superflow").join("index"), access))
    }

    /// The directory.
    pub fn dir(&self) -> &Path {
        &self.dir
    }

    /// How it is written and bounded.
    pub fn access(&self) -> &CacheAccess {
        &self.access
    }

    /// Checks the directory before use, or makes it: an error when users it does not
    /// trust may write it. A directory that cannot be made is said once (WARN); the work
    /// goes on without storing, and [`stores`] counts what was not stored.
    pub fn prepare(&self) -> Result<(), CacheError> {
        match self.access.prepare(&self.dir) {
            Err(CacheError::Io { dir, source }) => {
                warn_unwritable(&dir, &source);
                Ok(())
            }
            other => other,
        }
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
        let loaded = self
            .load_entry::<FileIndex>(&FILE_INDEX, fingerprint)
            .and_then(|index| match index {
                Some(index) => index
                    .fits(file.len())
                    .map(|()| Some(index))
                    .map_err(EntryError::Inconsistent),
                None => Ok(None),
            });
        match loaded {
            Ok(index) => index.map(|index| index.moved_to(file.path())),
            Err(e) => {
                log_ignored(&e, file.path(), &entry, "indexing the file again");
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
        match files::read_entry(&self.path_of(kind, key), &self.access)? {
            Some(bytes) => entry::decode(kind, key, &bytes).map(Some),
            None => Ok(None),
        }
    }

    /// Stores `value` as the entry `key` of `kind`. A cache that cannot be written is
    /// said once per process (WARN) and counted ([`stores`]); the work goes on without it.
    pub fn store_entry<T: Serialize>(&self, kind: &EntryKind, key: u128, value: &T) {
        match self.write(kind, key, value) {
            Ok(()) => {
                STORED.fetch_add(1, Ordering::Relaxed);
            }
            Err(e) => {
                STORE_FAILURES.fetch_add(1, Ordering::Relaxed);
                warn_unwritable(&self.dir, &e);
            }
        }
    }

    fn write<T: Serialize>(&self, kind: &EntryKind, key: u128, value: &T) -> std::io::Result<()> {
        let bytes = entry::encode(kind, key, value).map_err(std::io::Error::other)?;
        if !self.dir.is_dir() {
            self.access.make(&self.dir)?;
        }
        let stem = format!(".{key:032x}.{}", kind.extension);
        let (tmp, mut file) = files::create_temp(&self.dir, &stem, &self.access)?;
        let written = file
            .write_all(&bytes)
            .and_then(|()| std::fs::rename(&tmp, self.path_of(kind, key)));
        if written.is_err() {
            let _ = std::fs::remove_file(&tmp);
        }
        written
    }

    /// Sweeps the temporary files of dead writers and evicts the least recently used
    /// entries beyond the size bound; with `prune`, first removes the entries of these
    /// kinds that this build cannot use (another build, damaged, misnamed).
    pub fn upkeep(&self, prune: Option<&[&EntryKind]>) -> std::io::Result<Upkeep> {
        upkeep::upkeep(&self.dir, &self.access, prune)
    }

    /// [`upkeep`](Self::upkeep) without pruning, when this process stored entries since
    /// the last one: a start that only read the cache lists no directory.
    pub fn upkeep_if_grown(&self) {
        static AT: AtomicU64 = AtomicU64::new(0);
        let stored = STORED.load(Ordering::Relaxed);
        if AT.swap(stored, Ordering::Relaxed) == stored {
            return;
        }
        match self.upkeep(None) {
            Ok(done) if done.evicted + done.temps_removed > 0 => tracing::info!(
                dir = %self.dir.display(),
                evicted = done.evicted,
                stale_temporary_files = done.temps_removed,
                entries = done.entries,
                mb = done.bytes >> 20,
                bound_mb = self.access.max_bytes >> 20,
                "index cache kept within its bound"
            ),
            Ok(_) => {}
            Err(e) => tracing::debug!(dir = %self.dir.display(), "index cache upkeep: {e}"),
        }
    }
}

/// Says once per process that the cache at `dir` cannot be written.
fn warn_unwritable(dir: &Path, e: &std::io::Error) {
    static SAID: AtomicBool = AtomicBool::new(false);
    if !SAID.swap(true, Ordering::Relaxed) {
        tracing::warn!(dir = %dir.display(), "the index cache cannot be written ({e}); files will be indexed again at the next start");
    }
}

/// One line saying why the entry `entry` of `file` is not used: WARN for what nobody
/// but another user or an attacker puts there, INFO for what versions and damage do.
pub fn log_ignored(e: &EntryError, file: &Path, entry: &Path, then: &str) {
    let suspicious = matches!(
        e,
        EntryError::Symlink
            | EntryError::NotAFile(_)
            | EntryError::Owner { .. }
            | EntryError::TooLarge(_)
            | EntryError::Key(_)
            | EntryError::Inconsistent(_)
    );
    if suspicious {
        tracing::warn!(file = %file.display(), entry = %entry.display(), "index cache entry ignored: {e}; {then}");
    } else {
        tracing::info!(file = %file.display(), entry = %entry.display(), "index cache entry ignored: {e}; {then}");
    }
}
