//! [`RemoteObject`]: the reads of one MCAP file in an object store. Every GET names a
//! byte range and carries the ETag the object was listed with (`If-Match`), so a file
//! is never read as two versions: a replaced object fails its reads as
//! [`SourceError::Replaced`]. Three buffers spare requests:
//! * the tail (one suffix GET): the footer and summary a scan reads first;
//! * the read-ahead window while a scan goes through the file front to back, and a small
//!   object read whole by it, until its drive is assembled (see
//!   [`RemoteObject::release_scan`]);
//! * the prefetched ranges ([`super::prefetch`]) of the samples about to be built.
//!
//! Anything else is one GET of exactly the bytes asked for, split into parts fetched in
//! parallel when it is long.

use super::listing::{listed, location};
use super::prefetch;
use super::stats;
use super::store::{block_on, open_url, permit, settings};
use super::url::ObjectUrl;
use crate::source::SourceError;
use bytes::Bytes;
use object_store::{GetOptions, GetRange, ObjectStore};
use std::ops::Range;
use std::path::{Path, PathBuf};
use std::sync::atomic::{AtomicBool, AtomicU64, Ordering};
use std::sync::{Arc, Mutex, PoisonError};

/// The suffix a scan reads first: the footer, the summary of all but the largest
/// drives, and the summary offsets.
const TAIL_BYTES: u64 = 512 << 10;

/// How far one read-ahead of a scan reaches, in parts (see [`RemoteSettings::part_bytes`]).
///
/// [`RemoteSettings::part_bytes`]: super::RemoteSettings::part_bytes
const READ_AHEAD_PARTS: u64 = 4;

/// The most bytes of whole objects kept between the end of their scans and the
/// assembly of their drives ([`RemoteObject::release_scan`]), over all objects.
const SCANNED_CAP: u64 = 256 << 20;

/// The bytes of whole objects kept now, over all objects.
static SCANNED_BYTES: AtomicU64 = AtomicU64::new(0);

/// One object, as listed: its URL, key, size and ETag.
#[derive(Debug)]
pub(crate) struct RemoteObject {
    path: PathBuf,
    url: ObjectUrl,
    store: Arc<dyn ObjectStore>,
    location: object_store::path::Path,
    size: u64,
    etag: Option<String>,
    /// Set while a scan reads the object front to back: reads then fetch ahead.
    sequential: AtomicBool,
    /// The footer and summary (`start`, bytes), once read.
    tail: Mutex<Option<(u64, Bytes)>>,
    /// The scan's read-ahead (`start`, bytes).
    window: Mutex<Option<(u64, Bytes)>>,
    /// The whole object, read by a scan that has ended, until its drive is assembled:
    /// what the drive reads next (the sweep that times its cameras) is kept from it.
    scanned: Mutex<Option<Bytes>>,
}

impl RemoteObject {
    /// The object at `path` (listed before, or one HEAD now). Nothing is read yet.
    pub(crate) fn open(path: &Path) -> Result<RemoteObject, SourceError> {
        let (url, store) = open_url(path)?;
        let known = listed(path)?;
        Ok(RemoteObject {
            path: path.to_path_buf(),
            location: location(&url.key),
            url,
            store,
            size: known.size,
            etag: known.etag,
            sequential: AtomicBool::new(false),
            tail: Mutex::new(None),
            window: Mutex::new(None),
            scanned: Mutex::new(None),
        })
    }

    /// Its size in bytes.
    pub(crate) fn size(&self) -> u64 {
        self.size
    }

    /// What names this version of the object: its URL, ETag and size (the index
    /// cache's key of a remote file: no byte of it is read to compute it).
    pub(crate) fn version(&self) -> (&Path, Option<&str>, u64) {
        (&self.path, self.etag.as_deref(), self.size)
    }

    /// Marks the start or end of a scan: while one runs, reads fetch ahead. At its end,
    /// a window holding the whole object is kept (within [`SCANNED_CAP`]) until
    /// [`release_scan`](Self::release_scan).
    pub(crate) fn set_sequential(&self, on: bool) {
        self.sequential.store(on, Ordering::Relaxed);
        if on {
            return;
        }
        *self.tail.lock().unwrap_or_else(PoisonError::into_inner) = None;
        let window = self
            .window
            .lock()
            .unwrap_or_else(PoisonError::into_inner)
            .take();
        let Some((0, bytes)) = window.filter(|(_, b)| b.len() as u64 == self.size) else {
            return;
        };
        let len = bytes.len() as u64;
        if SCANNED_BYTES.fetch_add(len, Ordering::Relaxed) + len > SCANNED_CAP {
            SCANNED_BYTES.fetch_sub(len, Ordering::Relaxed);
            return;
        }
        let old = self
            .scanned
            .lock()
            .unwrap_or_else(PoisonError::into_inner)
            .replace(bytes);
        if let Some(old) = old {
            SCANNED_BYTES.fetch_sub(old.len() as u64, Ordering::Relaxed);
        }
    }

    /// Lets go of what the ended scan read, first keeping `keep` (byte ranges the
    /// object is read at next) among the prefetched ranges, so that they are not asked
    /// of the store again; nothing is fetched.
    pub(crate) fn release_scan(&self, keep: &[Range<u64>]) {
        let Some(whole) = self
            .scanned
            .lock()
            .unwrap_or_else(PoisonError::into_inner)
            .take()
        else {
            return;
        };
        SCANNED_BYTES.fetch_sub(whole.len() as u64, Ordering::Relaxed);
        let key = self.prefetch_key();
        for range in keep {
            if let Some(bytes) = whole.get(range.start as usize..range.end as usize) {
                // A copy: a slice would hold the whole object.
                prefetch::keep(&key, range.clone(), Bytes::copy_from_slice(bytes));
            }
        }
    }

    /// What prefetches of this object are keyed by: its URL and version.
    pub(crate) fn prefetch_key(&self) -> String {
        format!(
            "{}#{}",
            self.path.display(),
            self.etag.as_deref().unwrap_or("")
        )
    }

    /// Fills `buf` with the bytes at `offset`.
    pub(crate) fn read_into(&self, buf: &mut [u8], offset: u64) -> Result<(), SourceError> {
        let end = offset.saturating_add(buf.len() as u64);
        if end > self.size {
            return Err(SourceError::Io {
                path: self.path.clone(),
                source: std::io::Error::new(
                    std::io::ErrorKind::UnexpectedEof,
                    format!(
                        "bytes {offset}..{end} run past the end of the object ({} bytes)",
                        self.size
                    ),
                ),
            });
        }
        if buf.is_empty() {
            return Ok(());
        }
        let sequential = self.sequential.load(Ordering::Relaxed);
        if Self::copy_from(&self.tail, buf, offset) || Self::copy_from(&self.window, buf, offset) {
            return Ok(());
        }
        let tail_start = self.size.saturating_sub(TAIL_BYTES);
        let ahead = settings().part_bytes.max(1 << 20) * READ_AHEAD_PARTS;
        if sequential && offset >= tail_start && self.size > ahead {
            // The footer and summary: one suffix read.
            let bytes = self.fetch(tail_start..self.size)?;
            *self.tail.lock().unwrap_or_else(PoisonError::into_inner) = Some((tail_start, bytes));
            Self::copy_from(&self.tail, buf, offset);
            return Ok(());
        }
        if sequential {
            // A scan: read ahead (a small object whole, footer and summary included).
            let to = if self.size <= ahead {
                self.size
            } else {
                end.max(offset.saturating_add(ahead)).min(self.size)
            };
            let from = if self.size <= ahead { 0 } else { offset };
            let bytes = self.fetch(from..to)?;
            *self.window.lock().unwrap_or_else(PoisonError::into_inner) = Some((from, bytes));
            Self::copy_from(&self.window, buf, offset);
            return Ok(());
        }
        let key = self.prefetch_key();
        // A failed prefetch is read again on demand, with retries of its own.
        if let Some(Ok(bytes)) = prefetch::take(&key, offset..end) {
            buf.copy_from_slice(&bytes);
            stats::count_prefetch_hit(true);
            return Ok(());
        }
        stats::count_prefetch_hit(false);
        let bytes = self.fetch(offset..end)?;
        buf.copy_from_slice(&bytes);
        prefetch::keep(&key, offset..end, bytes);
        Ok(())
    }

    /// Copies `buf.len()` bytes at `offset` out of `held` when it holds them all.
    fn copy_from(held: &Mutex<Option<(u64, Bytes)>>, buf: &mut [u8], offset: u64) -> bool {
        let held = held.lock().unwrap_or_else(PoisonError::into_inner);
        let Some((start, bytes)) = held.as_ref() else {
            return false;
        };
        let Some(from) = offset.checked_sub(*start) else {
            return false;
        };
        let (from, len) = (from as usize, buf.len());
        match bytes.get(from..from + len) {
            Some(held) => {
                buf.copy_from_slice(held);
                true
            }
            None => false,
        }
    }

    /// The bytes of `range`, waiting for them.
    pub(crate) fn fetch(&self, range: Range<u64>) -> Result<Bytes, SourceError> {
        block_on(self.fetch_task(range))
    }

    /// A task that reads `range` (in parallel parts when it is long), every GET pinned
    /// to the listed ETag.
    pub(crate) fn fetch_task(
        &self,
        range: Range<u64>,
    ) -> impl std::future::Future<Output = Result<Bytes, SourceError>> + Send + 'static {
        let store = Arc::clone(&self.store);
        let location = self.location.clone();
        let etag = self.etag.clone();
        let path = self.path.clone();
        let url = self.url.clone();
        let part = settings().part_bytes.max(1 << 20);
        let cached = super::disk::object_key(&self.path, self.etag.as_deref());
        tracing::trace!(object = %self.path.display(), start = range.start, end = range.end, "read");
        async move {
            if let Some(object) = cached {
                let wanted = range.clone();
                let held = tokio::task::spawn_blocking(move || super::disk::get(object, &wanted));
                if let Ok(Some(bytes)) = held.await {
                    return Ok(bytes);
                }
            }
            let parts: Vec<Range<u64>> = (range.start..range.end)
                .step_by(part as usize)
                .map(|s| s..(s + part).min(range.end))
                .collect();
            let gets = parts.into_iter().map(|r| {
                let store = Arc::clone(&store);
                let location = location.clone();
                let etag = etag.clone();
                async move {
                    let _permit = permit().await;
                    let want = r.end - r.start;
                    let options = GetOptions {
                        if_match: etag,
                        range: Some(GetRange::Bounded(r)),
                        ..GetOptions::default()
                    };
                    let bytes = store.get_opts(&location, options).await?.bytes().await?;
                    stats::count_bytes(bytes.len() as u64);
                    if bytes.len() as u64 != want {
                        return Err(object_store::Error::Generic {
                            store: "object",
                            source: format!(
                                "the store sent {} bytes of the {want} asked for",
                                bytes.len()
                            )
                            .into(),
                        });
                    }
                    Ok(bytes)
                }
            });
            let parts = futures::future::try_join_all(gets)
                .await
                .map_err(|e| super::source_error(&path, &url, e))?;
            let bytes = match parts.len() {
                1 => parts.into_iter().next().unwrap_or_default(),
                _ => {
                    let mut whole = Vec::with_capacity((range.end - range.start) as usize);
                    parts.iter().for_each(|p| whole.extend_from_slice(p));
                    Bytes::from(whole)
                }
            };
            if let Some(object) = cached {
                let kept = bytes.clone();
                tokio::task::spawn_blocking(move || super::disk::put(object, &range, &kept));
            }
            Ok(bytes)
        }
    }
}

impl Drop for RemoteObject {
    fn drop(&mut self) {
        self.release_scan(&[]);
    }
}
