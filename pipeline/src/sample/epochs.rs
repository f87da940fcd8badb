//! What an epoch is made of when dataset groups are weighted ([`crate::drive::groups`]):
//! the [`EpochMix`] of a plan says which keyframes, how many times each, form epoch `e`,
//! and in which order.
//!
//! A group of `n` keyframes with `repeat = r` gives every keyframe `⌊r⌋` entries, plus
//! one entry each for `round((r − ⌊r⌋)·n)` of them chosen afresh each epoch (seeded by
//! `(seed, epoch, group)`): the count per epoch is exact, and a fraction of a group is
//! a different subset every epoch. The entries of every group, in group order, are
//! then shuffled by the epoch's seeded shuffle. An entry's position in the epoch keys
//! its sample's draws, so the two entries of a keyframe served twice are two different
//! samples (other cameras, flips and augmentation). With one group at `repeat = 1` the
//! epoch is the plan's [`Plan::epoch_order`], entry for entry.

use super::plan::Plan;
use super::rng::{Purpose, SampleRng};
use crate::drive::DriveGroup;
use serde::Serialize;
use std::ops::Range;

/// Entries per epoch of a group of `keyframes` keyframes at `repeat`:
/// `⌊r⌋·n + round((r − ⌊r⌋)·n)`.
pub fn per_epoch(repeat: f64, keyframes: usize) -> usize {
    let whole = repeat.floor();
    let extra = ((repeat - whole) * keyframes as f64).round() as usize;
    whole as usize * keyframes + extra.min(keyframes)
}

/// One group's part of every epoch.
#[derive(Debug, Clone, PartialEq, Serialize)]
pub struct GroupShare {
    /// The group's name.
    pub name: String,
    /// Its repeat.
    pub repeat: f64,
    /// Its keyframes in the plan (the plan lists drives in order, a group's drives are
    /// consecutive, so its keyframes are too).
    pub keyframes: Range<u32>,
    /// Its drives in the dataset.
    pub drives: Range<usize>,
    /// Entries per epoch: `⌊r⌋·n + round((r − ⌊r⌋)·n)`.
    pub per_epoch: usize,
}

impl GroupShare {
    /// Keyframes of the group.
    pub fn len(&self) -> usize {
        (self.keyframes.end - self.keyframes.start) as usize
    }

    /// Whether the group has no keyframe.
    pub fn is_empty(&self) -> bool {
        self.keyframes.is_empty()
    }

    /// Every keyframe's guaranteed entries per epoch (`⌊r⌋`).
    fn whole(&self) -> usize {
        self.repeat.floor() as usize
    }

    /// Keyframes drawn for one more entry each epoch.
    fn extra(&self) -> usize {
        self.per_epoch - self.whole() * self.len()
    }
}

/// How the keyframes of a plan make up each epoch.
#[derive(Debug, Clone, PartialEq, Serialize)]
pub struct EpochMix {
    /// Each group's share, in dataset order.
    pub groups: Vec<GroupShare>,
    /// Entries per epoch, all groups.
    pub len: usize,
}

impl EpochMix {
    /// The mix of `plan`'s keyframes over the dataset's `groups` (a group without
    /// keyframes has no share).
    pub fn new(plan: &Plan, groups: &[DriveGroup]) -> Self {
        let shares: Vec<GroupShare> = groups
            .iter()
            .map(|group| {
                let of = |drive: usize| {
                    plan.keyframes
                        .partition_point(|k| (k.drive as usize) < drive) as u32
                };
                let keyframes = of(group.drives.start)..of(group.drives.end);
                let n = (keyframes.end - keyframes.start) as usize;
                GroupShare {
                    name: group.name.clone(),
                    repeat: group.repeat,
                    keyframes,
                    drives: group.drives.clone(),
                    per_epoch: per_epoch(group.repeat, n),
                }
            })
            .collect();
        let len = shares.iter().map(|g| g.per_epoch).sum();
        Self {
            groups: shares,
            len,
        }
    }

    /// One group of every keyframe at `repeat = 1`: the epoch is the plan's shuffle.
    pub fn whole(plan: &Plan) -> Self {
        let drives = plan.keyframes.last().map_or(0, |k| k.drive as usize + 1);
        Self::new(
            plan,
            &[DriveGroup {
                name: crate::drive::groups::DEFAULT_GROUP.into(),
                repeat: 1.0,
                drives: 0..drives,
            }],
        )
    }

    /// The keyframes of `epoch`, one per entry, in the order they are served: each
    /// group's entries (see the module documentation), then the epoch's shuffle.
    pub fn order(&self, seed: u64, epoch: u64) -> Vec<u32> {
        let mut order = Vec::with_capacity(self.len);
        for (g, group) in self.groups.iter().enumerate() {
            for _ in 0..group.whole() {
                order.extend(group.keyframes.clone());
            }
            if group.extra() > 0 {
                let share = Purpose::GroupShare { group: g as u32 };
                let chosen =
                    SampleRng::new(seed, epoch, 0, share).choose(group.len(), group.extra());
                order.extend(chosen.into_iter().map(|i| group.keyframes.start + i as u32));
            }
        }
        SampleRng::new(seed, epoch, 0, Purpose::Shuffle).shuffle(&mut order);
        order
    }

    /// The share of the epoch of each group, in `0..=1`.
    pub fn fractions(&self) -> Vec<f64> {
        self.groups
            .iter()
            .map(|g| g.per_epoch as f64 / self.len.max(1) as f64)
            .collect()
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::sample::plan::KeyframeRef;

    /// A plan of `per_drive` keyframes on each of `drives.len()` drives.
    fn plan(per_drive: &[u32]) -> Plan {
        let mut plan = Plan::default();
        for (d, &n) in per_drive.iter().enumerate() {
            for s in 0..n {
                plan.keyframes.push(KeyframeRef {
                    drive: d as u32,
                    sweep: s,
                    frame_sweeps: vec![s],
                    reused: 0,
                    worst_camera_offset_nanos: 0,
                });
            }
        }
        plan
    }

    fn group(name: &str, repeat: f64, drives: Range<usize>) -> DriveGroup {
        DriveGroup {
            name: name.into(),
            repeat,
            drives,
        }
    }

    #[test]
    fn one_group_at_repeat_one_is_the_plans_shuffle() {
        let plan = plan(&[5, 7, 3]);
        let mix = EpochMix::whole(&plan);
        assert_eq!(mix.len, 15);
        for epoch in 0..4 {
            assert_eq!(mix.order(9, epoch), plan.epoch_order(9, epoch));
        }
    }

    #[test]
    fn repeats_give_exact_counts_and_fractions_change_every_epoch() {
        // Group a: drives 0-1 (12 keyframes) at 0.5; b: drive 2 (5) at 2; c: drive 3 (4)
        // at 1.5.
        let plan = plan(&[4, 8, 5, 4]);
        let mix = EpochMix::new(
            &plan,
            &[
                group("a", 0.5, 0..2),
                group("b", 2.0, 2..3),
                group("c", 1.5, 3..4),
            ],
        );
        let per: Vec<usize> = mix.groups.iter().map(|g| g.per_epoch).collect();
        assert_eq!(per, [6, 10, 6]);
        assert_eq!(mix.len, 22);
        assert_eq!(mix.groups[1].keyframes, 12..17);
        let fractions = mix.fractions();
        assert!((fractions[1] - 10.0 / 22.0).abs() < 1e-12);
        let mut halves = Vec::new();
        for epoch in 0..6 {
            let order = mix.order(3, epoch);
            assert_eq!(order.len(), 22);
            assert_eq!(order, mix.order(3, epoch), "seeded");
            let mut count = [0usize; 21];
            for &k in &order {
                count[k as usize] += 1;
            }
            // a: 6 of its 12 once, none twice; b: every keyframe twice; c: each once,
            // 2 of 4 twice.
            assert!(count[..12].iter().all(|&c| c <= 1));
            assert_eq!(count[..12].iter().sum::<usize>(), 6);
            assert!(count[12..17].iter().all(|&c| c == 2));
            assert!(count[17..].iter().all(|&c| c == 1 || c == 2));
            assert_eq!(count[17..].iter().sum::<usize>(), 6);
            let half: Vec<usize> = (0..12).filter(|&k| count[k] == 1).collect();
            halves.push(half);
        }
        halves.sort();
        halves.dedup();
        assert!(
            halves.len() > 1,
            "the half of group a changes with the epoch"
        );
    }

    #[test]
    fn a_group_without_keyframes_has_no_share() {
        let plan = plan(&[3, 0, 2]);
        let mix = EpochMix::new(
            &plan,
            &[
                group("a", 1.0, 0..1),
                group("empty", 3.0, 1..2),
                group("c", 1.0, 2..3),
            ],
        );
        assert_eq!(mix.groups[1].per_epoch, 0);
        assert_eq!(mix.len, 5);
        let mut order = mix.order(0, 0);
        order.sort_unstable();
        assert_eq!(order, [0, 1, 2, 3, 4]);
    }
}
