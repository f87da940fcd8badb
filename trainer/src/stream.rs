//! Where a trainer is in the pipeline's stream of batches, and what to do with each batch
//! that arrives: train on it, skip it, or ask the pipeline to continue elsewhere.
//!
//! Every batch carries its stream position (epoch, batch in epoch) and the id of the
//! publisher (pipeline process) that sent it. A [`StreamTracker`] remembers the position
//! of the next batch to train on (unknown until the first step, or the checkpoint's when
//! resuming) and the publisher of the last trained batch, and decides:
//!
//! * the first batch, and every batch at the expected position → [`Action::Train`];
//! * a batch from another publisher (the pipeline died and was restarted) at another
//!   position, or a batch further along the same epoch (the shared broadcast stream was
//!   moved ahead by another trainer's resume) → [`Action::Resume`] at the expected position;
//! * a batch before the expected position (another broadcast subscriber rewound the shared
//!   stream by its resume) → [`Action::Skip`]: it was trained on already;
//! * a batch of a later epoch from the same publisher → trained on (the pipeline moved on).
//!
//! ```
//! use superflow_trainer::stream::{Action, StreamPosition, StreamTracker};
//!
//! let mut stream = StreamTracker::new(None);
//! let first = StreamPosition::new(0, 0);
//! assert_eq!(stream.classify(7, first), Action::Train);
//! stream.trained(first);
//! // Publisher 9 (a restarted pipeline) starts over at batch 0: ask it for batch 1.
//! let at = StreamPosition::new(0, 1);
//! assert_eq!(stream.classify(9, first), Action::Resume { at, restarted: true });
//! stream.resumed(9);
//! assert_eq!(stream.classify(9, at), Action::Train);
//! ```

use std::fmt;

/// A batch's place in a run's stream: its epoch and its number within the epoch
/// (`BatchHeader::epoch`, `BatchHeader::step`). Ordered by epoch, then batch.
#[derive(Debug, Clone, Copy, PartialEq, Eq, PartialOrd, Ord, Hash, Default)]
pub struct StreamPosition {
    /// Epoch.
    pub epoch: u64,
    /// Batch within the epoch.
    pub batch: u64,
}

impl StreamPosition {
    /// Batch `batch` of epoch `epoch`.
    pub fn new(epoch: u64, batch: u64) -> Self {
        Self { epoch, batch }
    }

    /// The position after this one in the same epoch (where a trainer continues after
    /// training on this batch; the pipeline moves to the next epoch by itself).
    pub fn following(self) -> Self {
        Self::new(self.epoch, self.batch + 1)
    }
}

impl fmt::Display for StreamPosition {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        write!(f, "epoch {} batch {}", self.epoch, self.batch)
    }
}

/// What to do with a received batch.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum Action {
    /// Train on it.
    Train,
    /// Drop it: this trainer trained on it already (a broadcast stream rewound by
    /// another subscriber's resume). `skipped` counts such batches so far.
    Skip {
        /// Batches skipped so far, this one included.
        skipped: u64,
    },
    /// Drop it and ask the pipeline to continue the stream at `at`, then report the
    /// answering publisher with [`StreamTracker::resumed`].
    Resume {
        /// The position to continue at: this trainer's next batch.
        at: StreamPosition,
        /// Whether the batch came from another publisher than the last trained one (a
        /// restarted pipeline) rather than from a stream moved ahead.
        restarted: bool,
    },
}

/// The stream-position protocol of one trainer (see the [module docs](self)).
#[derive(Debug, Clone, Default, PartialEq, Eq)]
pub struct StreamTracker {
    /// The position of the next batch to train on, once known.
    expected: Option<StreamPosition>,
    /// The publisher of the last trained batch (or the one that accepted a resume).
    origin: Option<u128>,
    /// Batches skipped as already trained on.
    skipped: u64,
}

impl StreamTracker {
    /// A tracker for a fresh run (`None`: the first batch is trained on, wherever the
    /// stream is) or for a run resumed from a checkpoint whose next batch is `resumed_at`
    /// (the pipeline was asked to continue there).
    pub fn new(resumed_at: Option<StreamPosition>) -> Self {
        Self {
            expected: resumed_at,
            ..Self::default()
        }
    }

    /// Decides what to do with a batch at `position` sent by publisher `origin`. A
    /// [`Action::Train`] takes `origin` as the stream's publisher; call
    /// [`trained`](Self::trained) once the step succeeded.
    pub fn classify(&mut self, origin: u128, position: StreamPosition) -> Action {
        let restarted = self.origin.is_some_and(|o| o != origin);
        if let Some(next) = self.expected
            && position != next
            // A new pipeline began elsewhere, or (broadcast) another trainer's resume
            // moved the shared stream ahead within the epoch.
            && (restarted || (position.epoch == next.epoch && position.batch > next.batch))
        {
            return Action::Resume {
                at: next,
                restarted,
            };
        }
        if self.expected.is_some_and(|next| position < next) {
            self.skipped += 1;
            return Action::Skip {
                skipped: self.skipped,
            };
        }
        self.origin = Some(origin);
        Action::Train
    }

    /// Records a finished step on the batch at `position`: the next one is expected.
    pub fn trained(&mut self, position: StreamPosition) {
        self.expected = Some(position.following());
    }

    /// Records that `publisher` accepted to continue at the expected position.
    pub fn resumed(&mut self, publisher: u128) {
        self.origin = Some(publisher);
    }

    /// The next batch to train on is at `at`: where a pipeline asked to continue at a
    /// sample count said that sample lies in this stream (a job resumed on another
    /// size starts the epoch there, at step 0).
    pub fn expect(&mut self, at: StreamPosition) {
        self.expected = Some(at);
    }

    /// The position of the next batch to train on (what a checkpoint records), once known.
    pub fn next(&self) -> Option<StreamPosition> {
        self.expected
    }

    /// Batches skipped so far as already trained on.
    pub fn skipped(&self) -> u64 {
        self.skipped
    }
}

/// Where a data-parallel rank stands before a step.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum RankState {
    /// It holds the batch at this position.
    At(StreamPosition),
    /// It holds a lost batch at this position (every sample failed in the pipeline): it
    /// counts as that position, with no gradient of its own.
    Lost(StreamPosition),
    /// Its stream ended (the pipeline's last epoch is through for its shard).
    Ended,
    /// It caught a stop signal.
    Stopping,
}

/// The step data-parallel ranks take together: `None` when a rank stops (all stop after
/// the same step) or every rank's stream ended, otherwise the earliest position held.
/// Ranks holding a later batch (their shard began the next epoch while others finish
/// theirs: shards differ by at most one batch, more often after a job resumed on another
/// number of ranks) keep it for a later step, and ranks whose stream ended wait for the
/// others' last batches; neither adds a gradient to this step, so no sample is dropped or
/// repeated. A lost batch holds its position like any other.
pub fn agree(ranks: &[RankState]) -> Option<StreamPosition> {
    if ranks.contains(&RankState::Stopping) {
        return None;
    }
    ranks.iter().filter_map(|r| r.position()).min()
}

/// Whether some rank has samples to train on at `at` (a batch there that is not lost).
/// When none has, the ranks at `at` only count their lost batches: no rank steps, so no
/// update is made from nothing.
pub fn trains_at(ranks: &[RankState], at: StreamPosition) -> bool {
    ranks.contains(&RankState::At(at))
}

impl RankState {
    /// The position of the batch it holds, lost or not.
    pub fn position(self) -> Option<StreamPosition> {
        match self {
            RankState::At(at) | RankState::Lost(at) => Some(at),
            RankState::Ended | RankState::Stopping => None,
        }
    }
}

/// The plan a rank's pipeline serves (the plan fields of its schedule): every rank of a
/// data-parallel job must see the same, or the hosts' pipelines deal different epochs
/// and their shares overlap or leave gaps without anyone noticing.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Default)]
pub struct PlanView {
    /// Digest of what defines the samples (`ScheduleReply::plan_digest`).
    pub plan_digest: u64,
    /// The run's seed.
    pub seed: u64,
    /// Hosts whose pipelines share each epoch.
    pub host_count: u64,
    /// Distinct keyframes of the whole dataset.
    pub keyframes: u64,
    /// Samples per epoch, all hosts.
    pub samples: u64,
    /// Samples per step of the whole job.
    pub global_batch: u64,
    /// Epochs served (0: endless).
    pub epochs: u64,
}

impl PlanView {
    /// Numbers exchanged per rank by [`PlanView::to_words`].
    pub const WORDS: usize = 8;

    /// The plan a schedule names.
    pub fn of(schedule: &superflow_schemas::service::ScheduleReply) -> Self {
        Self {
            plan_digest: schedule.plan_digest,
            seed: schedule.seed,
            host_count: u64::from(schedule.host_count),
            keyframes: schedule.keyframes,
            samples: schedule.samples,
            global_batch: schedule.global_batch,
            epochs: schedule.epochs,
        }
    }

    /// The fields, with what they are called in messages.
    fn fields(&self) -> [(&'static str, u64); 7] {
        [
            ("plan digest", self.plan_digest),
            ("seed", self.seed),
            ("host count", self.host_count),
            ("keyframes", self.keyframes),
            ("samples per epoch", self.samples),
            ("samples per step", self.global_batch),
            ("epochs", self.epochs),
        ]
    }

    /// `plan` (`None`: not known yet) as words for an all-gather: a known-flag, then the
    /// fields.
    pub fn to_words(plan: Option<&Self>) -> [u64; Self::WORDS] {
        let mut words = [0u64; Self::WORDS];
        if let Some(plan) = plan {
            words[0] = 1;
            for (word, (_, value)) in words[1..].iter_mut().zip(plan.fields()) {
                *word = value;
            }
        }
        words
    }

    /// The plan of [`PlanView::to_words`]'s words (`None`: not known).
    pub fn from_words(words: &[u64]) -> Option<Self> {
        match *words {
            [
                1,
                plan_digest,
                seed,
                host_count,
                keyframes,
                samples,
                global_batch,
                epochs,
            ] => Some(Self {
                plan_digest,
                seed,
                host_count,
                keyframes,
                samples,
                global_batch,
                epochs,
            }),
            _ => None,
        }
    }
}

/// Ranks whose pipelines serve another plan than the first rank that knows one.
#[derive(Debug, Clone, PartialEq, Eq, thiserror::Error)]
#[error(
    "{} — every host's pipeline needs the same drives, seed and configuration",
    differences.join("; ")
)]
pub struct PlanMismatch {
    /// One line per differing rank, such as `rank 2's pipeline serves another plan:
    /// keyframes 36 vs 48 on rank 0`.
    pub differences: Vec<String>,
}

/// Checks that every rank that knows its pipeline's plan (`None`: not yet) knows the same
/// one; the error names each differing rank and field, against the first rank that knows
/// one.
pub fn check_plans(plans: &[Option<PlanView>]) -> Result<(), PlanMismatch> {
    let Some((first, reference)) = plans
        .iter()
        .enumerate()
        .find_map(|(rank, plan)| plan.map(|p| (rank, p)))
    else {
        return Ok(());
    };
    let differences: Vec<String> = plans
        .iter()
        .enumerate()
        .filter_map(|(rank, plan)| {
            let plan = (*plan)?;
            let fields: Vec<String> = plan
                .fields()
                .iter()
                .zip(reference.fields())
                .filter(|((_, mine), (_, theirs))| mine != theirs)
                .map(|((name, mine), (_, theirs))| {
                    if *name == "plan digest" {
                        format!("{name} {mine:016x} vs {theirs:016x}")
                    } else {
                        format!("{name} {mine} vs {theirs}")
                    }
                })
                .collect();
            (!fields.is_empty()).then(|| {
                format!(
                    "rank {rank}'s pipeline serves another plan: {} on rank {first}",
                    fields.join(", ")
                )
            })
        })
        .collect();
    if differences.is_empty() {
        Ok(())
    } else {
        Err(PlanMismatch { differences })
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    const A: u128 = 1;
    const B: u128 = 2;

    fn at(epoch: u64, batch: u64) -> StreamPosition {
        StreamPosition::new(epoch, batch)
    }

    /// A tracker that trained on `position` from publisher `origin`.
    fn after(origin: u128, position: StreamPosition) -> StreamTracker {
        let mut s = StreamTracker::new(None);
        assert_eq!(s.classify(origin, position), Action::Train);
        s.trained(position);
        s
    }

    #[test]
    fn the_first_batch_is_trained_wherever_the_stream_is() {
        let mut s = StreamTracker::new(None);
        assert_eq!(s.next(), None);
        assert_eq!(s.classify(A, at(3, 17)), Action::Train);
        s.trained(at(3, 17));
        assert_eq!(s.next(), Some(at(3, 18)));
        assert_eq!(s.skipped(), 0);
    }

    #[test]
    fn batches_in_order_are_trained() {
        let mut s = after(A, at(0, 0));
        for batch in 1..5 {
            assert_eq!(s.classify(A, at(0, batch)), Action::Train);
            s.trained(at(0, batch));
        }
        assert_eq!(s.next(), Some(at(0, 5)));
        // The pipeline moves on to the next epoch by itself.
        assert_eq!(s.classify(A, at(1, 0)), Action::Train);
        s.trained(at(1, 0));
        assert_eq!(s.next(), Some(at(1, 1)));
    }

    #[test]
    fn a_restarted_publisher_elsewhere_is_asked_to_continue_here() {
        let mut s = after(A, at(0, 4));
        // The restarted pipeline begins at the start, or anywhere else.
        for other in [at(0, 0), at(0, 9), at(2, 0)] {
            assert_eq!(
                s.classify(B, other),
                Action::Resume {
                    at: at(0, 5),
                    restarted: true
                }
            );
        }
        s.resumed(B);
        assert_eq!(s.classify(B, at(0, 5)), Action::Train);
        s.trained(at(0, 5));
        assert_eq!(s.next(), Some(at(0, 6)));
        assert_eq!(s.skipped(), 0);
    }

    #[test]
    fn a_restarted_publisher_at_the_expected_position_is_trained() {
        let mut s = after(A, at(0, 4));
        assert_eq!(s.classify(B, at(0, 5)), Action::Train);
        s.trained(at(0, 5));
        // B is now the stream's publisher: its next batch is in order.
        assert_eq!(s.classify(B, at(0, 6)), Action::Train);
    }

    #[test]
    fn a_gap_in_the_epoch_asks_to_continue_here() {
        let mut s = after(A, at(1, 2));
        assert_eq!(
            s.classify(A, at(1, 7)),
            Action::Resume {
                at: at(1, 3),
                restarted: false
            }
        );
        s.resumed(A);
        assert_eq!(s.classify(A, at(1, 3)), Action::Train);
    }

    #[test]
    fn a_broadcast_rewind_is_skipped_and_counted() {
        let mut s = after(A, at(0, 6));
        assert_eq!(s.classify(A, at(0, 2)), Action::Skip { skipped: 1 });
        assert_eq!(s.classify(A, at(0, 3)), Action::Skip { skipped: 2 });
        // An earlier epoch is behind too.
        let mut later = after(A, at(2, 0));
        assert_eq!(later.classify(A, at(1, 9)), Action::Skip { skipped: 1 });
        // Back at the expected position: trained; skipping did not move it.
        assert_eq!(s.next(), Some(at(0, 7)));
        assert_eq!(s.classify(A, at(0, 7)), Action::Train);
        assert_eq!(s.skipped(), 2);
    }

    #[test]
    fn after_a_checkpoint_the_stream_continues_at_its_next_batch() {
        // Resumed from a checkpoint whose next batch is (2, 10); the publisher is unknown.
        let mut s = StreamTracker::new(Some(at(2, 10)));
        assert_eq!(s.next(), Some(at(2, 10)));
        // Batches of the old position still queued: behind → skipped, ahead → resume.
        assert_eq!(s.classify(A, at(2, 4)), Action::Skip { skipped: 1 });
        assert_eq!(
            s.classify(A, at(2, 12)),
            Action::Resume {
                at: at(2, 10),
                restarted: false
            }
        );
        assert_eq!(s.classify(A, at(2, 10)), Action::Train);
        s.trained(at(2, 10));
        assert_eq!(s.next(), Some(at(2, 11)));
    }

    #[test]
    fn ranks_agree_on_the_earliest_batch_or_on_stopping() {
        use RankState::{At, Ended, Stopping};
        let (a, b) = (at(0, 2), at(1, 0));
        assert_eq!(agree(&[At(a), At(a)]), Some(a));
        // Rank 1's shard ended epoch 0 a batch earlier: rank 0 trains alone.
        assert_eq!(agree(&[At(a), At(b)]), Some(a));
        assert_eq!(agree(&[At(b), At(a)]), Some(a));
        assert_eq!(agree(&[At(a), Stopping]), None);
        // Rank 0's stream ended a batch before rank 1's last: rank 1 trains it alone.
        assert_eq!(agree(&[Ended, At(b)]), Some(b));
        assert_eq!(agree(&[Ended, Ended]), None);
        assert_eq!(agree(&[Ended, Stopping, At(a)]), None);
        assert_eq!(agree(&[]), None);
    }

    #[test]
    fn a_lost_batch_holds_its_position_without_training() {
        use RankState::{At, Ended, Lost, Stopping};
        let (a, b) = (at(0, 2), at(1, 0));
        // A rank with a lost batch takes part at its position; the others train there.
        assert_eq!(agree(&[Lost(a), At(a)]), Some(a));
        assert!(trains_at(&[Lost(a), At(a)], a));
        // Every rank's batch at the position is lost: nobody trains, all move on.
        assert_eq!(agree(&[Lost(a), Lost(a), Ended]), Some(a));
        assert!(!trains_at(&[Lost(a), Lost(a), Ended], a));
        // A lost batch of an earlier position goes first; the later batch waits.
        assert_eq!(agree(&[At(b), Lost(a)]), Some(a));
        assert!(!trains_at(&[At(b), Lost(a)], a));
        assert_eq!(agree(&[Lost(a), Stopping]), None);
        assert_eq!(Lost(b).position(), Some(b));
    }

    fn plan(keyframes: u64, seed: u64) -> PlanView {
        PlanView {
            plan_digest: 0xAB,
            seed,
            host_count: 2,
            keyframes,
            samples: keyframes,
            global_batch: 4,
            epochs: 3,
        }
    }

    #[test]
    fn ranks_must_see_one_plan() {
        let same = plan(48, 0);
        assert_eq!(check_plans(&[Some(same), None, Some(same)]), Ok(()));
        assert_eq!(check_plans(&[None, None]), Ok(()));
        let err = check_plans(&[None, Some(same), Some(same), Some(plan(36, 7))])
            .expect_err("rank 3 differs");
        let text = err.to_string();
        assert!(
            text.contains(
                "rank 3's pipeline serves another plan: seed 7 vs 0, keyframes 36 vs 48, samples per epoch 36 vs 48 on rank 1"
            ),
            "{text}"
        );
        assert!(
            text.ends_with("every host's pipeline needs the same drives, seed and configuration"),
            "{text}"
        );
        assert_eq!(err.differences.len(), 1);
        let digest = PlanView {
            plan_digest: 0xCD,
            ..same
        };
        let text = check_plans(&[Some(same), Some(digest)])
            .expect_err("the digest differs")
            .to_string();
        assert!(
            text.contains("plan digest 00000000000000cd vs 00000000000000ab on rank 0"),
            "{text}"
        );
        // Words for the all-gather round-trip; unknown stays unknown.
        for p in [Some(same), None] {
            let words = PlanView::to_words(p.as_ref());
            assert_eq!(PlanView::from_words(&words), p);
        }
    }
}
