//! The open input files: a bounded pool of handles shared by every [`McapFile`](super::McapFile).
//!
//! A dataset can have more files than the process may hold open (nuScenes: 850 drives and
//! two sidecars each, under a usual soft limit of 1 024 descriptors). So a file is opened
//! when it is read, through [`HandlePool`]: at most `limit` files stay open, the least
//! recently used one is closed when another must open, and reopening checks that the file
//! on disk is still the one that was scanned ([`FileIdentity`]).
//!
//! A handle is an `Arc<File>`: reads happen from many threads at once (`pread` on a shared
//! descriptor), and a reader keeps its handle valid for as long as it holds it. Eviction
//! drops only the pool's own reference; the descriptor closes when the last reader lets
//! go. The limit therefore bounds the pool, not the few handles readers hold beyond it
//! (at most one per reading thread).
//!
//! A file replaced on disk while it is open (a dataset re-sync writes new inodes; a
//! rewrite renames over the path) can only be read on through the descriptor opened
//! before: once closed, its content is gone. So the pool closes a file only when its path
//! still leads to it; one whose path moved on is *kept* open past the limit, as long as
//! the process has descriptors to spare ([`default_max_open_files`]), and read from there
//! for as long as the dataset holds it. A file replaced while it was closed is checked on
//! reopening instead (the same content is read on; other content is refused).

use super::error::SourceError;
use std::collections::HashMap;
use std::fs::File;
use std::os::unix::fs::MetadataExt;
use std::path::{Path, PathBuf};
use std::sync::{Arc, Mutex, OnceLock, PoisonError};

/// Descriptors left to everything else (sockets, shared memory, logs, the allocator).
const HEADROOM: u64 = 64;
/// The smallest default limit, however low the process's own.
const MIN_DEFAULT: usize = 16;

/// What a file was when it was first opened: a file replaced on disk (another inode) or
/// rewritten in place (another size, modification or status-change time) is not taken
/// for the old one unawares. The status-change time is what a rewrite that restores the
/// modification time (`touch -r`, `rsync --inplace`) cannot set back, on file systems
/// that keep it (ext4, XFS, Btrfs, NFS); on vfat, exFAT and many FUSE object stores it is
/// settable or absent, and a same-size rewrite with its times restored goes unseen.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Default)]
pub struct FileIdentity {
    /// Device.
    pub dev: u64,
    /// Inode.
    pub ino: u64,
    /// Size in bytes.
    pub len: u64,
    /// Modification time, seconds and nanoseconds since the epoch.
    pub mtime: (i64, i64),
    /// Status-change time, seconds and nanoseconds since the epoch.
    pub ctime: (i64, i64),
}

impl FileIdentity {
    fn of(meta: &std::fs::Metadata) -> Self {
        Self {
            dev: meta.dev(),
            ino: meta.ino(),
            len: meta.len(),
            mtime: (meta.mtime(), meta.mtime_nsec()),
            ctime: (meta.ctime(), meta.ctime_nsec()),
        }
    }
}

/// The default `[ingest] max_open_files`: the process's soft `RLIMIT_NOFILE` less
/// [`HEADROOM`] for everything else it opens and one per rayon thread (the handle each
/// reading thread may hold beyond the pool), and at least [`MIN_DEFAULT`].
pub fn default_max_open_files() -> usize {
    let soft = rustix::process::getrlimit(rustix::process::Resource::Nofile)
        .current
        .unwrap_or(u64::MAX);
    let readers = rayon::current_num_threads() as u64;
    usize::try_from(soft.saturating_sub(HEADROOM).saturating_sub(readers))
        .unwrap_or(usize::MAX)
        .max(MIN_DEFAULT)
}

/// The most descriptors [`raise_open_file_limit`] asks for: room for every file of a
/// large dataset (1 000 drives of a few files each), without a limit so high that code
/// walking every possible descriptor (in child processes, say) slows down.
const RAISED_LIMIT: u64 = 1 << 16;

/// Raises the process's soft limit on open files towards its hard limit (at most
/// [`RAISED_LIMIT`]), so that the pool's default holds every file of a dataset open: a
/// file replaced on disk can then always be read on from its first descriptor. Many
/// systems start processes at a soft limit of 1 024 under a hard limit far above it.
/// Returns the soft limit in force afterwards; call it before the pool is first used.
pub fn raise_open_file_limit() -> Option<u64> {
    use rustix::process::{Resource, getrlimit, setrlimit};
    let limits = getrlimit(Resource::Nofile);
    let soft = limits.current?;
    let target = limits.maximum.unwrap_or(u64::MAX).min(RAISED_LIMIT);
    if target <= soft {
        return Some(soft);
    }
    let raised = rustix::process::Rlimit {
        current: Some(target),
        maximum: limits.maximum,
    };
    match setrlimit(Resource::Nofile, raised) {
        Ok(()) => {
            tracing::debug!(from = soft, to = target, "raised the limit of open files");
            Some(target)
        }
        Err(e) => {
            tracing::debug!(soft, error = %e, "could not raise the limit of open files");
            Some(soft)
        }
    }
}

/// One open file of the pool.
#[derive(Debug)]
struct Entry {
    file: Arc<File>,
    /// When it was last handed out ([`Pool::tick`]); the smallest is closed first.
    used: u64,
    /// Where it was opened, and what it was then: closing it is safe only while the path
    /// still leads to this very file.
    path: PathBuf,
    identity: FileIdentity,
}

impl Entry {
    /// Whether `path` no longer leads to this file (replaced, rewritten or deleted).
    fn moved_on(&self) -> bool {
        std::fs::metadata(&self.path)
            .ok()
            .map(|meta| FileIdentity::of(&meta))
            != Some(self.identity)
    }
}

#[derive(Debug, Default)]
struct Pool {
    limit: usize,
    /// The most descriptors open and kept together: the process's own room.
    room: usize,
    tick: u64,
    open: HashMap<u64, Entry>,
    /// Files replaced on disk while open, held past the limit (see the module's notes).
    kept: HashMap<u64, Entry>,
}

impl Pool {
    /// Takes the least recently used files out until at most `keep` are open, and returns
    /// them: the caller closes or keeps each ([`HandlePool::close_or_keep`]) outside the
    /// lock, as that looks at the file system.
    #[must_use]
    fn shrink_to(&mut self, keep: usize) -> Vec<(u64, Entry)> {
        let mut out = Vec::new();
        while self.open.len() > keep {
            let Some(oldest) = self
                .open
                .iter()
                .min_by_key(|(_, e)| e.used)
                .map(|(key, _)| *key)
            else {
                break;
            };
            out.extend(self.open.remove_entry(&oldest));
        }
        out
    }
}

/// A bounded set of open files, keyed by the opening of a file ([`McapFile`](super::McapFile)
/// numbers each): the least recently used is closed when the limit is reached.
#[derive(Debug)]
pub struct HandlePool {
    pool: Mutex<Pool>,
}

impl HandlePool {
    /// A pool keeping at most `limit` files open (at least 1).
    pub fn new(limit: usize) -> Self {
        Self {
            pool: Mutex::new(Pool {
                limit: limit.max(1),
                room: limit.max(default_max_open_files()),
                ..Pool::default()
            }),
        }
    }

    /// The process's pool, its limit [`default_max_open_files`] until
    /// [`set_limit`](Self::set_limit) changes it.
    pub fn global() -> &'static HandlePool {
        static GLOBAL: OnceLock<HandlePool> = OnceLock::new();
        GLOBAL.get_or_init(|| HandlePool::new(default_max_open_files()))
    }

    fn lock(&self) -> std::sync::MutexGuard<'_, Pool> {
        self.pool.lock().unwrap_or_else(PoisonError::into_inner)
    }

    /// The most files kept open.
    pub fn limit(&self) -> usize {
        self.lock().limit
    }

    /// Keeps at most `limit` files open from now on (at least 1), closing the least
    /// recently used beyond it.
    pub fn set_limit(&self, limit: usize) {
        let evicted = {
            let mut pool = self.lock();
            pool.limit = limit.max(1);
            pool.room = pool.room.max(pool.limit);
            let keep = pool.limit;
            pool.shrink_to(keep)
        };
        self.close_or_keep(evicted);
    }

    /// How many files the pool holds open now, within its limit.
    pub fn open_count(&self) -> usize {
        self.lock().open.len()
    }

    /// How many files the pool holds open past its limit, because they were replaced on
    /// disk while open.
    pub fn kept_count(&self) -> usize {
        self.lock().kept.len()
    }

    /// Closes each file taken out of the pool whose path still leads to it; keeps the
    /// others open (the only way left to read them) while there is room.
    fn close_or_keep(&self, evicted: Vec<(u64, Entry)>) {
        for (key, entry) in evicted {
            if !entry.moved_on() {
                continue;
            }
            let mut pool = self.lock();
            let held = pool.open.len() + pool.kept.len();
            if held >= pool.room {
                tracing::warn!(
                    file = %entry.path.display(),
                    held,
                    "the file changed on disk while open, and no descriptor is left to keep \
                     it open: reads of it will be checked against what is on disk now"
                );
                continue;
            }
            tracing::warn!(
                file = %entry.path.display(),
                kept = pool.kept.len() + 1,
                "the file changed on disk while open: keeping the file first opened open, \
                 past the limit of open files, and reading on from it"
            );
            pool.kept.insert(key, entry);
        }
    }

    /// Opens `path` for the first time as `key`, returning the handle and what the file is.
    pub fn open_new(
        &self,
        key: u64,
        path: &Path,
    ) -> Result<(Arc<File>, FileIdentity), SourceError> {
        let (file, identity) = self.open_file(path)?;
        Ok((self.insert(key, file, path, identity), identity))
    }

    /// The handle of `key`, reopening `path` if the pool closed it; `check` says whether
    /// the file reopened (and what it is now) may be read as the one first opened.
    pub fn get(
        &self,
        key: u64,
        path: &Path,
        check: impl FnOnce(&File, &FileIdentity) -> Result<(), SourceError>,
    ) -> Result<Arc<File>, SourceError> {
        {
            let mut pool = self.lock();
            pool.tick += 1;
            let tick = pool.tick;
            if let Some(entry) = pool.open.get_mut(&key) {
                entry.used = tick;
                return Ok(Arc::clone(&entry.file));
            }
            if let Some(entry) = pool.kept.get(&key) {
                return Ok(Arc::clone(&entry.file));
            }
        }
        // Opened outside the lock: other threads go on reading meanwhile.
        let (file, found) = self.open_file(path)?;
        check(&file, &found)?;
        tracing::trace!(file = %path.display(), "reopened");
        Ok(self.insert(key, file, path, found))
    }

    /// The handle of `key` if the pool holds it open now, without opening it or making it
    /// more recently used: what advice to the kernel reads through, as opening files for
    /// it would close the ones samples are reading under a tight limit.
    pub fn open_now(&self, key: u64) -> Option<Arc<File>> {
        let pool = self.lock();
        pool.open
            .get(&key)
            .or_else(|| pool.kept.get(&key))
            .map(|entry| Arc::clone(&entry.file))
    }

    /// Forgets `key`, closing its file once no reader holds it.
    pub fn forget(&self, key: u64) {
        let mut pool = self.lock();
        pool.open.remove(&key);
        pool.kept.remove(&key);
    }

    fn open_file(&self, path: &Path) -> Result<(File, FileIdentity), SourceError> {
        let io = |source: std::io::Error| {
            if source.raw_os_error() == Some(rustix::io::Errno::MFILE.raw_os_error())
                || source.raw_os_error() == Some(rustix::io::Errno::NFILE.raw_os_error())
            {
                SourceError::TooManyOpenFiles {
                    path: path.to_path_buf(),
                    limit: self.limit(),
                    source,
                }
            } else {
                SourceError::Io {
                    path: path.to_path_buf(),
                    source,
                }
            }
        };
        let file = File::open(path).map_err(io)?;
        let meta = file.metadata().map_err(io)?;
        Ok((file, FileIdentity::of(&meta)))
    }

    /// Puts `file` in the pool as `key` (or takes the one another thread put there first),
    /// closing the least recently used beyond the limit.
    fn insert(&self, key: u64, file: File, path: &Path, identity: FileIdentity) -> Arc<File> {
        let (file, evicted) = {
            let mut pool = self.lock();
            pool.tick += 1;
            let tick = pool.tick;
            if let Some(entry) = pool.open.get_mut(&key) {
                entry.used = tick;
                return Arc::clone(&entry.file);
            }
            let keep = pool.limit - 1;
            let evicted = pool.shrink_to(keep);
            let file = Arc::new(file);
            pool.open.insert(
                key,
                Entry {
                    file: Arc::clone(&file),
                    used: tick,
                    path: path.to_path_buf(),
                    identity,
                },
            );
            (file, evicted)
        };
        self.close_or_keep(evicted);
        file
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use std::os::unix::fs::FileExt;

    fn files(n: usize) -> (std::path::PathBuf, Vec<std::path::PathBuf>) {
        let dir = std::env::temp_dir().join(format!(
            "superflow-handles-{}-{}",
            std::process::id(),
            std::time::SystemTime::now()
                .duration_since(std::time::UNIX_EPOCH)
                .map_or(0, |d| d.as_nanos())
        ));
        std::fs::create_dir_all(&dir).unwrap();
        let paths = (0..n)
            .map(|i| {
                let p = dir.join(format!("{i}.bin"));
                std::fs::write(&p, [i as u8; 16]).unwrap();
                p
            })
            .collect();
        (dir, paths)
    }

    /// A reopening check that takes only the very file first opened.
    fn must_be(
        identity: FileIdentity,
        path: &std::path::Path,
    ) -> impl FnOnce(&File, &FileIdentity) -> Result<(), SourceError> {
        let path = path.to_path_buf();
        move |_, found| {
            if *found == identity {
                Ok(())
            } else {
                Err(SourceError::Replaced { path })
            }
        }
    }

    #[test]
    fn closes_the_least_recently_used_first() {
        let (dir, paths) = files(4);
        let pool = HandlePool::new(3);
        let ids: Vec<FileIdentity> = paths
            .iter()
            .take(3)
            .enumerate()
            .map(|(i, p)| pool.open_new(i as u64, p).unwrap().1)
            .collect();
        // 0 used again: 1 is now the least recently used.
        let zero = pool.get(0, &paths[0], must_be(ids[0], &paths[0])).unwrap();
        drop(zero);
        pool.open_new(3, &paths[3]).unwrap();
        assert_eq!(pool.open_count(), 3);
        let open: Vec<u64> = {
            let mut keys: Vec<u64> = pool.lock().open.keys().copied().collect();
            keys.sort_unstable();
            keys
        };
        assert_eq!(open, [0, 2, 3]);
        // 1 reopens (same file), closing 2, now the least recently used.
        pool.get(1, &paths[1], must_be(ids[1], &paths[1])).unwrap();
        let mut keys: Vec<u64> = pool.lock().open.keys().copied().collect();
        keys.sort_unstable();
        assert_eq!(keys, [0, 1, 3]);
        pool.set_limit(1);
        assert_eq!(pool.open_count(), 1);
        std::fs::remove_dir_all(dir).unwrap();
    }

    #[test]
    fn a_look_at_the_open_files_opens_none_and_reorders_none() {
        let (dir, paths) = files(3);
        let pool = HandlePool::new(2);
        pool.open_new(0, &paths[0]).unwrap();
        pool.open_new(1, &paths[1]).unwrap();
        // 0 is the least recently used; looking at it keeps it so.
        assert!(pool.open_now(0).is_some());
        pool.open_new(2, &paths[2]).unwrap();
        assert!(pool.open_now(0).is_none(), "0 was closed first");
        assert!(pool.open_now(0).is_none(), "and a look does not reopen it");
        assert!(pool.open_now(1).is_some() && pool.open_now(2).is_some());
        assert_eq!(pool.open_count(), 2);
        std::fs::remove_dir_all(dir).unwrap();
    }

    #[test]
    fn a_reader_keeps_its_handle_after_eviction() {
        let (dir, paths) = files(2);
        let pool = HandlePool::new(1);
        let (held, _) = pool.open_new(0, &paths[0]).unwrap();
        pool.open_new(1, &paths[1]).unwrap();
        assert_eq!(pool.open_count(), 1);
        assert!(!pool.lock().open.contains_key(&0));
        let mut buf = [0u8; 16];
        held.read_exact_at(&mut buf, 0).unwrap();
        assert_eq!(buf, [0u8; 16]);
        std::fs::remove_dir_all(dir).unwrap();
    }

    #[test]
    fn a_replaced_file_is_refused_on_reopen() {
        let (dir, paths) = files(2);
        let pool = HandlePool::new(1);
        let (_, identity) = pool.open_new(0, &paths[0]).unwrap();
        pool.open_new(1, &paths[1]).unwrap();
        // Replaced by another file (another inode) at the same path.
        let other = dir.join("other.bin");
        std::fs::write(&other, [7u8; 16]).unwrap();
        std::fs::rename(&other, &paths[0]).unwrap();
        let err = pool
            .get(0, &paths[0], must_be(identity, &paths[0]))
            .unwrap_err();
        assert!(matches!(err, SourceError::Replaced { .. }), "{err}");
        assert!(err.to_string().contains("0.bin"), "{err}");
        // Rewritten in place with another size.
        let (_, identity) = pool.open_new(2, &paths[1]).unwrap();
        pool.open_new(3, &paths[0]).unwrap();
        std::fs::write(&paths[1], [1u8; 32]).unwrap();
        let err = pool
            .get(2, &paths[1], must_be(identity, &paths[1]))
            .unwrap_err();
        assert!(matches!(err, SourceError::Replaced { .. }), "{err}");
        std::fs::remove_dir_all(dir).unwrap();
    }

    /// A file replaced by other content (and one deleted) while open: the pool keeps
    /// each past its limit and reads on from it; one whose path still leads to it closes.
    #[test]
    fn a_file_changed_while_open_is_kept_and_read_on() {
        let (dir, paths) = files(4);
        let pool = HandlePool::new(1);
        let (_, identity) = pool.open_new(0, &paths[0]).unwrap();
        let other = dir.join("other.bin");
        std::fs::write(&other, [7u8; 16]).unwrap();
        std::fs::rename(&other, &paths[0]).unwrap();
        pool.open_new(1, &paths[1]).unwrap();
        assert_eq!((pool.open_count(), pool.kept_count()), (1, 1));
        let kept = pool
            .get(0, &paths[0], must_be(identity, &paths[0]))
            .unwrap();
        let mut buf = [9u8; 16];
        kept.read_exact_at(&mut buf, 0).unwrap();
        assert_eq!(buf, [0u8; 16], "the first file's bytes, not the new one's");
        // Deleted while open: kept as well.
        std::fs::remove_file(&paths[1]).unwrap();
        pool.open_new(2, &paths[2]).unwrap();
        assert_eq!((pool.open_count(), pool.kept_count()), (1, 2));
        let gone = pool
            .get(1, &paths[1], |_, _| panic!("not reopened"))
            .unwrap();
        gone.read_exact_at(&mut buf, 0).unwrap();
        assert_eq!(buf, [1u8; 16]);
        // Unchanged: closed as usual.
        pool.open_new(3, &paths[3]).unwrap();
        assert_eq!((pool.open_count(), pool.kept_count()), (1, 2));
        assert!(!pool.lock().open.contains_key(&2));
        // The file is forgotten (its dataset closed): the kept descriptor goes too.
        pool.forget(0);
        pool.forget(1);
        assert_eq!(pool.kept_count(), 0);
        std::fs::remove_dir_all(dir).unwrap();
    }

    #[test]
    fn the_open_file_limit_is_raised_within_the_hard_limit() {
        let soft = raise_open_file_limit();
        let now = rustix::process::getrlimit(rustix::process::Resource::Nofile);
        assert_eq!(soft, now.current);
        if let (Some(soft), Some(hard)) = (now.current, now.maximum) {
            assert!(soft <= hard);
            assert!(soft >= hard.min(RAISED_LIMIT));
        }
    }

    #[test]
    fn the_default_limit_leaves_headroom() {
        let limit = default_max_open_files();
        assert!(limit >= MIN_DEFAULT);
        let soft = rustix::process::getrlimit(rustix::process::Resource::Nofile).current;
        if let Some(soft) = soft {
            assert!(limit as u64 <= soft.saturating_sub(HEADROOM).max(MIN_DEFAULT as u64));
        }
    }
}
