//! Reads issued ahead of the samples that need them: the producer knows the epoch's
//! schedule, so the chunks of the next batches are requested while this one is built
//! and a sample finds its bytes waiting (or in flight: it then waits for that request
//! instead of sending a second one). Ranges read on demand are held too, so that the
//! next sample sharing a chunk finds it. What is held is bounded by
//! [`RemoteSettings::prefetch_bytes`](super::RemoteSettings::prefetch_bytes): ranges
//! already read go first, the least recently read first; a range not yet read is never
//! dropped for a new one, which is left to be read on demand instead. A small budget
//! slows reads down; it never blocks one, nor drops what is about to be read.

use super::object::RemoteObject;
use super::stats;
use super::store::{settings, spawn};
use bytes::Bytes;
use futures::FutureExt;
use futures::future::{BoxFuture, Shared};
use std::collections::VecDeque;
use std::ops::Range;
use std::sync::atomic::{AtomicBool, Ordering};
use std::sync::{Arc, LazyLock, Mutex, PoisonError};
use std::time::{Duration, Instant};

/// A range being read or read, shared by every reader that wants it.
type Fetch = Shared<BoxFuture<'static, Result<Bytes, Arc<str>>>>;

struct Entry {
    key: String,
    range: Range<u64>,
    fetch: Fetch,
    /// Whether a read took bytes from it (else its bytes were read for nothing).
    used: AtomicBool,
    /// When it was requested.
    at: Instant,
}

/// A range requested this long ago and still not read was predicted wrong (its sample
/// failed first, or the run moved on): it may go like one read.
const STALE: Duration = Duration::from_secs(60);

#[derive(Default)]
struct Held {
    entries: VecDeque<Entry>,
    bytes: u64,
}

static HELD: LazyLock<Mutex<Held>> = LazyLock::new(Default::default);

/// Starts reading `ranges` of `object` (the bodies of records) unless they are held or
/// in flight already. Ranges that touch, or lie apart by no more than a record's head,
/// are read as one request; a wider gap is not bridged (its bytes would be read for
/// nothing).
pub(crate) fn start(object: &RemoteObject, mut ranges: Vec<Range<u64>>) {
    let budget = settings().prefetch_bytes;
    if budget == 0 || ranges.is_empty() {
        return;
    }
    let key = object.prefetch_key();
    ranges.sort_by_key(|r| r.start);
    let mut merged: Vec<Range<u64>> = Vec::with_capacity(ranges.len());
    for r in ranges {
        match merged.last_mut() {
            Some(last) if r.start <= last.end + RECORD_HEAD => last.end = last.end.max(r.end),
            _ => merged.push(r),
        }
    }
    let mut held = HELD.lock().unwrap_or_else(PoisonError::into_inner);
    for range in merged {
        let len = range.end - range.start;
        if len == 0 || len > budget || held.covers(&key, &range) {
            continue;
        }
        if !held.make_room(len, budget) {
            continue; // read on demand when its turn comes
        }
        let task = spawn(object.fetch_task(range.clone()));
        let fetch = async move {
            match task.await {
                Ok(Ok(bytes)) => Ok(bytes),
                Ok(Err(e)) => Err(Arc::from(e.to_string())),
                Err(e) => Err(Arc::from(e.to_string())),
            }
        }
        .boxed()
        .shared();
        stats::count_prefetched(len);
        held.push(key.clone(), range, fetch, false);
    }
}

/// Holds `bytes`, read on demand as `range` of the object `key`, for the next reader of
/// the same range (a chunk shared by neighbouring samples), if the budget has room.
pub(super) fn keep(key: &str, range: Range<u64>, bytes: Bytes) {
    let budget = settings().prefetch_bytes;
    let len = range.end - range.start;
    let mut held = HELD.lock().unwrap_or_else(PoisonError::into_inner);
    if budget == 0 || held.covers(key, &range) || !held.make_room(len, budget) {
        return;
    }
    let fetch = futures::future::ready(Ok(bytes)).boxed().shared();
    held.push(key.to_string(), range, fetch, true);
}

/// The head of an MCAP record (opcode and length) between two records' bodies.
const RECORD_HEAD: u64 = 9;

impl Held {
    fn push(&mut self, key: String, range: Range<u64>, fetch: Fetch, used: bool) {
        self.bytes += range.end - range.start;
        self.entries.push_back(Entry {
            key,
            range,
            fetch,
            used: AtomicBool::new(used),
            at: Instant::now(),
        });
    }

    /// Drops ranges already read, least recently read first, until `len` more bytes fit
    /// `budget`; `false` when they do not fit even so (ranges not yet read stay).
    fn make_room(&mut self, len: u64, budget: u64) -> bool {
        if len > budget {
            return false;
        }
        while self.bytes + len > budget {
            let Some(i) = self
                .entries
                .iter()
                .position(|e| e.used.load(Ordering::Relaxed) || e.at.elapsed() > STALE)
            else {
                return false;
            };
            if let Some(old) = self.entries.remove(i) {
                let len = old.range.end - old.range.start;
                self.bytes -= len;
                if !old.used.load(Ordering::Relaxed) {
                    stats::count_prefetch_unused(len);
                }
            }
        }
        true
    }

    fn covers(&self, key: &str, range: &Range<u64>) -> bool {
        self.position(key, range).is_some()
    }

    /// The newest entry of `key` that holds all of `range`.
    fn position(&self, key: &str, range: &Range<u64>) -> Option<usize> {
        self.entries
            .iter()
            .rposition(|e| e.key == key && e.range.start <= range.start && range.end <= e.range.end)
    }
}

/// The bytes of `range` of the object `key` when a prefetch holds them (waiting for it
/// if it is in flight); `None` when none does. A failed prefetch is `Some(Err)`: the
/// caller reads on demand, with retries of its own.
pub(super) fn take(key: &str, range: Range<u64>) -> Option<Result<Bytes, Arc<str>>> {
    let (fetch, start) = {
        let mut held = HELD.lock().unwrap_or_else(PoisonError::into_inner);
        let i = held.position(key, &range)?;
        // Read now: it moves to the back, the last of the read ones to go.
        let entry = held.entries.remove(i)?;
        entry.used.store(true, Ordering::Relaxed);
        let found = (entry.fetch.clone(), entry.range.start);
        held.entries.push_back(entry);
        found
    };
    let bytes = futures::executor::block_on(fetch);
    Some(bytes.map(|b| {
        let from = (range.start - start) as usize;
        b.slice(from..from + (range.end - range.start) as usize)
    }))
}
