//! [`Schedule`]: which keyframes form batch `step` of `epoch` for stream `rank`. The
//! epoch's seeded shuffle (`Plan::epoch_order`) is dealt round-robin to
//! `host_count × streams` global ranks (host `h` owns global ranks
//! `h·streams .. (h+1)·streams`) and cut into batches of `batch_size`; the last batch of
//! an epoch may be short, no keyframe is dropped. Every host computes the same shuffle
//! from the seed, so hosts get disjoint shares that together cover each epoch exactly
//! once without talking to each other.

/// Which keyframes make up each batch.
#[derive(Debug, Clone)]
pub struct Schedule {
    keyframes: usize,
    batch_size: usize,
    /// Streams of this host.
    streams: usize,
    /// Global rank of this host's stream 0.
    first_rank: usize,
    /// Streams of all hosts together.
    total_streams: usize,
    seed: u64,
}

/// One entry of a batch: plan keyframe and its position in the epoch (keys the draws).
pub type Slot = (u32, u64);

impl Schedule {
    /// A schedule over `keyframes` keyframes for one host.
    pub fn new(keyframes: usize, batch_size: usize, streams: usize, seed: u64) -> Self {
        Self::for_host(keyframes, batch_size, streams, (0, 1), seed)
    }

    /// The schedule of host `host.0` of `host.1`, each with `streams` streams: global
    /// rank `host.0 · streams + rank` of `host.1 · streams`.
    pub fn for_host(
        keyframes: usize,
        batch_size: usize,
        streams: usize,
        host: (u32, u32),
        seed: u64,
    ) -> Self {
        let streams = streams.max(1);
        let hosts = (host.1 as usize).max(1);
        Self {
            keyframes,
            batch_size: batch_size.max(1),
            streams,
            first_rank: (host.0 as usize).min(hosts - 1) * streams,
            total_streams: hosts * streams,
            seed,
        }
    }

    /// Keyframes per epoch of this host's stream `rank`.
    fn share(&self, rank: usize) -> usize {
        if rank >= self.streams {
            return 0;
        }
        let global = self.first_rank + rank;
        self.keyframes / self.total_streams
            + usize::from(global < self.keyframes % self.total_streams)
    }

    /// Batches per epoch of stream `rank`.
    pub fn steps(&self, rank: usize) -> u64 {
        self.share(rank).div_ceil(self.batch_size) as u64
    }

    /// The fewest batches per epoch of any stream of the run, every host's included.
    pub fn min_steps(&self) -> u64 {
        (self.keyframes / self.total_streams).div_ceil(self.batch_size) as u64
    }

    /// The slots of batch `step` of `epoch` for `rank` given the epoch's `order`
    /// (`Plan::epoch_order`), or `None` past the epoch's end.
    pub fn batch(&self, order: &[u32], rank: usize, step: u64) -> Option<Vec<Slot>> {
        let first = (step as usize).checked_mul(self.batch_size)?;
        let share = self.share(rank);
        if first >= share {
            return None;
        }
        let last = (first + self.batch_size).min(share);
        Some(
            (first..last)
                .map(|j| {
                    let position = j * self.total_streams + self.first_rank + rank;
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
    use crate::publish::ServiceConfig;

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
                let steps = schedule.steps(rank);
                for step in 0..steps {
                    let slots = schedule.batch(&order, rank, step).unwrap();
                    assert!(!slots.is_empty() && slots.len() <= b);
                    for (keyframe, position) in slots {
                        seen[keyframe as usize] += 1;
                        positions[position as usize] += 1;
                        assert_eq!(order[position as usize], keyframe);
                    }
                }
                assert!(schedule.batch(&order, rank, steps).is_none());
            }
            assert!(seen.iter().all(|c| *c == 1), "{n} {b} {w}: {seen:?}");
            let fewest = (0..w).map(|r| schedule.steps(r)).min().unwrap();
            assert_eq!(schedule.min_steps(), fewest, "{n} {b} {w}");
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
                    for step in 0..schedule.steps(rank) {
                        for (keyframe, position) in schedule.batch(&order, rank, step).unwrap() {
                            positions[position as usize] += 1;
                            per_host[host as usize] += 1;
                            assert_eq!(order[position as usize], keyframe);
                        }
                    }
                    assert!(schedule.batch(&order, rank, schedule.steps(rank)).is_none());
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
            assert_eq!(a.batch(&order, rank, 1), b.batch(&order, rank, 1));
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
}
