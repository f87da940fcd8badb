//! The optional local chunk cache (`[ingest] remote_cache_dir`, `remote_cache_mb`): byte
//! ranges of objects kept on a local disk, keyed by the object's URL, ETag and range, so
//! that a second epoch over a dataset the cache holds reads no remote byte. The least
//! recently used ranges are evicted first; a range larger than the whole cache is read
//! through and never stored, so a cache smaller than one sample still works and nothing
//! ever waits for room.
//!
//! The directory is private (made `0700`; one that other users may write is refused),
//! ranges are written to temporary files created exclusively under names of their own,
//! then renamed into place, and read without following links. Several processes may
//! share a cache: each keeps its own view of what is in it (built from the directory at
//! its first use) and a range another process removed is read again from the store.

use super::stats;
use bytes::Bytes;
use std::collections::HashMap;
use std::fs::File;
use std::io::Write as _;
use std::ops::Range;
use std::os::unix::fs::{
    DirBuilderExt as _, FileExt as _, MetadataExt as _, OpenOptionsExt as _, PermissionsExt as _,
};
use std::path::{Path, PathBuf};
use std::sync::atomic::{AtomicU64, Ordering};
use std::sync::{LazyLock, Mutex, PoisonError, RwLock};
use xxhash_rust::xxh3::xxh3_128;

/// Where the cache is and how large it may grow.
#[derive(Debug, Clone, PartialEq, Eq)]
pub struct DiskCacheSettings {
    /// The directory.
    pub dir: PathBuf,
    /// The most bytes of ranges kept.
    pub max_bytes: u64,
}

/// One range on disk.
#[derive(Debug, Clone)]
struct Held {
    range: Range<u64>,
    /// When it was last read or written (a counter, for least-recently-used eviction).
    used: u64,
}

#[derive(Debug, Default)]
struct State {
    /// Ranges per object (the hash of its URL and ETag), sorted by start.
    objects: HashMap<u128, Vec<Held>>,
    bytes: u64,
    clock: u64,
}

struct Cache {
    settings: DiskCacheSettings,
    state: Mutex<State>,
}

static SETTINGS: RwLock<Option<DiskCacheSettings>> = RwLock::new(None);

/// Turns the cache on (or off with `None`) before the first remote read.
pub fn configure(settings: Option<DiskCacheSettings>) {
    *SETTINGS.write().unwrap_or_else(PoisonError::into_inner) = settings;
}

/// The cache, opened at first use; `None` when off or when its directory is refused.
fn cache() -> Option<&'static Cache> {
    static CACHE: LazyLock<Option<Cache>> = LazyLock::new(|| {
        let settings = SETTINGS
            .read()
            .unwrap_or_else(PoisonError::into_inner)
            .clone()?;
        match open(&settings) {
            Ok(state) => Some(Cache {
                settings,
                state: Mutex::new(state),
            }),
            Err(e) => {
                tracing::warn!(
                    dir = %settings.dir.display(),
                    "the local chunk cache is not used: {e}"
                );
                None
            }
        }
    });
    CACHE.as_ref()
}

/// The key of an object version.
pub(super) fn object_key(url: &Path, etag: Option<&str>) -> Option<u128> {
    // Without an ETag a later version could not be told from this one.
    let etag = etag?;
    let mut text = url.as_os_str().as_encoded_bytes().to_vec();
    text.push(0);
    text.extend_from_slice(etag.as_bytes());
    Some(xxh3_128(&text))
}

fn file_name(object: u128, range: &Range<u64>) -> String {
    format!("{object:032x}.{}-{}.range", range.start, range.end)
}

/// Makes or checks the directory and lists what it holds.
fn open(settings: &DiskCacheSettings) -> std::io::Result<State> {
    let dir = &settings.dir;
    if !dir.exists() {
        std::fs::DirBuilder::new()
            .recursive(true)
            .mode(0o700)
            .create(dir)?;
    }
    let meta = std::fs::symlink_metadata(dir)?;
    if !meta.is_dir() {
        return Err(std::io::Error::other("not a directory"));
    }
    // SAFETY: getuid has no preconditions and cannot fail.
    #[allow(unsafe_code)]
    let me = unsafe { libc::getuid() };
    if meta.uid() != me || meta.mode() & 0o022 != 0 {
        return Err(std::io::Error::other(format!(
            "the directory must be this user's and writable by no one else (mode {:o}, owner {})",
            meta.mode() & 0o7777,
            meta.uid()
        )));
    }
    let mut state = State::default();
    for entry in std::fs::read_dir(dir)?.flatten() {
        let name = entry.file_name();
        let Some(name) = name.to_str() else { continue };
        if name.ends_with(".tmp") {
            // A writer that died; a live one's file is gone by the time it matters.
            let _ = std::fs::remove_file(entry.path());
            continue;
        }
        let Some((object, range)) = parse_name(name) else {
            continue;
        };
        let Ok(meta) = entry.metadata() else { continue };
        if !meta.is_file() || meta.len() != range.end - range.start {
            let _ = std::fs::remove_file(entry.path());
            continue;
        }
        state.bytes += meta.len();
        state.objects.entry(object).or_default().push(Held {
            range,
            // Older files first out: their modification time orders them.
            used: meta.mtime().max(0) as u64,
        });
    }
    state.clock = state
        .objects
        .values()
        .flatten()
        .map(|h| h.used)
        .max()
        .unwrap_or(0);
    for held in state.objects.values_mut() {
        held.sort_by_key(|h| h.range.start);
    }
    Ok(state)
}

fn parse_name(name: &str) -> Option<(u128, Range<u64>)> {
    let (object, rest) = name.strip_suffix(".range")?.split_once('.')?;
    let (start, end) = rest.split_once('-')?;
    let range = start.parse().ok()?..end.parse().ok()?;
    (range.start < range.end).then_some(())?;
    Some((u128::from_str_radix(object, 16).ok()?, range))
}

/// The bytes of `range` of `object` when the cache holds them all (in one stored range
/// or several that touch).
pub(super) fn get(object: u128, range: &Range<u64>) -> Option<Bytes> {
    let cache = cache()?;
    // (stored range, the part of `range` it gives)
    let pieces: Vec<(Range<u64>, Range<u64>)> = {
        let mut state = cache.state.lock().unwrap_or_else(PoisonError::into_inner);
        state.clock += 1;
        let clock = state.clock;
        let held = state.objects.get_mut(&object)?;
        let mut at = range.start;
        let mut pieces = Vec::new();
        for h in held.iter_mut() {
            if at >= range.end {
                break;
            }
            if h.range.start <= at && at < h.range.end {
                h.used = clock;
                let to = h.range.end.min(range.end);
                pieces.push((h.range.clone(), at..to));
                at = to;
            }
        }
        if at < range.end {
            return None;
        }
        pieces
    };
    let mut out = Vec::with_capacity((range.end - range.start) as usize);
    for (piece, part) in pieces {
        let (from, to) = (part.start, part.end);
        let path = cache.settings.dir.join(file_name(object, &piece));
        let mut buf = vec![0u8; (to - from) as usize];
        let read = std::fs::OpenOptions::new()
            .read(true)
            .custom_flags(libc::O_NOFOLLOW | libc::O_NONBLOCK | libc::O_CLOEXEC)
            .open(&path)
            .and_then(|file| {
                let meta = file.metadata()?;
                if !meta.is_file() || meta.len() != piece.end - piece.start {
                    return Err(std::io::Error::other("not the range it is named for"));
                }
                file.read_exact_at(&mut buf, from - piece.start)
            });
        if read.is_err() {
            // Removed by another process, or damaged: forget it, read from the store.
            forget(cache, object, &piece);
            return None;
        }
        out.extend_from_slice(&buf);
    }
    stats::count_disk_cache(true, out.len() as u64);
    Some(Bytes::from(out))
}

fn forget(cache: &Cache, object: u128, piece: &Range<u64>) {
    let mut state = cache.state.lock().unwrap_or_else(PoisonError::into_inner);
    if let Some(held) = state.objects.get_mut(&object)
        && let Some(i) = held.iter().position(|h| h.range == *piece)
    {
        held.remove(i);
        state.bytes -= piece.end - piece.start;
    }
    let _ = std::fs::remove_file(cache.settings.dir.join(file_name(object, piece)));
}

/// Keeps `bytes`, the bytes of `range` of `object`, evicting the least recently used
/// ranges to make room. A range larger than the cache, or one it holds, is not stored;
/// a write that fails is logged once and skipped.
pub(super) fn put(object: u128, range: &Range<u64>, bytes: &[u8]) {
    let Some(cache) = cache() else { return };
    let len = range.end - range.start;
    if len == 0 || len > cache.settings.max_bytes || bytes.len() as u64 != len {
        return;
    }
    stats::count_disk_cache(false, len);
    let evicted = {
        let mut state = cache.state.lock().unwrap_or_else(PoisonError::into_inner);
        let held = state.objects.entry(object).or_default();
        if held.iter().any(|h| h.range == *range) {
            return;
        }
        let mut evicted = Vec::new();
        while state.bytes + len > cache.settings.max_bytes {
            let Some((key, i)) = state
                .objects
                .iter()
                .flat_map(|(k, held)| held.iter().enumerate().map(move |(i, h)| (h.used, *k, i)))
                .min()
                .map(|(_, k, i)| (k, i))
            else {
                break;
            };
            let Some(held) = state.objects.get_mut(&key) else {
                break;
            };
            let gone = held.remove(i);
            state.bytes -= gone.range.end - gone.range.start;
            evicted.push((key, gone.range));
        }
        state.clock += 1;
        let used = state.clock;
        let held = state.objects.entry(object).or_default();
        let at = held.partition_point(|h| h.range.start < range.start);
        held.insert(
            at,
            Held {
                range: range.clone(),
                used,
            },
        );
        state.bytes += len;
        evicted
    };
    for (key, gone) in evicted {
        let _ = std::fs::remove_file(cache.settings.dir.join(file_name(key, &gone)));
    }
    if let Err(e) = write(&cache.settings.dir, &file_name(object, range), bytes) {
        static SAID: std::sync::Once = std::sync::Once::new();
        SAID.call_once(|| {
            tracing::warn!(dir = %cache.settings.dir.display(), "the local chunk cache could not be written ({e}); reading through");
        });
        forget(cache, object, range);
    }
}

/// Writes `bytes` to a new temporary file in `dir`, then renames it to `name`.
fn write(dir: &Path, name: &str, bytes: &[u8]) -> std::io::Result<()> {
    static NEXT: AtomicU64 = AtomicU64::new(0);
    let temp = dir.join(format!(
        "{name}.{}.{}.tmp",
        std::process::id(),
        NEXT.fetch_add(1, Ordering::Relaxed)
    ));
    let result = std::fs::OpenOptions::new()
        .write(true)
        .create_new(true)
        .mode(0o600)
        .custom_flags(libc::O_NOFOLLOW | libc::O_CLOEXEC)
        .open(&temp)
        .and_then(|mut file: File| {
            file.write_all(bytes)?;
            file.set_permissions(std::fs::Permissions::from_mode(0o600))
        })
        .and_then(|()| std::fs::rename(&temp, dir.join(name)));
    if result.is_err() {
        let _ = std::fs::remove_file(&temp);
    }
    result
}
