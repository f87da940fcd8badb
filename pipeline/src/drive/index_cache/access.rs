//! Who may write a cache directory, and the checks that keep anyone else from changing
//! what the pipeline trains on: the directory is made with the configured mode (`0700`
//! unless shared), refused at start when users other than its owner may write it, and
//! only entries owned by this user or the configured owner are read.

use std::collections::HashMap;
use std::os::unix::fs::{DirBuilderExt, MetadataExt, PermissionsExt};
use std::path::{Path, PathBuf};
use std::sync::{Mutex, OnceLock, PoisonError};

/// The mode of a cache directory made by the pipeline when none is configured.
pub const DEFAULT_MODE: u32 = 0o700;
/// The size bound of a cache when none is configured (`[ingest] index_cache_max_mb`).
pub const DEFAULT_MAX_MB: u64 = 8192;

/// How a cache directory may be written and how large it may grow.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub struct CacheAccess {
    /// The permission bits of the directory; entries get them less the execute bits.
    pub mode: u32,
    /// A user besides this one whose entries are read (the owner of a shared cache).
    pub owner: Option<u32>,
    /// The most bytes of entries kept: the least recently used go first beyond it.
    pub max_bytes: u64,
}

impl Default for CacheAccess {
    fn default() -> Self {
        Self {
            mode: DEFAULT_MODE,
            owner: None,
            max_bytes: DEFAULT_MAX_MB << 20,
        }
    }
}

/// Why a cache directory is refused.
#[derive(Debug, thiserror::Error)]
pub enum CacheError {
    /// Users other than its owner may write it.
    #[error(
        "index cache {dir}: writable by {who} (mode {mode:04o}), who could then change what \
         training reads; make it `chmod {fix} {dir}`, or for a cache shared by a group set \
         `[ingest] index_cache_mode` (e.g. 0o2770) and `index_cache_owner`"
    )]
    Writable {
        /// The directory.
        dir: PathBuf,
        /// `every user` or `its group`.
        who: &'static str,
        /// Its permission bits.
        mode: u32,
        /// The `chmod` argument that makes it safe.
        fix: &'static str,
    },
    /// It belongs to a user the cache does not trust.
    #[error(
        "index cache {dir}: owned by uid {uid}, neither this user ({me}) nor \
         `[ingest] index_cache_owner`"
    )]
    Owner {
        /// The directory.
        dir: PathBuf,
        /// Its owner.
        uid: u32,
        /// This process's user.
        me: u32,
    },
    /// Something other than a directory is there.
    #[error("index cache {0}: not a directory")]
    NotADirectory(PathBuf),
    /// Its metadata cannot be read.
    #[error("index cache {dir}: {source}")]
    Io {
        /// The directory.
        dir: PathBuf,
        /// What failed.
        #[source]
        source: std::io::Error,
    },
}

impl CacheAccess {
    /// The permission bits of entry files.
    pub fn entry_mode(&self) -> u32 {
        self.mode & 0o666
    }

    /// Whether entries owned by `uid` are read.
    pub fn trusts(&self, uid: u32) -> bool {
        uid == me() || Some(uid) == self.owner
    }

    /// Checks an existing cache directory, or makes it with [`mode`](Self::mode).
    pub fn prepare(&self, dir: &Path) -> Result<(), CacheError> {
        let io = |source| CacheError::Io {
            dir: dir.to_path_buf(),
            source,
        };
        let meta = match std::fs::metadata(dir) {
            Ok(meta) => meta,
            Err(e) if e.kind() == std::io::ErrorKind::NotFound => {
                return self.make(dir).map_err(io);
            }
            Err(e) => return Err(io(e)),
        };
        if !meta.is_dir() {
            return Err(CacheError::NotADirectory(dir.to_path_buf()));
        }
        if !self.trusts(meta.uid()) {
            return Err(CacheError::Owner {
                dir: dir.to_path_buf(),
                uid: meta.uid(),
                me: me(),
            });
        }
        let mode = meta.mode() & 0o7777;
        if mode & 0o002 != 0 {
            return Err(CacheError::Writable {
                dir: dir.to_path_buf(),
                who: "every user",
                mode,
                fix: "o-w",
            });
        }
        if mode & 0o020 != 0 && self.mode & 0o020 == 0 {
            return Err(CacheError::Writable {
                dir: dir.to_path_buf(),
                who: "its group",
                mode,
                fix: "g-w",
            });
        }
        Ok(())
    }

    /// Makes `dir` (and its parents) with this mode, whatever the umask.
    pub fn make(&self, dir: &Path) -> std::io::Result<()> {
        if let Some(parent) = dir.parent() {
            std::fs::create_dir_all(parent)?;
        }
        match std::fs::DirBuilder::new().mode(self.mode).create(dir) {
            Ok(()) => std::fs::set_permissions(dir, std::fs::Permissions::from_mode(self.mode)),
            Err(e) if e.kind() == std::io::ErrorKind::AlreadyExists => Ok(()),
            Err(e) => Err(e),
        }
    }
}

/// This process's effective user.
pub fn me() -> u32 {
    rustix::process::geteuid().as_raw()
}

/// The uid of a user given by name or number (`[ingest] index_cache_owner`), looked up
/// once per process.
pub fn uid_of(user: &str) -> Option<u32> {
    if let Ok(uid) = user.parse::<u32>() {
        return Some(uid);
    }
    static KNOWN: OnceLock<Mutex<HashMap<String, Option<u32>>>> = OnceLock::new();
    let known = KNOWN.get_or_init(Mutex::default);
    let mut known = known.lock().unwrap_or_else(PoisonError::into_inner);
    *known
        .entry(user.to_string())
        .or_insert_with(|| lookup(user))
}

/// The password database's uid of `name`.
#[allow(unsafe_code)]
fn lookup(name: &str) -> Option<u32> {
    let name = std::ffi::CString::new(name).ok()?;
    let mut buf = vec![0 as libc::c_char; 1 << 16];
    // SAFETY: `passwd` is plain data that getpwnam_r fills in; all-zero is a valid value.
    let mut entry: libc::passwd = unsafe { std::mem::zeroed() };
    let mut found: *mut libc::passwd = std::ptr::null_mut();
    // SAFETY: every pointer is valid for the call and `buf` outlives it; the strings it
    // writes into `buf` are not read afterwards, only the uid.
    let rc = unsafe {
        libc::getpwnam_r(
            name.as_ptr(),
            &mut entry,
            buf.as_mut_ptr(),
            buf.len(),
            &mut found,
        )
    };
    (rc == 0 && !found.is_null()).then_some(entry.pw_uid)
}

#[cfg(test)]
mod tests {
    use super::*;

    fn scratch(tag: &str) -> PathBuf {
        let dir = std::env::temp_dir().join(format!(
            "superflow-cache-access-{tag}-{}",
            std::process::id()
        ));
        let _ = std::fs::remove_dir_all(&dir);
        dir
    }

    #[test]
    fn a_new_cache_is_private_whatever_the_umask_and_a_writable_one_is_refused() {
        let root = scratch("modes");
        let dir = root.join("a/b/cache");
        let access = CacheAccess::default();
        access.prepare(&dir).unwrap();
        let mode = std::fs::metadata(&dir).unwrap().mode() & 0o777;
        assert_eq!(mode, 0o700);
        for (mode, refused) in [(0o755, false), (0o775, true), (0o777, true), (0o750, false)] {
            std::fs::set_permissions(&dir, std::fs::Permissions::from_mode(mode)).unwrap();
            let result = access.prepare(&dir);
            assert_eq!(result.is_err(), refused, "{mode:o}: {result:?}");
            if let Err(e) = result {
                assert!(e.to_string().contains(&dir.display().to_string()), "{e}");
            }
        }
        // A group cache, configured as such.
        let shared = CacheAccess {
            mode: 0o2770,
            ..access
        };
        std::fs::set_permissions(&dir, std::fs::Permissions::from_mode(0o2770)).unwrap();
        shared.prepare(&dir).unwrap();
        std::fs::set_permissions(&dir, std::fs::Permissions::from_mode(0o2777)).unwrap();
        assert!(shared.prepare(&dir).is_err());
        let made = root.join("shared");
        shared.prepare(&made).unwrap();
        assert_eq!(std::fs::metadata(&made).unwrap().mode() & 0o7777, 0o2770);
        assert_eq!(shared.entry_mode(), 0o660);
        std::fs::write(root.join("file"), b"x").unwrap();
        assert!(matches!(
            access.prepare(&root.join("file")),
            Err(CacheError::NotADirectory(_))
        ));
        std::fs::remove_dir_all(root).unwrap();
    }

    #[test]
    fn owners_resolve_by_name_or_number() {
        assert_eq!(uid_of("0"), Some(0));
        assert_eq!(uid_of("root"), Some(0));
        assert_eq!(uid_of("no-such-user-superflow"), None);
        let access = CacheAccess {
            owner: Some(4242),
            ..CacheAccess::default()
        };
        assert!(access.trusts(me()) && access.trusts(4242));
        assert!(!CacheAccess::default().trusts(me().wrapping_add(1)));
    }
}
