//! The producer thread: builds batches ahead of the publisher (at most `prefetch`
//! waiting in the channel), stream by stream in turn, each from its stream's cursor,
//! the samples of a batch in parallel (rayon).

use super::config::ServiceConfig;
use super::cursors::{Cursors, MAX_LEAD_STEPS};
use super::metrics::Metrics;
use super::schedule::Schedule;
use crate::sample::{Sample, SampleBuilder, SampleError};
use rayon::prelude::*;
use std::collections::{HashMap, HashSet};
use std::sync::atomic::{AtomicBool, Ordering};
use std::sync::mpsc::SyncSender;
use std::sync::{Mutex, PoisonError};
use std::time::Duration;

/// A batch built by the producer.
pub(super) struct Prepared {
    /// The stream (rank) it is for.
    pub stream: u32,
    /// The stream's generation when it was planned (see [`Cursors`]).
    pub generation: u64,
    /// Its epoch.
    pub epoch: u64,
    /// Its step in the epoch.
    pub step: u64,
    /// The samples built (failed ones left out). Empty when every one failed: the
    /// batch is published lost, so that subscribers still see it and their epoch end.
    pub samples: Vec<Sample>,
    /// Samples of the batch that failed to build.
    pub failed: usize,
}

/// What the producer thread works with.
pub(super) struct Producer<'a> {
    pub builder: &'a SampleBuilder<'a>,
    pub schedule: &'a Schedule,
    pub config: &'a ServiceConfig,
    pub cursors: &'a Cursors,
    pub stop: &'a AtomicBool,
    /// Set while every stream is past the configured epochs (and all it built was
    /// sent): the publisher reads it to tell "done" from "slow".
    pub idle: &'a AtomicBool,
    pub metrics: &'a Metrics,
    /// The failures already logged at ERROR: a file gone or replaced fails every sample
    /// that reads it the same way, said once (each sample is still counted).
    pub said: Mutex<HashSet<String>>,
}

/// Batches of each stream whose reads are requested ahead of their building
/// ([`SampleBuilder::will_read`]): enough to cover the latency of an object store, few
/// enough that the prefetch budget holds them.
const READ_AHEAD_BATCHES: u64 = 2;

/// The most distinct failures remembered in [`Producer::said`].
const SAID_FAILURES: usize = 4096;

impl Producer<'_> {
    /// Builds batches until `stop` or until the publisher hangs up.
    pub fn run(&self, tx: &SyncSender<Prepared>) {
        let streams = self.config.streams() as usize;
        let mut orders: HashMap<u64, Vec<u32>> = HashMap::new();
        let mut finished = vec![false; streams];
        let mut stream = 0usize;
        let mut advised: HashSet<(usize, u64, u64)> = HashSet::new();
        while !self.stop.load(Ordering::SeqCst) {
            let (epoch, step, generation) = self.cursors.position(stream);
            if self.config.epochs > 0 && epoch >= self.config.epochs {
                finished[stream] = true;
                if finished.iter().all(|f| *f) {
                    // Every stream is done: idle until a resume request rewinds one (the
                    // publisher decides when the service ends).
                    self.idle.store(true, Ordering::SeqCst);
                    std::thread::sleep(Duration::from_millis(10));
                    finished.iter_mut().for_each(|f| *f = false);
                }
                stream = (stream + 1) % streams;
                continue;
            }
            self.idle.store(false, Ordering::SeqCst);
            finished[stream] = false;
            if self.too_far_ahead((epoch, step)) {
                // The others' batches first (see `MAX_LEAD_STEPS`).
                stream = (stream + 1) % streams;
                std::thread::yield_now();
                continue;
            }
            if orders.len() > 4 {
                orders.retain(|e, _| *e + 1 >= epoch);
            }
            let order = orders
                .entry(epoch)
                .or_insert_with(|| self.builder.epoch_order(epoch));
            let Some(slots) = self.schedule.batch(order, epoch, stream, step) else {
                // Past the epoch's end: next epoch.
                self.cursors.advance(stream, generation, (epoch + 1, 0));
                continue;
            };
            // What the next batches read is requested now, while this one is built.
            // (This batch's own reads too, the first time: they then go out at once.)
            for ahead in 0..=READ_AHEAD_BATCHES {
                if advised.insert((stream, epoch, step + ahead)) {
                    for &(keyframe, index) in self
                        .schedule
                        .batch(order, epoch, stream, step + ahead)
                        .iter()
                        .flatten()
                    {
                        self.builder.will_read(keyframe as usize, epoch, index);
                    }
                }
            }
            if advised.len() > 4096 {
                advised.retain(|&(_, e, s)| e == epoch && s > step);
            }
            let samples = self.build(&slots, stream, epoch, step);
            if let Some(cache) = self.builder.frame_cache() {
                let stats = cache.stats();
                for (to, from) in [
                    (&self.metrics.frame_hits, &stats.hits),
                    (&self.metrics.frame_misses, &stats.misses),
                    (&self.metrics.frame_bytes, &stats.bytes),
                ] {
                    to.store(from.load(Ordering::Relaxed), Ordering::Relaxed);
                }
            }
            // Advance this stream unless a resume moved it meanwhile. A batch whose
            // samples all failed goes too: left out, its subscribers would wait forever
            // for the step that ends their epoch.
            let current = self.cursors.advance(stream, generation, (epoch, step + 1));
            if current {
                let prepared = Prepared {
                    stream: stream as u32,
                    generation,
                    epoch,
                    step,
                    failed: slots.len() - samples.len(),
                    samples,
                };
                if tx.send(prepared).is_err() {
                    return;
                }
            }
            stream = (stream + 1) % streams;
        }
    }

    /// Whether a stream at `at` is further ahead of the stream furthest behind than the
    /// publisher lets batches go, plus what it holds built ahead (`prefetch`).
    fn too_far_ahead(&self, at: (u64, u64)) -> bool {
        let end = self.config.epochs;
        let run_sample = |(e, s): (u64, u64)| self.schedule.run_sample(e, s);
        let slowest = self
            .cursors
            .positions()
            .into_iter()
            .filter(|(e, _)| end == 0 || *e < end)
            .map(run_sample)
            .min();
        let lead = MAX_LEAD_STEPS + u128::from(self.config.prefetch);
        slowest.is_some_and(|slowest| {
            run_sample(at) >= slowest + lead * self.schedule.global_batch() as u128
        })
    }

    /// The samples of one batch; a sample that fails is counted, logged and left out.
    fn build(
        &self,
        slots: &[super::schedule::Slot],
        stream: usize,
        epoch: u64,
        step: u64,
    ) -> Vec<Sample> {
        let span = tracing::debug_span!("build batch", stream, epoch, step);
        let _entered = span.enter();
        let built: Vec<Result<Sample, SampleError>> = slots
            .par_iter()
            .map(|&(keyframe, index)| self.builder.build_keyframe(keyframe as usize, epoch, index))
            .collect();
        let mut samples = Vec::with_capacity(built.len());
        for (result, (keyframe, _)) in built.into_iter().zip(slots) {
            match result {
                Ok(sample) => {
                    self.metrics.add_stages(&sample.times);
                    samples.push(sample);
                }
                Err(e) => {
                    self.metrics.failed_samples.fetch_add(1, Ordering::Relaxed);
                    let message = e.to_string();
                    let mut said = self.said.lock().unwrap_or_else(PoisonError::into_inner);
                    if said.contains(&message) {
                        tracing::debug!(keyframe, epoch, "sample lost: {message}");
                    } else {
                        tracing::error!(
                            keyframe,
                            epoch,
                            "sample lost: {message} (the same failure of other samples is counted in superflow_failed_samples_total, logged at DEBUG)"
                        );
                        if said.len() < SAID_FAILURES {
                            said.insert(message);
                        }
                    }
                }
            }
        }
        samples
    }
}
