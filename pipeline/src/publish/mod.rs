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
//! * A batch whose samples all failed to build is still published, as a lost batch
//!   (`BATCH_LOST`, nothing in it) at its place in the stream: subscribers count it and
//!   see their epochs end. A batch of which some samples failed goes out with the rest.
//! * Backpressure never loses a batch: the service does not overflow and the publisher
//!   retries until a full subscriber has room. While it waits it checks, every
//!   `dead_node_check_ms`, whether the subscriber's process has died; a dead one is
//!   cleaned up (iceoryx2 dead-node detection) and skipped, the others keep receiving.
//! * A subscriber resumes through the control service (`control.rs`): it names
//!   `(epoch, samples the whole job had consumed)` — or its own step — and the next
//!   batch of its stream is the one there; a job resumed on another number of ranks or
//!   hosts continues the epoch at that sample ([`Schedule`]).
//! * [`Metrics`] (`metrics.rs`) counts what happens, for the log and Prometheus;
//!   [`ServiceConfig`] (`config.rs`) is `[service]` of `pipeline.toml`.
//! * [`SideTasks`] (`side_tasks.rs`): the SIGINT/SIGTERM handlers that stop the service
//!   and the Prometheus endpoint.

mod config;
mod control;
mod metrics;
mod plan_id;
mod ports;
mod producer;
mod schedule;
mod serve;
mod side_tasks;

pub use config::{Mode, ServiceConfig};
pub use metrics::Metrics;
pub use plan_id::PlanId;
pub use schedule::{Schedule, Slot};
pub use serve::serve;
pub use side_tasks::{SideTaskError, SideTasks};
/// Where the service starts: at a step of every stream (`--start-step`), or after the
/// samples of an epoch a job of any size had consumed (`--start-sample`; its
/// `global_batch` is not used).
pub use superflow_schemas::service::ResumeAt;

/// How many steps a stream's batches may run ahead of the stream furthest behind (both
/// built and published). Data-parallel ranks take their steps together: a rank's
/// batches published far ahead fill its queue while it waits for the others, and the
/// publisher, blocked on that full queue, would never get the others theirs. It happens
/// when ranks resume one after another, each from where the job stopped. Two steps keep
/// streams in lockstep with room for epoch ends, where shares differ by one batch.
const MAX_LEAD_STEPS: u128 = 2;

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
    /// `--start-sample` beyond the epoch.
    #[error("--start-sample {sample} is past the end of an epoch of {samples} samples")]
    StartPastEpoch {
        /// The sample asked for.
        sample: u64,
        /// Samples per epoch.
        samples: usize,
    },
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

/// Where each stream is, a generation counter bumped by every resume so batches
/// prepared for the old position are dropped, and the publisher-wide sequence number of
/// the next batch sent. The producer advances it, the control server moves it, the
/// publisher checks it and takes sequence numbers from it — under one lock, so a resume
/// answered while a batch is on its way names a sequence number above that batch's.
#[derive(Debug)]
struct Cursors(Mutex<Positions>);

#[derive(Debug)]
struct Positions {
    /// `(epoch, step)` of the next batch to build, per stream.
    at: Vec<(u64, u64)>,
    /// Resumes so far, per stream.
    generations: Vec<u64>,
    /// Sequence number of the next batch sent.
    next_sequence: u64,
}

impl Cursors {
    /// Every one of `streams` streams at `start`.
    fn new(streams: usize, start: (u64, u64)) -> Self {
        Self(Mutex::new(Positions {
            at: vec![start; streams],
            generations: vec![0; streams],
            next_sequence: 0,
        }))
    }

    /// The sequence number of a batch planned at `generation` of `stream` that is about
    /// to be sent, unless a resume replaced its position since (`None`: drop it).
    fn claim(&self, stream: usize, generation: u64) -> Option<u64> {
        let mut c = self.lock();
        (c.generations[stream] == generation).then(|| {
            c.next_sequence += 1;
            c.next_sequence - 1
        })
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

    /// A resume request: `stream` continues at `to`, what was planned before is stale;
    /// the sequence number every batch at the new position will have at least.
    fn resume(&self, stream: usize, to: (u64, u64)) -> u64 {
        let mut c = self.lock();
        c.at[stream] = to;
        c.generations[stream] += 1;
        c.next_sequence
    }

    /// `(epoch, step)` of the next batch to build, of every stream.
    fn positions(&self) -> Vec<(u64, u64)> {
        self.lock().at.clone()
    }

    /// Whether every stream is at or past epoch `epochs`.
    fn all_past(&self, epochs: u64) -> bool {
        self.0
            .lock()
            .map(|c| c.at.iter().all(|(e, _)| *e >= epochs))
            .unwrap_or(true)
    }
}
