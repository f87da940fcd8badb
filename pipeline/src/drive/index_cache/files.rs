//! Reading and writing entry files without trusting what stands at their names: entries
//! are opened without following links and without blocking (a FIFO would hang a plain
//! open), read only when they are regular files of a trusted owner and of a size an
//! entry can have; new entries are written to temporary files created exclusively under
//! unpredictable names, then renamed into place.

use super::access::{CacheAccess, me};
use super::entry::EntryError;
use std::fs::File;
use std::hash::{BuildHasher, Hasher};
use std::io::Read;
use std::os::unix::fs::{FileTypeExt, MetadataExt, OpenOptionsExt, PermissionsExt};
use std::path::{Path, PathBuf};
use std::time::{Duration, SystemTime};

/// The largest entry read: far above any file's index, far below what could exhaust
/// memory.
pub const MAX_ENTRY_BYTES: u64 = 1 << 30;
/// An entry used again after this long is marked used (its modification time), so that
/// the size bound evicts the least recently used first.
const TOUCH_AFTER: Duration = Duration::from_secs(3600);
/// The suffix of temporary files.
pub const TEMP_SUFFIX: &str = ".tmp";

/// The bytes of the entry at `path`: `None` when there is none, an error saying why
/// when something stands there that is not read.
pub fn read_entry(path: &Path, access: &CacheAccess) -> Result<Option<Vec<u8>>, EntryError> {
    let opened = std::fs::OpenOptions::new()
        .read(true)
        .custom_flags(libc::O_NOFOLLOW | libc::O_NONBLOCK | libc::O_CLOEXEC)
        .open(path);
    let mut file = match opened {
        Ok(file) => file,
        Err(e) if e.kind() == std::io::ErrorKind::NotFound => return Ok(None),
        Err(e) if e.raw_os_error() == Some(libc::ELOOP) => return Err(EntryError::Symlink),
        Err(e) => return Err(EntryError::Unreadable(e)),
    };
    let meta = file.metadata().map_err(EntryError::Unreadable)?;
    check_kind(&meta)?;
    if !access.trusts(meta.uid()) {
        return Err(EntryError::Owner { uid: meta.uid() });
    }
    if meta.len() > MAX_ENTRY_BYTES {
        return Err(EntryError::TooLarge(meta.len()));
    }
    let mut bytes = Vec::with_capacity(meta.len() as usize);
    // At most the size seen: a file growing meanwhile is read as cut short, and refused.
    (&mut file)
        .take(meta.len())
        .read_to_end(&mut bytes)
        .map_err(EntryError::Unreadable)?;
    if meta.uid() == me()
        && meta
            .modified()
            .is_ok_and(|m| m.elapsed().is_ok_and(|age| age > TOUCH_AFTER))
    {
        // Best effort: a read-only cache still serves.
        let _ = file.set_modified(SystemTime::now());
    }
    Ok(Some(bytes))
}

/// An error unless `meta` is a regular file's.
fn check_kind(meta: &std::fs::Metadata) -> Result<(), EntryError> {
    let kind = meta.file_type();
    let what = if kind.is_file() {
        return Ok(());
    } else if kind.is_dir() {
        "directory"
    } else if kind.is_fifo() {
        "FIFO"
    } else if kind.is_char_device() {
        "character device"
    } else if kind.is_block_device() {
        "block device"
    } else if kind.is_socket() {
        "socket"
    } else {
        "special file"
    };
    Err(EntryError::NotAFile(what))
}

/// A new temporary file in `dir` named `<stem>.<random>.tmp`, created exclusively (never
/// an existing file, never through a link) with the entry mode of `access`.
pub fn create_temp(
    dir: &Path,
    stem: &str,
    access: &CacheAccess,
) -> std::io::Result<(PathBuf, File)> {
    let mode = access.entry_mode();
    let mut last = None;
    for _ in 0..4 {
        let path = dir.join(format!("{stem}.{:016x}{TEMP_SUFFIX}", unpredictable()));
        match std::fs::OpenOptions::new()
            .write(true)
            .create_new(true)
            .mode(mode)
            .custom_flags(libc::O_NOFOLLOW | libc::O_CLOEXEC)
            .open(&path)
        {
            Ok(file) => {
                // The umask may have taken bits a shared cache's readers need.
                if file.metadata()?.mode() & 0o777 != mode {
                    file.set_permissions(std::fs::Permissions::from_mode(mode))?;
                }
                return Ok((path, file));
            }
            Err(e) if e.kind() == std::io::ErrorKind::AlreadyExists => last = Some(e),
            Err(e) => return Err(e),
        }
    }
    Err(last.unwrap_or_else(|| std::io::Error::other("no temporary file name left")))
}

/// 64 bits no other process can predict or share: the standard library's per-process
/// random hash keys over this process, thread and moment.
fn unpredictable() -> u64 {
    use std::sync::atomic::{AtomicU64, Ordering};
    static COUNTER: AtomicU64 = AtomicU64::new(0);
    let mut h = std::collections::hash_map::RandomState::new().build_hasher();
    h.write_u32(std::process::id());
    h.write_u64(COUNTER.fetch_add(1, Ordering::Relaxed));
    h.write(format!("{:?}", std::thread::current().id()).as_bytes());
    h.write_u128(
        SystemTime::now()
            .duration_since(SystemTime::UNIX_EPOCH)
            .map_or(0, |d| d.as_nanos()),
    );
    h.finish()
}

#[cfg(test)]
mod tests {
    use super::*;
    use std::os::unix::fs::symlink;

    fn scratch(tag: &str) -> PathBuf {
        let dir = std::env::temp_dir().join(format!(
            "superflow-cache-files-{tag}-{}",
            std::process::id()
        ));
        let _ = std::fs::remove_dir_all(&dir);
        std::fs::create_dir_all(&dir).unwrap();
        dir
    }

    #[test]
    fn links_fifos_devices_and_directories_are_refused_without_blocking() {
        let dir = scratch("kinds");
        let access = CacheAccess::default();
        assert!(read_entry(&dir.join("none"), &access).unwrap().is_none());
        std::fs::write(dir.join("plain"), b"entry").unwrap();
        assert_eq!(
            read_entry(&dir.join("plain"), &access).unwrap().unwrap(),
            b"entry"
        );
        symlink("/dev/zero", dir.join("zero")).unwrap();
        symlink(dir.join("plain"), dir.join("link")).unwrap();
        std::fs::create_dir(dir.join("sub")).unwrap();
        let fifo = dir.join("fifo");
        let made = std::process::Command::new("mkfifo").arg(&fifo).status();
        assert!(made.unwrap().success());
        for (name, why) in [
            ("zero", "symbolic link"),
            ("link", "symbolic link"),
            ("sub", "directory"),
            ("fifo", "FIFO"),
        ] {
            let err = read_entry(&dir.join(name), &access).unwrap_err();
            assert!(err.to_string().contains(why), "{name}: {err}");
        }
        std::fs::remove_dir_all(dir).unwrap();
    }

    #[test]
    fn temporary_files_are_new_private_and_never_shared() {
        let dir = scratch("temp");
        let access = CacheAccess::default();
        let (a, _) = create_temp(&dir, ".k.sfidx", &access).unwrap();
        let (b, _) = create_temp(&dir, ".k.sfidx", &access).unwrap();
        assert_ne!(a, b);
        assert_eq!(std::fs::metadata(&a).unwrap().mode() & 0o777, 0o600);
        let name = a.file_name().unwrap().to_string_lossy().into_owned();
        assert!(
            name.starts_with(".k.sfidx.") && name.ends_with(TEMP_SUFFIX),
            "{name}"
        );
        std::fs::remove_dir_all(dir).unwrap();
    }
}
