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

use super::SourceError;
use std::collections::HashMap;
use std::fs::File;
use std::os::unix::fs::MetadataExt;
use std::path::Path;
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
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
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

/// One open file of the pool.
#[derive(Debug)]
struct Entry {
    file: Arc<File>,
    /// When it was last handed out ([`Pool::tick`]); the smallest is closed first.
    used: u64,
}

#[derive(Debug, Default)]
struct Pool {
    limit: usize,
    tick: u64,
    open: HashMap<u64, Entry>,
}

impl Pool {
    /// Closes the least recently used files until at most `keep` are open.
    fn shrink_to(&mut self, keep: usize) {
        while self.open.len() > keep {
            let Some(oldest) = self
                .open
                .iter()
                .min_by_key(|(_, e)| e.used)
                .map(|(key, _)| *key)
            else {
                return;
            };
            self.open.remove(&oldest);
        }
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
        let mut pool = self.lock();
        pool.limit = limit.max(1);
        let keep = pool.limit;
        pool.shrink_to(keep);
    }

    /// How many files the pool holds open now.
    pub fn open_count(&self) -> usize {
        self.lock().open.len()
    }

    /// Opens `path` for the first time as `key`, returning the handle and what the file is.
    pub fn open_new(
        &self,
        key: u64,
        path: &Path,
    ) -> Result<(Arc<File>, FileIdentity), SourceError> {
        let (file, identity) = self.open_file(path)?;
        Ok((self.insert(key, file), identity))
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
        }
        // Opened outside the lock: other threads go on reading meanwhile.
        let (file, found) = self.open_file(path)?;
        check(&file, &found)?;
        tracing::trace!(file = %path.display(), "reopened");
        Ok(self.insert(key, file))
    }

    /// Forgets `key`, closing its file once no reader holds it.
    pub fn forget(&self, key: u64) {
        self.lock().open.remove(&key);
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
    fn insert(&self, key: u64, file: File) -> Arc<File> {
        let mut pool = self.lock();
        pool.tick += 1;
        let tick = pool.tick;
        if let Some(entry) = pool.open.get_mut(&key) {
            entry.used = tick;
            return Arc::clone(&entry.file);
        }
        let keep = pool.limit - 1;
        pool.shrink_to(keep);
        let file = Arc::new(file);
        pool.open.insert(
            key,
            Entry {
                file: Arc::clone(&file),
                used: tick,
            },
        );
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
