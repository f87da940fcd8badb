//! [`Schedule`]: which samples form batch `step` of `epoch` for stream `rank`. The
//! epoch's seeded order (`SampleBuilder::epoch_order`: every dataset group's keyframes
//! times its repeat, shuffled) is dealt round-robin to `host_count × streams` global
//! ranks (host `h` owns global ranks `h·streams .. (h+1)·streams`) and cut into batches
//! of `batch_size`; the last batch of an epoch may be short, no sample is dropped.
//! Every host computes the same order from the seed, so hosts get disjoint shares that
//! together cover each epoch exactly once without talking to each other.
//!
//! Because the order is dealt round-robin, once every rank has taken its first `s`
//! batches of an epoch the job has consumed exactly the epoch's first
//! `min(s · batch_size · ranks, samples)` positions, whatever the number of ranks. That
//! count ([`Schedule::consumed`]) is what a checkpoint keeps: a job resumed with another
//! number of ranks or hosts starts the epoch's remaining positions at that sample
//! ([`Schedule::starting_at`], `--start-sample`), dealt round-robin to its own ranks,
//! so every sample of the epoch is served exactly once across the change.

use std::sync::{Mutex, PoisonError};

/// Which samples make up each batch.
#[derive(Debug)]
pub struct Schedule {
    /// Samples per epoch (all groups, all hosts).
    samples: usize,
    batch_size: usize,
    /// Streams of this host.
    streams: usize,
    /// Global rank of this host's stream 0.
    first_rank: usize,
    /// Streams of all hosts together.
    total_streams: usize,
    seed: u64,
    /// The epoch that starts part-way and its first sample (`(0, 0)`: none does).
    start: Mutex<(u64, usize)>,
}

/// One entry of a batch: plan keyframe and its position in the epoch (keys the draws).
pub type Slot = (u32, u64);

impl Schedule {
    /// A schedule over `samples` samples per epoch for one host.
    pub fn new(samples: usize, batch_size: usize, streams: usize, seed: u64) -> Self {
        Self::for_host(samples, batch_size, streams, (0, 1), seed)
    }

    /// The schedule of host `host.0` of `host.1`, each with `streams` streams: global
    /// rank `host.0 · streams + rank` of `host.1 · streams`.
    pub fn for_host(
        samples: usize,
        batch_size: usize,
        streams: usize,
        host: (u32, u32),
        seed: u64,
    ) -> Self {
        let streams = streams.max(1);
        let hosts = (host.1 as usize).max(1);
        Self {
            samples,
            batch_size: batch_size.max(1),
            streams,
            first_rank: (host.0 as usize).min(hosts - 1) * streams,
            total_streams: hosts * streams,
            seed,
            start: Mutex::new((0, 0)),
        }
    }

    /// This schedule with epoch `epoch` starting at sample `sample` (what a job of any
    /// size had consumed of it): the epoch's remaining samples are dealt to this job's
    /// ranks.
    pub fn starting_at(self, epoch: u64, sample: usize) -> Self {
        self.rebase(epoch, sample);
        self
    }

    /// Moves the part-way epoch to `epoch`, starting at `sample` (at most the epoch).
    pub fn rebase(&self, epoch: u64, sample: usize) {
        *self.start.lock().unwrap_or_else(PoisonError::into_inner) =
            (epoch, sample.min(self.samples));
    }

    /// The epoch that starts part-way and its first sample.
    pub fn start(&self) -> (u64, usize) {
        *self.start.lock().unwrap_or_else(PoisonError::into_inner)
    }

    /// The first sample of `epoch` served.
    pub fn first_sample(&self, epoch: u64) -> usize {
        match self.start() {
            (e, sample) if e == epoch => sample,
            _ => 0,
        }
    }

    /// Samples per epoch.
    pub fn samples(&self) -> usize {
        self.samples
    }

    /// Samples per step of the whole job: batch size × streams of all hosts.
    pub fn global_batch(&self) -> usize {
        self.batch_size * self.total_streams
    }

    /// Samples of `epoch` dealt to this host's stream `rank`.
    fn share(&self, epoch: u64, rank: usize) -> usize {
        if rank >= self.streams {
            return 0;
        }
        let rest = self.samples - self.first_sample(epoch);
        let global = self.first_rank + rank;
        rest / self.total_streams + usize::from(global < rest % self.total_streams)
    }

    /// Batches of stream `rank` in `epoch`.
    pub fn steps(&self, epoch: u64, rank: usize) -> u64 {
        self.share(epoch, rank).div_ceil(self.batch_size) as u64
    }

    /// The fewest batches of any stream of the run in `epoch`, every host's included.
    pub fn min_steps(&self, epoch: u64) -> u64 {
        let rest = self.samples - self.first_sample(epoch);
        (rest / self.total_streams).div_ceil(self.batch_size) as u64
    }

    /// The samples of `epoch` the whole job has consumed once every stream has taken its
    /// first `steps` batches of it: they are the epoch's first ones, in order.
    pub fn consumed(&self, epoch: u64, steps: u64) -> usize {
        let first = self.first_sample(epoch);
        let taken = usize::try_from(steps)
            .unwrap_or(usize::MAX)
            .saturating_mul(self.global_batch());
        first + taken.min(self.samples - first)
    }

    /// Where step `step` of `epoch` starts in the whole run, in samples: `epoch` whole
    /// epochs, then what the job consumed of this one. Streams at the same run sample are
    /// in step; a stream ahead of another by a global batch is one step ahead.
    pub fn run_sample(&self, epoch: u64, step: u64) -> u128 {
        u128::from(epoch) * self.samples as u128 + self.consumed(epoch, step) as u128
    }

    /// The step of `epoch` at which the job has consumed exactly `sample` samples, if
    /// there is one: `sample` is a step boundary of this schedule (the epoch's end
    /// included). `None` when it falls inside a step (a job of another size saved it).
    pub fn step_at(&self, epoch: u64, sample: usize) -> Option<u64> {
        let first = self.first_sample(epoch);
        if sample < first || sample > self.samples {
            return None;
        }
        let taken = sample - first;
        if taken.is_multiple_of(self.global_batch()) {
            Some((taken / self.global_batch()) as u64)
        } else if sample == self.samples {
            Some(taken.div_ceil(self.global_batch()) as u64)
        } else {
            None
        }
    }

    /// The slots of batch `step` of `epoch` for `rank` given the epoch's `order`
    /// (`SampleBuilder::epoch_order`), or `None` past the epoch's end.
    pub fn batch(&self, order: &[u32], epoch: u64, rank: usize, step: u64) -> Option<Vec<Slot>> {
        let first = (step as usize).checked_mul(self.batch_size)?;
        let share = self.share(epoch, rank);
        if first >= share {
            return None;
        }
        let base = self.first_sample(epoch);
        let last = (first + self.batch_size).min(share);
        Some(
            (first..last)
                .map(|j| {
                    let position = base + j * self.total_streams + self.first_rank + rank;
                    (order[position], position as u64)
                })
                .collect(),
        )
    }

    /// The seed.
    pub fn seed(&self) -> u64 {
        self.seed
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::publish::config::ServiceConfig;

    #[test]
    fn ranks_get_disjoint_covering_shares_in_short_last_batches() {
        for (n, b, w) in [
            (6usize, 2usize, 2usize),
            (7, 3, 2),
            (10, 4, 3),
            (5, 1, 5),
            (9, 4, 1),
        ] {
            let schedule = Schedule::new(n, b, w, 7);
            let order: Vec<u32> = (0..n as u32).rev().collect();
            let mut seen = vec![0; n];
            let mut positions = vec![0; n];
            for rank in 0..w {
                let steps = schedule.steps(0, rank);
                for step in 0..steps {
                    let slots = schedule.batch(&order, 0, rank, step).unwrap();
                    assert!(!slots.is_empty() && slots.len() <= b);
                    for (keyframe, position) in slots {
                        seen[keyframe as usize] += 1;
                        positions[position as usize] += 1;
                        assert_eq!(order[position as usize], keyframe);
                    }
                }
                assert!(schedule.batch(&order, 0, rank, steps).is_none());
            }
            assert!(seen.iter().all(|c| *c == 1), "{n} {b} {w}: {seen:?}");
            let fewest = (0..w).map(|r| schedule.steps(0, r)).min().unwrap();
            assert_eq!(schedule.min_steps(0), fewest, "{n} {b} {w}");
            assert!(positions.iter().all(|c| *c == 1));
        }
    }

    #[test]
    fn hosts_get_disjoint_shares_that_cover_each_epoch() {
        for (n, b, w, hosts) in [
            (12usize, 2usize, 1usize, 2u32),
            (13, 3, 2, 2),
            (10, 4, 1, 3),
            (17, 2, 3, 2),
            (8, 1, 2, 4),
        ] {
            let order: Vec<u32> = (0..n as u32).map(|i| (i * 5 + 3) % n as u32).collect();
            let mut positions = vec![0; n];
            let mut per_host = vec![0usize; hosts as usize];
            for host in 0..hosts {
                let schedule = Schedule::for_host(n, b, w, (host, hosts), 7);
                for rank in 0..w {
                    for step in 0..schedule.steps(0, rank) {
                        for (keyframe, position) in schedule.batch(&order, 0, rank, step).unwrap() {
                            positions[position as usize] += 1;
                            per_host[host as usize] += 1;
                            assert_eq!(order[position as usize], keyframe);
                        }
                    }
                    assert!(
                        schedule
                            .batch(&order, 0, rank, schedule.steps(0, rank))
                            .is_none()
                    );
                }
            }
            assert!(
                positions.iter().all(|c| *c == 1),
                "{n} {b} {w} {hosts}: {positions:?}"
            );
            // Balanced: hosts differ by at most one keyframe per stream.
            let (lo, hi) = (
                per_host.iter().min().unwrap(),
                per_host.iter().max().unwrap(),
            );
            assert!(hi - lo <= w, "{per_host:?}");
        }
        // One host of one is the single-host schedule.
        let order: Vec<u32> = (0..9).collect();
        let (a, b) = (
            Schedule::new(9, 2, 3, 1),
            Schedule::for_host(9, 2, 3, (0, 1), 1),
        );
        for rank in 0..3 {
            assert_eq!(a.batch(&order, 0, rank, 1), b.batch(&order, 0, rank, 1));
        }
        let mut bad = ServiceConfig {
            host_count: 2,
            host_rank: 2,
            ..ServiceConfig::default()
        };
        assert!(
            bad.validate()
                .unwrap_err()
                .to_string()
                .contains("host_rank")
        );
        bad.host_rank = 1;
        assert!(bad.validate().is_ok());
    }

    /// Every position of `epoch` served by `ranks` streams on each of `hosts` hosts from
    /// step `from` on: `(position, how many times)`.
    fn served(
        n: usize,
        b: usize,
        (ranks, hosts): (usize, u32),
        start: (u64, usize),
        from_step: u64,
    ) -> Vec<usize> {
        let order: Vec<u32> = (0..n as u32).collect();
        let mut count = vec![0; n];
        for host in 0..hosts {
            let schedule =
                Schedule::for_host(n, b, ranks, (host, hosts), 3).starting_at(start.0, start.1);
            for rank in 0..ranks {
                for step in from_step..schedule.steps(start.0, rank) {
                    for (_, position) in schedule.batch(&order, start.0, rank, step).unwrap() {
                        count[position as usize] += 1;
                    }
                }
            }
        }
        count
    }

    #[test]
    fn a_job_resumed_on_another_size_serves_every_sample_once() {
        // (samples, batch, (ranks, hosts) before, steps taken, (ranks, hosts) after)
        for (n, b, before, steps, after) in [
            (36usize, 3usize, (2usize, 1u32), 2u64, (3usize, 1u32)),
            (36, 3, (3, 1), 2, (2, 1)),
            (37, 2, (2, 2), 3, (2, 1)),
            (37, 4, (1, 1), 5, (3, 2)),
            (10, 4, (2, 1), 1, (3, 1)),
        ] {
            let epoch = 5;
            let old = Schedule::for_host(n, b, before.0, (0, before.1), 3);
            let consumed = old.consumed(epoch, steps);
            assert_eq!(
                consumed,
                (steps as usize * b * before.0 * before.1 as usize).min(n)
            );
            let mut count = vec![0usize; n];
            // A whole epoch of the old job serves every sample once.
            let all_old = served(n, b, before, (epoch, 0), 0);
            // What the old job served before it stopped: every rank's first `steps`.
            let old_sched: Vec<Schedule> = (0..before.1)
                .map(|h| Schedule::for_host(n, b, before.0, (h, before.1), 3))
                .collect();
            let order: Vec<u32> = (0..n as u32).collect();
            for s in &old_sched {
                for rank in 0..before.0 {
                    for step in 0..steps.min(s.steps(epoch, rank)) {
                        for (_, p) in s.batch(&order, epoch, rank, step).unwrap() {
                            count[p as usize] += 1;
                        }
                    }
                }
            }
            // Exactly the epoch's first `consumed` positions.
            assert!(count[..consumed].iter().all(|&c| c == 1), "{count:?}");
            assert!(count[consumed..].iter().all(|&c| c == 0), "{count:?}");
            assert!(all_old.iter().all(|&c| c == 1));
            // The new job from `consumed`: the rest, once.
            for (p, c) in served(n, b, after, (epoch, consumed), 0)
                .into_iter()
                .enumerate()
            {
                count[p] += c;
            }
            assert!(
                count.iter().all(|&c| c == 1),
                "{n} {b} {before:?}->{after:?}: {count:?}"
            );
            // Ranks stay within one batch of each other.
            let new =
                Schedule::for_host(n, b, after.0, (0, after.1), 3).starting_at(epoch, consumed);
            let steps: Vec<u64> = (0..after.0).map(|r| new.steps(epoch, r)).collect();
            let (lo, hi) = (steps.iter().min().unwrap(), steps.iter().max().unwrap());
            assert!(hi - lo <= 1, "{steps:?}");
            assert!(new.min_steps(epoch) <= *lo);
            // The next epoch is whole again.
            assert_eq!(new.first_sample(epoch + 1), 0);
            assert_eq!(new.step_at(epoch, consumed), Some(0));
        }
    }

    #[test]
    fn step_boundaries_map_samples_to_steps() {
        let s = Schedule::new(22, 3, 2, 0);
        assert_eq!(s.global_batch(), 6);
        assert_eq!(s.step_at(1, 0), Some(0));
        assert_eq!(s.step_at(1, 12), Some(2));
        assert_eq!(s.step_at(1, 22), Some(4), "the epoch's end");
        assert_eq!(s.step_at(1, 7), None);
        assert_eq!(s.step_at(1, 23), None);
        assert_eq!(s.consumed(1, 2), 12);
        assert_eq!(s.consumed(1, 9), 22);
        s.rebase(1, 7);
        assert_eq!(s.step_at(1, 7), Some(0));
        assert_eq!(s.step_at(1, 13), Some(1));
        assert_eq!(s.step_at(1, 0), None);
        assert_eq!(s.step_at(2, 0), Some(0));
        assert_eq!(s.consumed(1, 1), 13);
        assert_eq!((s.steps(1, 0), s.steps(1, 1)), (3, 3));
        assert_eq!(s.min_steps(1), 3);
    }
}
