//! What the object-store reads of this process did, counted where they happen: every
//! HTTP attempt by its outcome (so retries show by cause), the time to each response's
//! head, the bytes delivered, and what the prefetch saved. Read by the Prometheus
//! endpoint ([`prometheus`]) and the benches ([`RemoteStats::now`]).

use std::sync::atomic::{AtomicU64, Ordering};
use std::time::Duration;

/// Why an HTTP attempt did not deliver: each is retried by the client within its bound.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum Failure {
    /// 503 (S3's SlowDown) or 429: the store asks for less.
    Throttled,
    /// Another 5xx.
    ServerError,
    /// 408, or no response within the request timeout.
    Timeout,
    /// The connection failed or was reset before a response.
    Connection,
    /// The response body ended before its length.
    BodyCut,
}

impl Failure {
    const ALL: [Failure; 5] = [
        Failure::Throttled,
        Failure::ServerError,
        Failure::Timeout,
        Failure::Connection,
        Failure::BodyCut,
    ];

    /// The label value of this cause.
    pub fn as_str(self) -> &'static str {
        match self {
            Failure::Throttled => "throttled",
            Failure::ServerError => "server_error",
            Failure::Timeout => "timeout",
            Failure::Connection => "connection",
            Failure::BodyCut => "body_cut",
        }
    }
}

/// Upper bounds of the latency histogram's buckets, milliseconds.
const LATENCY_BUCKETS_MS: [u64; 12] = [1, 2, 5, 10, 20, 50, 100, 200, 500, 1_000, 5_000, 30_000];

#[derive(Debug)]
struct Counters {
    requests: AtomicU64,
    gets: AtomicU64,
    lists: AtomicU64,
    heads: AtomicU64,
    failures: [AtomicU64; 5],
    bytes: AtomicU64,
    latency_buckets: [AtomicU64; LATENCY_BUCKETS_MS.len() + 1],
    latency_sum_micros: AtomicU64,
    prefetch_hits: AtomicU64,
    prefetch_misses: AtomicU64,
    prefetch_bytes: AtomicU64,
    prefetch_unused_bytes: AtomicU64,
    disk_hit_bytes: AtomicU64,
    disk_stored_bytes: AtomicU64,
}

static COUNTERS: Counters = Counters {
    requests: AtomicU64::new(0),
    gets: AtomicU64::new(0),
    lists: AtomicU64::new(0),
    heads: AtomicU64::new(0),
    failures: [const { AtomicU64::new(0) }; 5],
    bytes: AtomicU64::new(0),
    latency_buckets: [const { AtomicU64::new(0) }; LATENCY_BUCKETS_MS.len() + 1],
    latency_sum_micros: AtomicU64::new(0),
    prefetch_hits: AtomicU64::new(0),
    prefetch_misses: AtomicU64::new(0),
    prefetch_bytes: AtomicU64::new(0),
    prefetch_unused_bytes: AtomicU64::new(0),
    disk_hit_bytes: AtomicU64::new(0),
    disk_stored_bytes: AtomicU64::new(0),
};

/// The kind of an HTTP request, from its method and query.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub(super) enum RequestKind {
    Get,
    List,
    Head,
    Other,
}

pub(super) fn count_request(kind: RequestKind) {
    COUNTERS.requests.fetch_add(1, Ordering::Relaxed);
    let counter = match kind {
        RequestKind::Get => &COUNTERS.gets,
        RequestKind::List => &COUNTERS.lists,
        RequestKind::Head => &COUNTERS.heads,
        RequestKind::Other => return,
    };
    counter.fetch_add(1, Ordering::Relaxed);
}

pub(super) fn count_failure(failure: Failure) {
    let i = Failure::ALL.iter().position(|f| *f == failure).unwrap_or(0);
    COUNTERS.failures[i].fetch_add(1, Ordering::Relaxed);
}

pub(super) fn count_latency(latency: Duration) {
    let ms = latency.as_millis() as u64;
    let bucket = LATENCY_BUCKETS_MS
        .iter()
        .position(|&b| ms <= b)
        .unwrap_or(LATENCY_BUCKETS_MS.len());
    COUNTERS.latency_buckets[bucket].fetch_add(1, Ordering::Relaxed);
    COUNTERS
        .latency_sum_micros
        .fetch_add(latency.as_micros() as u64, Ordering::Relaxed);
}

pub(super) fn count_bytes(n: u64) {
    COUNTERS.bytes.fetch_add(n, Ordering::Relaxed);
}

pub(super) fn count_prefetch_hit(hit: bool) {
    let counter = if hit {
        &COUNTERS.prefetch_hits
    } else {
        &COUNTERS.prefetch_misses
    };
    counter.fetch_add(1, Ordering::Relaxed);
}

pub(super) fn count_prefetched(bytes: u64) {
    COUNTERS.prefetch_bytes.fetch_add(bytes, Ordering::Relaxed);
}

pub(super) fn count_prefetch_unused(bytes: u64) {
    COUNTERS
        .prefetch_unused_bytes
        .fetch_add(bytes, Ordering::Relaxed);
}

/// Bytes the local chunk cache served (`hit`) or took in.
pub(super) fn count_disk_cache(hit: bool, bytes: u64) {
    let counter = if hit {
        &COUNTERS.disk_hit_bytes
    } else {
        &COUNTERS.disk_stored_bytes
    };
    counter.fetch_add(bytes, Ordering::Relaxed);
}

/// A snapshot of the counters.
#[derive(Debug, Clone, Copy, Default, PartialEq, Eq)]
pub struct RemoteStats {
    /// HTTP requests sent, retries included.
    pub requests: u64,
    /// Of them, GETs of object bytes.
    pub gets: u64,
    /// Of them, LIST pages.
    pub lists: u64,
    /// Of them, HEADs.
    pub heads: u64,
    /// Attempts that failed and were retried (or gave up), by [`Failure`] in the order
    /// throttled, server error, timeout, connection, body cut.
    pub failures: [u64; 5],
    /// Object bytes delivered to readers (prefetched ones included).
    pub bytes: u64,
    /// Chunk reads served by the prefetch, and those that went to the store.
    pub prefetch_hits: u64,
    /// Chunk reads of remote files the prefetch had not fetched.
    pub prefetch_misses: u64,
    /// Bytes fetched ahead of their reader.
    pub prefetch_bytes: u64,
    /// Bytes fetched ahead and dropped unread (budget or end of run).
    pub prefetch_unused_bytes: u64,
    /// Bytes the local chunk cache served instead of the store.
    pub disk_hit_bytes: u64,
    /// Bytes written into the local chunk cache.
    pub disk_stored_bytes: u64,
}

impl RemoteStats {
    /// The counters now.
    pub fn now() -> RemoteStats {
        let load = |c: &AtomicU64| c.load(Ordering::Relaxed);
        RemoteStats {
            requests: load(&COUNTERS.requests),
            gets: load(&COUNTERS.gets),
            lists: load(&COUNTERS.lists),
            heads: load(&COUNTERS.heads),
            failures: std::array::from_fn(|i| load(&COUNTERS.failures[i])),
            bytes: load(&COUNTERS.bytes),
            prefetch_hits: load(&COUNTERS.prefetch_hits),
            prefetch_misses: load(&COUNTERS.prefetch_misses),
            prefetch_bytes: load(&COUNTERS.prefetch_bytes),
            prefetch_unused_bytes: load(&COUNTERS.prefetch_unused_bytes),
            disk_hit_bytes: load(&COUNTERS.disk_hit_bytes),
            disk_stored_bytes: load(&COUNTERS.disk_stored_bytes),
        }
    }

    /// Attempts that failed, every cause together.
    pub fn retries(&self) -> u64 {
        self.failures.iter().sum()
    }
}

/// The counters in Prometheus text format; empty while this process has made no request
/// (a run over local drives only shows nothing of it).
pub fn prometheus() -> String {
    let s = RemoteStats::now();
    if s.requests == 0 && s.disk_hit_bytes == 0 {
        return String::new();
    }
    let mut out = String::new();
    let mut counter = |name: &str, help: &str, value: u64| {
        out.push_str(&format!(
            "# HELP {name} {help}\n# TYPE {name} counter\n{name} {value}\n"
        ));
    };
    counter(
        "superflow_remote_requests_total",
        "HTTP requests to object stores, retries included",
        s.requests,
    );
    counter(
        "superflow_remote_gets_total",
        "Ranged GETs of object bytes",
        s.gets,
    );
    counter("superflow_remote_lists_total", "LIST pages", s.lists);
    counter("superflow_remote_heads_total", "HEAD requests", s.heads);
    counter(
        "superflow_remote_bytes_total",
        "Object bytes read from object stores",
        s.bytes,
    );
    counter(
        "superflow_remote_prefetch_hits_total",
        "Chunk reads served by the prefetch",
        s.prefetch_hits,
    );
    counter(
        "superflow_remote_prefetch_misses_total",
        "Chunk reads of remote drives not prefetched",
        s.prefetch_misses,
    );
    counter(
        "superflow_remote_prefetch_bytes_total",
        "Bytes fetched ahead of their reader",
        s.prefetch_bytes,
    );
    counter(
        "superflow_remote_prefetch_unused_bytes_total",
        "Bytes fetched ahead and dropped unread",
        s.prefetch_unused_bytes,
    );
    counter(
        "superflow_remote_cache_hit_bytes_total",
        "Object bytes served by the local chunk cache",
        s.disk_hit_bytes,
    );
    counter(
        "superflow_remote_cache_stored_bytes_total",
        "Object bytes written into the local chunk cache",
        s.disk_stored_bytes,
    );
    out.push_str(
        "# HELP superflow_remote_retries_total Failed attempts, retried within the bound\n\
         # TYPE superflow_remote_retries_total counter\n",
    );
    for (failure, n) in Failure::ALL.iter().zip(s.failures) {
        out.push_str(&format!(
            "superflow_remote_retries_total{{cause=\"{}\"}} {n}\n",
            failure.as_str()
        ));
    }
    out.push_str(
        "# HELP superflow_remote_request_seconds Time to a response's head\n\
         # TYPE superflow_remote_request_seconds histogram\n",
    );
    let mut cumulative = 0u64;
    for (i, bound) in LATENCY_BUCKETS_MS.iter().enumerate() {
        cumulative += COUNTERS.latency_buckets[i].load(Ordering::Relaxed);
        out.push_str(&format!(
            "superflow_remote_request_seconds_bucket{{le=\"{}\"}} {cumulative}\n",
            *bound as f64 / 1e3
        ));
    }
    cumulative += COUNTERS.latency_buckets[LATENCY_BUCKETS_MS.len()].load(Ordering::Relaxed);
    let sum = COUNTERS.latency_sum_micros.load(Ordering::Relaxed) as f64 / 1e6;
    out.push_str(&format!(
        "superflow_remote_request_seconds_bucket{{le=\"+Inf\"}} {cumulative}\n\
         superflow_remote_request_seconds_sum {sum}\n\
         superflow_remote_request_seconds_count {cumulative}\n"
    ));
    out
}
