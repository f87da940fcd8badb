//! The service: an endless (or bounded) stream of batches over iceoryx2.
//!
//! * [`Schedule`] (`schedule.rs`) says which keyframes form batch `step` of `epoch` for
//!   stream `rank`: the epoch's seeded shuffle, dealt round-robin to
//!   `host_count × streams` global ranks (host `h` owns global ranks
//!   `h·streams .. (h+1)·streams`), cut into batches of `batch_size` (the last one of an
//!   epoch may be short — no keyframe is dropped). Every host computes the same shuffle
//!   from the seed, so hosts get disjoint shares that together cover each epoch exactly
//!   once, without talking to each other. A sample's draws are keyed by its position in
//!   the epoch, so the same keyframe gets the same sample whatever the world size or
//!   host count.
//! * A producer thread (`producer.rs`) builds batches ahead (`prefetch`) with rayon; the
//!   publisher loop (`serve.rs`, the calling thread) writes each one in place into a
//!   loaned iceoryx2 slice, sends it and wakes subscribers through the ready event
//!   (`ports.rs`).
//! * Backpressure never loses a batch: the service does not overflow and the publisher
//!   retries until a full subscriber has room. While it waits it checks, every
//!   `dead_node_check_ms`, whether the subscriber's process has died; a dead one is
//!   cleaned up (iceoryx2 dead-node detection) and skipped, the others keep receiving.
//! * A subscriber resumes through the control service (`control.rs`): it names
//!   `(epoch, step)` and the next batch of its stream is that one.
//! * [`Metrics`] (`metrics.rs`) counts what happens, for the log and Prometheus;
//!   [`ServiceConfig`] (`config.rs`) is `[service]` of `pipeline.toml`.

mod config;
mod control;
mod metrics;
mod ports;
mod producer;
mod schedule;
mod serve;

pub use config::{Mode, ServiceConfig};
pub use metrics::Metrics;
pub use schedule::{Schedule, Slot};
pub use serve::serve;

use std::sync::{Mutex, MutexGuard};
use superflow_common::InvalidSetting;
use superflow_schemas::batch::BatchError;
use superflow_schemas::service::{IpcError, ServiceSetupError};

/// A failure of the service.
#[derive(Debug, thiserror::Error)]
pub enum ServiceError {
    /// A service could not be opened or created (name, or iceoryx2 refused).
    #[error(transparent)]
    Setup(#[from] ServiceSetupError),
    /// iceoryx2 refused something else (the node, a port, a loan, a send).
    #[error(transparent)]
    Ipc(#[from] IpcError),
    /// A `[service]` setting out of range.
    #[error(transparent)]
    Invalid(#[from] InvalidSetting),
    /// More streams than keyframes: some ranks would get nothing.
    #[error(
        "{streams} stream(s) on each of {hosts} host(s) exceed the {keyframes} keyframes of the drives: some ranks would get nothing"
    )]
    TooManyStreams {
        /// Streams per host.
        streams: u32,
        /// Hosts.
        hosts: u32,
        /// Keyframes of the drives.
        keyframes: usize,
    },
    /// A batch could not be laid out or written.
    #[error("{service}: {source}")]
    Batch {
        /// The batch service.
        service: String,
        /// What is wrong.
        source: BatchError,
    },
    /// The dataset has no keyframe.
    #[error("the drives have no usable keyframe")]
    NoKeyframes,
}

impl ServiceError {
    /// Wraps an iceoryx2 error with what was being done.
    fn ipc<E: std::error::Error + Send + Sync + 'static>(
        what: impl Into<String>,
    ) -> impl FnOnce(E) -> Self {
        let wrap = IpcError::doing(what);
        move |source| Self::Ipc(wrap(source))
    }
}

/// Where each stream is, and a generation counter bumped by every resume so batches
/// prepared for the old position are dropped. The producer advances it, the control
/// server moves it, the publisher checks it.
#[derive(Debug)]
struct Cursors(Mutex<Positions>);

#[derive(Debug)]
struct Positions {
    /// `(epoch, step)` of the next batch to build, per stream.
    at: Vec<(u64, u64)>,
    /// Resumes so far, per stream.
    generations: Vec<u64>,
}

impl Cursors {
    /// Every one of `streams` streams at `start`.
    fn new(streams: usize, start: (u64, u64)) -> Self {
        Self(Mutex::new(Positions {
            at: vec![start; streams],
            generations: vec![0; streams],
        }))
    }

    fn lock(&self) -> MutexGuard<'_, Positions> {
        self.0.lock().unwrap_or_else(|e| e.into_inner())
    }

    /// `(epoch, step, generation)` of `stream`.
    fn position(&self, stream: usize) -> (u64, u64, u64) {
        let c = self.lock();
        let (epoch, step) = c.at[stream];
        (epoch, step, c.generations[stream])
    }

    /// Whether a batch planned at `generation` of `stream` is still wanted (no resume
    /// request replaced its position since).
    fn is_current(&self, stream: usize, generation: u64) -> bool {
        self.lock().generations[stream] == generation
    }

    /// Moves `stream` to `to` unless a resume moved it since `generation`; whether it
    /// did.
    fn advance(&self, stream: usize, generation: u64, to: (u64, u64)) -> bool {
        let mut c = self.lock();
        let current = c.generations[stream] == generation;
        if current {
            c.at[stream] = to;
        }
        current
    }

    /// A resume request: `stream` continues at `to`, what was planned before is stale.
    fn resume(&self, stream: usize, to: (u64, u64)) {
        let mut c = self.lock();
        c.at[stream] = to;
        c.generations[stream] += 1;
    }

    /// Whether every stream is at or past epoch `epochs`.
    fn all_past(&self, epochs: u64) -> bool {
        self.0
            .lock()
            .map(|c| c.at.iter().all(|(e, _)| *e >= epochs))
            .unwrap_or(true)
    }
}
