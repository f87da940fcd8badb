//! [`Cursors`]: where each stream of the service is, shared by the producer, the
//! publisher and the control server.

use std::sync::{Mutex, MutexGuard};

/// How many steps a stream's batches may run ahead of the stream furthest behind (both
/// built and published). Data-parallel ranks take their steps together: a rank's
/// batches published far ahead fill its queue while it waits for the others, and the
/// publisher, blocked on that full queue, would never get the others theirs. It happens
/// when ranks resume one after another, each from where the job stopped. Two steps keep
/// streams in lockstep with room for epoch ends, where shares differ by one batch.
pub(super) const MAX_LEAD_STEPS: u128 = 2;

/// Where each stream is, a generation counter bumped by every resume so batches
/// prepared for the old position are dropped, and the publisher-wide sequence number of
/// the next batch sent. The producer advances it, the control server moves it, the
/// publisher checks it and takes sequence numbers from it — under one lock, so a resume
/// answered while a batch is on its way names a sequence number above that batch's.
#[derive(Debug)]
pub(super) struct Cursors(Mutex<Positions>);

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
    pub(super) fn new(streams: usize, start: (u64, u64)) -> Self {
        Self(Mutex::new(Positions {
            at: vec![start; streams],
            generations: vec![0; streams],
            next_sequence: 0,
        }))
    }

    /// The sequence number of a batch planned at `generation` of `stream` that is about
    /// to be sent, unless a resume replaced its position since (`None`: drop it).
    pub(super) fn claim(&self, stream: usize, generation: u64) -> Option<u64> {
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
    pub(super) fn position(&self, stream: usize) -> (u64, u64, u64) {
        let c = self.lock();
        let (epoch, step) = c.at[stream];
        (epoch, step, c.generations[stream])
    }

    /// Whether a batch planned at `generation` of `stream` is still wanted (no resume
    /// request replaced its position since).
    pub(super) fn is_current(&self, stream: usize, generation: u64) -> bool {
        self.lock().generations[stream] == generation
    }

    /// Moves `stream` to `to` unless a resume moved it since `generation`; whether it
    /// did.
    pub(super) fn advance(&self, stream: usize, generation: u64, to: (u64, u64)) -> bool {
        let mut c = self.lock();
        let current = c.generations[stream] == generation;
        if current {
            c.at[stream] = to;
        }
        current
    }

    /// A resume request: `stream` continues at `to`, what was planned before is stale;
    /// the sequence number every batch at the new position will have at least.
    pub(super) fn resume(&self, stream: usize, to: (u64, u64)) -> u64 {
        let mut c = self.lock();
        c.at[stream] = to;
        c.generations[stream] += 1;
        c.next_sequence
    }

    /// `(epoch, step)` of the next batch to build, of every stream.
    pub(super) fn positions(&self) -> Vec<(u64, u64)> {
        self.lock().at.clone()
    }

    /// Whether every stream is at or past epoch `epochs`.
    pub(super) fn all_past(&self, epochs: u64) -> bool {
        self.0
            .lock()
            .map(|c| c.at.iter().all(|(e, _)| *e >= epochs))
            .unwrap_or(true)
    }
}
