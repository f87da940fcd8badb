//! Keeping a cache directory in bounds: temporary files that killed writers left behind
//! are swept, the least recently used entries are evicted beyond the size bound, and a
//! prune (`superflow-pipeline index --prune`) also removes what this build cannot use.

use super::access::{CacheAccess, me};
use super::entry::{EntryKind, payload};
use super::files::{TEMP_SUFFIX, read_entry};
use std::os::unix::fs::MetadataExt;
use std::path::{Path, PathBuf};
use std::time::{Duration, SystemTime};

/// A temporary file older than this belongs to a writer that died: no write of an entry
/// takes this long.
pub const STALE_TEMP: Duration = Duration::from_secs(3600);

/// What an upkeep did.
#[derive(Debug, Clone, Copy, Default, PartialEq, Eq)]
pub struct Upkeep {
    /// Temporary files of dead writers removed.
    pub temps_removed: usize,
    /// Entries this build cannot use, removed (by a prune).
    pub unusable_removed: usize,
    /// Entries evicted by the size bound, least recently used first.
    pub evicted: usize,
    /// Entries left.
    pub entries: usize,
    /// Their bytes.
    pub bytes: u64,
}

/// One entry file of the directory.
struct Found {
    path: PathBuf,
    len: u64,
    used: SystemTime,
}

/// Sweeps stale temporary files of `dir`, removes (when `prune` names the kinds this
/// build reads) the entries it cannot use, then evicts the least recently used entries
/// until their bytes are within the bound of `access`. Only files this user owns are
/// touched; entry names are `<32 hex digits>.<extension>`.
pub fn upkeep(
    dir: &Path,
    access: &CacheAccess,
    prune: Option<&[&EntryKind]>,
) -> std::io::Result<Upkeep> {
    let mut done = Upkeep::default();
    let mut entries = Vec::new();
    let now = SystemTime::now();
    for item in std::fs::read_dir(dir)? {
        let item = item?;
        let name = item.file_name().to_string_lossy().into_owned();
        let Ok(meta) = item.metadata() else { continue }; // removed meanwhile
        if meta.uid() != me() {
            continue;
        }
        let path = item.path();
        let modified = meta.modified().unwrap_or(now);
        if name.starts_with('.') && name.ends_with(TEMP_SUFFIX) {
            let age = now.duration_since(modified).unwrap_or_default();
            if age > STALE_TEMP && std::fs::remove_file(&path).is_ok() {
                done.temps_removed += 1;
            }
            continue;
        }
        let Some(key) = entry_key(&name) else {
            continue;
        };
        if let Some(kinds) = prune {
            let extension = name.rsplit('.').next().unwrap_or_default();
            if let Some(kind) = kinds.iter().find(|k| k.extension == extension) {
                let usable = match read_entry(&path, access) {
                    Ok(Some(bytes)) => payload(kind, key, &bytes).is_ok(),
                    Ok(None) => continue,
                    Err(_) => false,
                };
                if !usable {
                    if std::fs::remove_file(&path).is_ok() {
                        done.unusable_removed += 1;
                    }
                    continue;
                }
            }
        }
        entries.push(Found {
            path,
            len: meta.len(),
            used: modified,
        });
    }
    entries.sort_by_key(|e| e.used);
    let mut bytes: u64 = entries.iter().map(|e| e.len).sum();
    let mut kept = entries.len();
    for entry in &entries {
        if bytes <= access.max_bytes {
            break;
        }
        if std::fs::remove_file(&entry.path).is_ok() {
            bytes -= entry.len;
            kept -= 1;
            done.evicted += 1;
        }
    }
    done.entries = kept;
    done.bytes = bytes;
    Ok(done)
}

/// The key of an entry file name (`<32 hex digits>.<extension>`).
fn entry_key(name: &str) -> Option<u128> {
    let (hex, extension) = name.split_once('.')?;
    if hex.len() != 32 || extension.is_empty() || extension.contains('.') {
        return None;
    }
    u128::from_str_radix(hex, 16).ok()
}

#[cfg(test)]
mod tests {
    use super::super::entry::encode;
    use super::*;

    const KIND: EntryKind = EntryKind {
        magic: *b"SFTEST\0\0",
        version: 1,
        extension: "sftest",
        what: "test",
    };

    #[test]
    fn the_bound_evicts_the_least_recently_used_and_stale_temps_go() {
        let dir = std::env::temp_dir().join(format!("superflow-upkeep-{}", std::process::id()));
        let _ = std::fs::remove_dir_all(&dir);
        std::fs::create_dir_all(&dir).unwrap();
        let day = Duration::from_secs(86_400);
        let now = SystemTime::now();
        let mut names = Vec::new();
        for key in 0..5u128 {
            let name = format!("{key:032x}.{}", KIND.extension);
            let bytes = encode(&KIND, key, &vec![key as u8; 1000]).unwrap();
            std::fs::write(dir.join(&name), &bytes).unwrap();
            // Entry 0 used most recently, 4 least.
            let used = now - day * (key as u32 + 1);
            let file = std::fs::File::options()
                .write(true)
                .open(dir.join(&name))
                .unwrap();
            file.set_modified(used).unwrap();
            names.push(name);
        }
        let one = std::fs::metadata(dir.join(&names[0])).unwrap().len();
        // A damaged entry and one stored under another key's name.
        std::fs::write(dir.join(format!("{:032x}.sftest", 9)), b"junk").unwrap();
        std::fs::copy(dir.join(&names[0]), dir.join(format!("{:032x}.sftest", 8))).unwrap();
        let stale = dir.join(format!(".{:032x}.sftest.0123{TEMP_SUFFIX}", 1));
        let fresh = dir.join(format!(".{:032x}.sftest.4567{TEMP_SUFFIX}", 2));
        std::fs::write(&stale, b"half").unwrap();
        std::fs::write(&fresh, b"half").unwrap();
        std::fs::File::options()
            .write(true)
            .open(&stale)
            .unwrap()
            .set_modified(now - day)
            .unwrap();
        let access = CacheAccess {
            max_bytes: 3 * one,
            ..CacheAccess::default()
        };
        let done = upkeep(&dir, &access, Some(&[&KIND])).unwrap();
        assert_eq!(done.temps_removed, 1);
        assert_eq!(done.unusable_removed, 2);
        assert_eq!(done.evicted, 2);
        assert_eq!((done.entries, done.bytes), (3, 3 * one));
        for (key, name) in names.iter().enumerate() {
            assert_eq!(dir.join(name).exists(), key < 3, "{name}");
        }
        assert!(!stale.exists() && fresh.exists());
        std::fs::remove_dir_all(dir).unwrap();
    }
}
