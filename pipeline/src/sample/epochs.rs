//! What an epoch is made of when dataset groups are weighted ([`crate::drive::groups`]):
//! the [`EpochMix`] of a plan says which keyframes, how many times each, form epoch `e`,
//! and in which order ([`EpochOrder`]).
//!
//! A group of `n` keyframes with `repeat = r` gives every keyframe `⌊r⌋` entries, plus
//! one entry each for `round((r − ⌊r⌋)·n)` of them chosen afresh each epoch (seeded by
//! `(seed, epoch, group)`): the count per epoch is exact, and a fraction of a group is
//! a different subset every epoch. An entry's position in the epoch keys its sample's
//! draws, so the two entries of a keyframe served twice are two different samples
//! (other cameras, flips and augmentation).
//!
//! The order of the entries is the epoch's seeded shuffle (`global`), or blocks of
//! consecutive keyframes of one drive served side by side (`blocks`, see
//! [`EpochOrder::Blocks`]). With one group at `repeat = 1` and the `global` order the
//! epoch is the plan's [`Plan::epoch_order`], entry for entry.

use super::plan::Plan;
use super::rng::{Purpose, SampleRng};
use crate::drive::DriveGroup;
use serde::{Deserialize, Serialize};
use std::ops::Range;

/// How the entries of an epoch are ordered (`[service] order`, `block_length`,
/// `open_blocks`). The order says which keyframe each position of the epoch names; the
/// sample at a position is a function of `(seed, epoch, position)` and that keyframe
/// alone, whichever order named it.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Default, Serialize, Deserialize)]
#[serde(rename_all = "snake_case")]
pub enum EpochOrder {
    /// Every entry shuffled over the whole epoch.
    #[default]
    Global,
    /// The entries cut into blocks of at most `length` consecutive keyframes of one
    /// drive (a run's first block ends at a seeded phase, so block boundaries move from
    /// epoch to epoch); the blocks shuffled; then `open` blocks served side by side,
    /// position `p` taking the next keyframe of open block `p mod open`, and a block
    /// that runs out replaced by the next one. Consecutive positions come from
    /// different blocks while `open` are open, and each block's keyframes are served in
    /// time order, `open` positions apart: the frames one keyframe shares with the next
    /// are still at hand when the next is built.
    Blocks {
        /// Keyframes a block, at most.
        length: u32,
        /// Blocks open at once.
        open: u32,
    },
}

/// An epoch's order with the block of every position (positions of the `global` order
/// are each a block of their own).
#[derive(Debug, Clone, PartialEq, Eq)]
pub struct Arrangement {
    /// The plan keyframe of each position.
    pub keyframes: Vec<u32>,
    /// The block of each position, numbered in serving order.
    pub blocks: Vec<u32>,
}

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
    /// How the entries are ordered.
    pub order: EpochOrder,
    /// The drive of each plan keyframe (where blocks end).
    #[serde(skip)]
    drive_of: Vec<u32>,
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
            order: EpochOrder::Global,
            drive_of: plan.keyframes.iter().map(|k| k.drive).collect(),
        }
    }

    /// This mix with its entries ordered by `order`.
    pub fn ordered(mut self, order: EpochOrder) -> Self {
        self.order = order;
        self
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
    /// group's entries (see the module documentation), in the epoch's order.
    pub fn order(&self, seed: u64, epoch: u64) -> Vec<u32> {
        match self.order {
            EpochOrder::Global => self.shuffled(seed, epoch),
            EpochOrder::Blocks { .. } => self.arrange(seed, epoch).keyframes,
        }
    }

    /// [`Self::order`] with the block of every position.
    pub fn arrange(&self, seed: u64, epoch: u64) -> Arrangement {
        match self.order {
            EpochOrder::Global => {
                let keyframes = self.shuffled(seed, epoch);
                let blocks = (0..keyframes.len() as u32).collect();
                Arrangement { keyframes, blocks }
            }
            EpochOrder::Blocks { length, open } => {
                let blocks = self.blocks(seed, epoch, length.max(1) as usize);
                interleave(blocks, open.max(1) as usize)
            }
        }
    }

    /// Every entry of `epoch` in runs of ascending keyframes: each whole repeat of a
    /// group, then the keyframes drawn for its fraction.
    fn runs(&self, seed: u64, epoch: u64) -> Vec<Vec<u32>> {
        let mut runs = Vec::new();
        for (g, group) in self.groups.iter().enumerate() {
            for _ in 0..group.whole() {
                runs.push(group.keyframes.clone().collect());
            }
            if group.extra() > 0 {
                let share = Purpose::GroupShare { group: g as u32 };
                let chosen =
                    SampleRng::new(seed, epoch, 0, share).choose(group.len(), group.extra());
                runs.push(
                    chosen
                        .into_iter()
                        .map(|i| group.keyframes.start + i as u32)
                        .collect(),
                );
            }
        }
        runs
    }

    /// The `global` order: every entry, shuffled.
    fn shuffled(&self, seed: u64, epoch: u64) -> Vec<u32> {
        let mut order: Vec<u32> = self.runs(seed, epoch).concat();
        SampleRng::new(seed, epoch, 0, Purpose::Shuffle).shuffle(&mut order);
        order
    }

    /// The blocks of `epoch`, shuffled: each run cut where its drive changes, then into
    /// blocks of `length` after a first one of a seeded `1..=length`.
    fn blocks(&self, seed: u64, epoch: u64, length: usize) -> Vec<Vec<u32>> {
        let mut blocks = Vec::new();
        let mut piece = 0u32;
        for run in self.runs(seed, epoch) {
            for same_drive in
                run.chunk_by(|a, b| self.drive_of[*a as usize] == self.drive_of[*b as usize])
            {
                let phase = Purpose::BlockPhase { run: piece };
                piece += 1;
                let first = 1 + SampleRng::new(seed, epoch, 0, phase).below(length as u64) as usize;
                let (head, rest) = same_drive.split_at(first.min(same_drive.len()));
                blocks.push(head.to_vec());
                blocks.extend(rest.chunks(length).map(<[u32]>::to_vec));
            }
        }
        SampleRng::new(seed, epoch, 0, Purpose::Shuffle).shuffle(&mut blocks);
        blocks
    }

    /// The share of the epoch of each group, in `0..=1`.
    pub fn fractions(&self) -> Vec<f64> {
        self.groups
            .iter()
            .map(|g| g.per_epoch as f64 / self.len.max(1) as f64)
            .collect()
    }
}

/// `blocks` served `open` side by side: position `p` takes the next keyframe of open
/// block `p mod open`; a block that runs out is replaced by the next one, and once none
/// is left the open ones go on round the fewer places.
fn interleave(blocks: Vec<Vec<u32>>, open: usize) -> Arrangement {
    let len = blocks.iter().map(Vec::len).sum();
    let mut keyframes = Vec::with_capacity(len);
    let mut block_of = Vec::with_capacity(len);
    let mut next = blocks.into_iter().enumerate();
    // (block number, its keyframes, how many are served)
    let mut lanes: Vec<(u32, Vec<u32>, usize)> = Vec::with_capacity(open);
    for (b, block) in next.by_ref().take(open) {
        lanes.push((b as u32, block, 0));
    }
    while !lanes.is_empty() {
        let mut lane = 0;
        while lane < lanes.len() {
            let (b, block, served) = &mut lanes[lane];
            if let Some(&k) = block.get(*served) {
                *served += 1;
                keyframes.push(k);
                block_of.push(*b);
                lane += 1;
            } else if let Some((b, block)) = next.next() {
                lanes[lane] = (b as u32, block, 0);
            } else {
                lanes.remove(lane);
            }
        }
    }
    Arrangement {
        keyframes,
        blocks: block_of,
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

    #[test]
    fn blocks_hold_the_same_entries_as_the_global_order() {
        // Weighted groups too: a fraction, a whole repeat, a repeat and a half.
        let plan = plan(&[4, 8, 5, 4, 30]);
        let groups = [
            group("a", 0.5, 0..2),
            group("b", 2.0, 2..3),
            group("c", 1.5, 3..5),
        ];
        let global = EpochMix::new(&plan, &groups);
        let blocks =
            EpochMix::new(&plan, &groups).ordered(EpochOrder::Blocks { length: 4, open: 3 });
        for epoch in 0..5 {
            let mut a = global.order(11, epoch);
            let arranged = blocks.arrange(11, epoch);
            assert_eq!(arranged.keyframes, blocks.order(11, epoch));
            let mut b = arranged.keyframes.clone();
            a.sort_unstable();
            b.sort_unstable();
            assert_eq!(a, b, "the same entries, each as often");
        }
    }

    #[test]
    fn a_block_is_consecutive_keyframes_of_one_drive_served_open_apart() {
        let plan = plan(&[10, 3, 17, 9]);
        let (length, open) = (4u32, 3usize);
        let mix = EpochMix::whole(&plan).ordered(EpochOrder::Blocks {
            length,
            open: open as u32,
        });
        let drive_of = |k: u32| plan.keyframes[k as usize].drive;
        let mut firsts = Vec::new();
        for epoch in 0..6 {
            let a = mix.arrange(5, epoch);
            assert_eq!(a, mix.arrange(5, epoch), "seeded");
            let count = a.blocks.iter().max().map_or(0, |b| b + 1);
            let mut first_length = Vec::new();
            for b in 0..count {
                let positions: Vec<usize> =
                    (0..a.blocks.len()).filter(|&p| a.blocks[p] == b).collect();
                let keys: Vec<u32> = positions.iter().map(|&p| a.keyframes[p]).collect();
                assert!(
                    !keys.is_empty() && keys.len() <= length as usize,
                    "{keys:?}"
                );
                assert!(
                    keys.windows(2).all(|w| w[1] == w[0] + 1),
                    "consecutive, in time order: {keys:?}"
                );
                assert!(
                    keys.iter().all(|&k| drive_of(k) == drive_of(keys[0])),
                    "one drive"
                );
                first_length.push((keys[0], keys.len()));
            }
            firsts.push(first_length);
            // While every place is taken, `open` consecutive positions are `open` blocks.
            let full = a.blocks.len() - 2 * (length as usize) * open;
            for p in 0..full {
                let mut window: Vec<u32> = a.blocks[p..p + open].to_vec();
                window.sort_unstable();
                window.dedup();
                assert_eq!(window.len(), open, "positions {p}.. of epoch {epoch}");
            }
        }
        firsts.dedup();
        assert!(firsts.len() > 1, "blocks change with the epoch");
    }

    #[test]
    fn one_open_block_serves_blocks_whole_one_after_another() {
        let plan = plan(&[6, 5]);
        let mix = EpochMix::whole(&plan).ordered(EpochOrder::Blocks { length: 2, open: 1 });
        let a = mix.arrange(1, 0);
        assert!(
            a.blocks
                .windows(2)
                .all(|w| w[1] == w[0] || w[1] == w[0] + 1)
        );
        let mut sorted = a.keyframes.clone();
        sorted.sort_unstable();
        assert_eq!(sorted, (0..11).collect::<Vec<u32>>());
    }
}
