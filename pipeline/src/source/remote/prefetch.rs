//! Reads issued ahead of the samples that need them: the producer knows the epoch's
//! schedule, so the chunks of the next batches are requested while this one is built
//! and a sample finds its bytes waiting (or in flight: it then waits for that request
//! instead of sending a second one). What is held is bounded by
//! [`RemoteSettings::prefetch_bytes`](super::RemoteSettings::prefetch_bytes): the
//! oldest ranges go first, and a range that does not fit is left to be read on demand,
//! so a small budget slows reads down but never blocks one.

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

/// A range being read or read, shared by every reader that wants it.
type Fetch = Shared<BoxFuture<'static, Result<Bytes, Arc<str>>>>;

struct Entry {
    key: String,
    range: Range<u64>,
    fetch: Fetch,
    /// Whether a read took bytes from it (else its bytes were read for nothing).
    used: AtomicBool,
}

#[derive(Default)]
struct Held {
    entries: VecDeque<Entry>,
    bytes: u64,
}

static HELD: LazyLock<Mutex<Held>> = LazyLock::new(Default::default);

/// Starts reading `ranges` of `object` (byte ranges of whole records) unless they are
/// held or in flight already. Ranges that touch are read as one request; a gap, however
/// small, is not bridged (its bytes would be read for nothing).
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
            Some(last) if r.start <= last.end => last.end = last.end.max(r.end),
            _ => merged.push(r),
        }
    }
    let mut held = HELD.lock().unwrap_or_else(PoisonError::into_inner);
    for range in merged {
        let len = range.end - range.start;
        if len == 0 || len > budget || held.covers(&key, &range) {
            continue;
        }
        while held.bytes + len > budget {
            let Some(old) = held.entries.pop_front() else {
                break;
            };
            let old_len = old.range.end - old.range.start;
            held.bytes -= old_len;
            if !old.used.load(Ordering::Relaxed) {
                stats::count_prefetch_unused(old_len);
            }
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
        held.bytes += len;
        held.entries.push_back(Entry {
            key: key.clone(),
            range,
            fetch,
            used: AtomicBool::new(false),
        });
    }
}

impl Held {
    fn covers(&self, key: &str, range: &Range<u64>) -> bool {
        self.find(key, range).is_some()
    }

    fn find(&self, key: &str, range: &Range<u64>) -> Option<&Entry> {
        self.entries
            .iter()
            .rev()
            .find(|e| e.key == key && e.range.start <= range.start && range.end <= e.range.end)
    }
}

/// The bytes of `range` of the object `key` when a prefetch holds them (waiting for it
/// if it is in flight); `None` when none does. A failed prefetch is `Some(Err)`: the
/// caller reads on demand, with retries of its own.
pub(super) fn take(key: &str, range: Range<u64>) -> Option<Result<Bytes, Arc<str>>> {
    let (fetch, start) = {
        let held = HELD.lock().unwrap_or_else(PoisonError::into_inner);
        let entry = held.find(key, &range)?;
        entry.used.store(true, Ordering::Relaxed);
        (entry.fetch.clone(), entry.range.start)
    };
    let bytes = futures::executor::block_on(fetch);
    Some(bytes.map(|b| {
        let from = (range.start - start) as usize;
        b.slice(from..from + (range.end - range.start) as usize)
    }))
}
