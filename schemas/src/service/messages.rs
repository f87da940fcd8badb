//! The messages of a run's request-response services: where a trainer resumes
//! (control) and how long its stream's epochs are (schedule). Their layouts are part of
//! the wire format (`BATCH_FORMAT.md`), mirrored by the Python package.

use iceoryx2::prelude::ZeroCopySend;

/// Asks the pipeline to continue stream `rank` (0 in broadcast mode) at a position of
/// epoch `epoch`: by `sample` when known — the samples of the epoch the whole job (every
/// rank of every host) had consumed, which holds whatever the job's size — else by
/// `step` of this stream. The next batch published on that service is the one at that
/// position. Sent on the control service.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Default, ZeroCopySend)]
#[type_name("superflow::ResumeRequest")]
#[repr(C)]
pub struct ResumeRequest {
    /// Shard rank (0 for the broadcast stream).
    pub rank: u32,
    /// 1 when the request is for the broadcast stream.
    pub broadcast: u32,
    /// Epoch to resume at.
    pub epoch: u64,
    /// Step within that epoch (used when `sample` is [`UNKNOWN`]).
    pub step: u64,
    /// Samples of `epoch` the whole job had consumed ([`UNKNOWN`]: resume by `step`).
    pub sample: u64,
    /// Samples per step of the whole job that saved the position (batch size × streams
    /// of all hosts; [`UNKNOWN`] when not known). A `step` saved by a job of another
    /// size names another position: such a request is refused (reason 3).
    pub global_batch: u64,
}

/// A field a request does not know.
pub const UNKNOWN: u64 = u64::MAX;

/// Where a stream continues (a resume request) or a service starts.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum ResumeAt {
    /// At `step` of `epoch` of the stream: a position of a job of this size.
    Step {
        /// The epoch.
        epoch: u64,
        /// The step of the stream.
        step: u64,
    },
    /// After `sample` samples of `epoch`, consumed by the whole job (every rank and
    /// host) that saved the position with `global_batch` samples per step ([`UNKNOWN`]
    /// when not known): holds across a change of the job's size.
    Sample {
        /// The epoch.
        epoch: u64,
        /// Samples of it the job had consumed.
        sample: u64,
        /// Samples per step of the job that saved it.
        global_batch: u64,
    },
}

impl ResumeAt {
    /// The request of stream `rank` (`broadcast`: the broadcast stream).
    pub fn request(self, rank: u32, broadcast: bool) -> ResumeRequest {
        match self {
            ResumeAt::Step { epoch, step } => ResumeRequest::at_step(rank, broadcast, epoch, step),
            ResumeAt::Sample {
                epoch,
                sample,
                global_batch,
            } => ResumeRequest {
                sample,
                global_batch,
                ..ResumeRequest::at_step(rank, broadcast, epoch, UNKNOWN)
            },
        }
    }

    /// The epoch.
    pub fn epoch(self) -> u64 {
        match self {
            ResumeAt::Step { epoch, .. } | ResumeAt::Sample { epoch, .. } => epoch,
        }
    }
}

impl ResumeRequest {
    /// A request by step, the position's job size unknown.
    pub fn at_step(rank: u32, broadcast: bool, epoch: u64, step: u64) -> Self {
        Self {
            rank,
            broadcast: u32::from(broadcast),
            epoch,
            step,
            sample: UNKNOWN,
            global_batch: UNKNOWN,
        }
    }
}

/// The pipeline's answer to a [`ResumeRequest`].
#[derive(Debug, Clone, Copy, PartialEq, Eq, Default, ZeroCopySend)]
#[type_name("superflow::ResumeReply")]
#[repr(C)]
pub struct ResumeReply {
    /// 1: the stream continues at the requested position; 0: refused (see `reason`).
    pub accepted: u32,
    /// Why a request was refused: 0 accepted; [`ResumeReply::NO_SUCH_STREAM`] (1);
    /// [`ResumeReply::OUT_OF_RANGE`] (2); [`ResumeReply::OTHER_JOB_SIZE`] (3);
    /// [`ResumeReply::RUN_COMPLETE`] (4, and `epoch` holds the configured epoch count).
    pub reason: u32,
    /// Sequence number of the first batch at the new position (publisher-wide).
    pub next_sequence: u64,
    /// Low 64 bits of the id of the publisher that will send it (batches of an earlier,
    /// dead pipeline carry another id).
    pub publisher_lo: u64,
    /// High 64 bits of that id.
    pub publisher_hi: u64,
    /// Epoch of the first batch at the new position; refused with
    /// [`ResumeReply::RUN_COMPLETE`]: the epochs the pipeline serves (`--epochs`).
    pub epoch: u64,
    /// Its step in this stream (a request by sample names the step it became).
    pub step: u64,
}

impl ResumeReply {
    /// `reason`: no such stream (rank out of range, or the pipeline runs in the other
    /// mode).
    pub const NO_SUCH_STREAM: u32 = 1;
    /// `reason`: a position that does not exist: a step past its epoch's end, a sample
    /// past the epoch's samples, in an epoch before the last.
    pub const OUT_OF_RANGE: u32 = 2;
    /// `reason`: a step saved by a job of another size (`global_batch` differs): resume
    /// by sample.
    pub const OTHER_JOB_SIZE: u32 = 3;
    /// `reason`: the run is complete. The position is at or past the end of the
    /// configured epochs (`--epochs E`): epoch `E` or later, or the end of epoch `E - 1`
    /// (its last step + 1, or all its samples). Nothing is left to serve; the reply's
    /// `epoch` is `E`. A requeued job of a finished run gets this, not an error.
    pub const RUN_COMPLETE: u32 = 4;

    /// The publisher id (iceoryx2 `UniquePublisherId` value).
    pub fn publisher(&self) -> u128 {
        (u128::from(self.publisher_hi) << 64) | u128::from(self.publisher_lo)
    }
}

/// Asks the pipeline how its stream `rank` (0 in broadcast mode) is scheduled. Sent on
/// the schedule service; the answer comes from a thread of its own, so it never waits
/// behind a publisher blocked on a full queue.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Default, ZeroCopySend)]
#[type_name("superflow::ScheduleRequest")]
#[repr(C)]
pub struct ScheduleRequest {
    /// Shard rank (0 for the broadcast stream).
    pub rank: u32,
    /// 1 when the request is for the broadcast stream.
    pub broadcast: u32,
}

/// The pipeline's answer to a [`ScheduleRequest`]. With it a subscriber knows which batch
/// ends an epoch of its stream (step `steps - 1`, or `start_steps - 1` in epoch
/// `start_epoch`) and which ends the stream (that step of epoch `epochs - 1`): only
/// `--epochs` reached ends a stream, a pipeline stopped by a signal and restarted does
/// not. It also tells how many samples of an epoch the whole job has consumed at a
/// position ([`ScheduleReply::consumed`]): what a checkpoint keeps so that a job resumes
/// on any number of ranks and hosts.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Default, ZeroCopySend)]
#[type_name("superflow::ScheduleReply")]
#[repr(C)]
pub struct ScheduleReply {
    /// 1: the fields below hold the stream's schedule; 0: no such stream (rank out of
    /// range, or the pipeline runs in the other mode).
    pub known: u32,
    /// 0, reserved.
    pub reserved: u32,
    /// Batches per epoch of this stream.
    pub steps: u64,
    /// The fewest batches per epoch of any stream of the run, all hosts included: where
    /// data-parallel ranks stop an epoch together when the keyframes do not divide evenly.
    pub min_steps: u64,
    /// Epochs the pipeline serves (`--epochs`); 0: endless.
    pub epochs: u64,
    /// Low 64 bits of the id of the stream's publisher.
    pub publisher_lo: u64,
    /// High 64 bits of that id.
    pub publisher_hi: u64,
    /// Samples per epoch, all ranks and hosts together (every dataset group's keyframes
    /// times its repeat).
    pub samples: u64,
    /// Samples per step of the whole job: batch size × streams of all hosts.
    pub global_batch: u64,
    /// The epoch that starts part-way, at sample `start_sample` (a job resumed on
    /// another size: `--start-sample`, or a resume request by sample); every other epoch
    /// starts at sample 0.
    pub start_epoch: u64,
    /// See `start_epoch`.
    pub start_sample: u64,
    /// Batches of this stream in epoch `start_epoch`.
    pub start_steps: u64,
    /// The fewest batches of any stream in epoch `start_epoch`.
    pub start_min_steps: u64,
    /// The run's seed (`[sample] seed`): with `(epoch, sample)` it fixes every draw.
    pub seed: u64,
    /// This pipeline's host among `host_count` (`[service] host_rank`).
    pub host_rank: u32,
    /// Hosts whose pipelines share each epoch (`[service] host_count`).
    pub host_count: u32,
    /// Distinct keyframes of the whole dataset (every host's share, before the dataset
    /// groups' repeats).
    pub keyframes: u64,
    /// A digest of what defines the samples served: the seed, the sample recipe, the
    /// dataset groups with their repeats, and per drive its keyframes (count and
    /// stamps); never file paths. Every host of one job must show the same digest, or
    /// its pipelines deal different epochs and the hosts' shares overlap or leave gaps.
    pub plan_digest: u64,
}

impl ScheduleReply {
    /// The publisher id (iceoryx2 `UniquePublisherId` value).
    pub fn publisher(&self) -> u128 {
        (u128::from(self.publisher_hi) << 64) | u128::from(self.publisher_lo)
    }

    /// Whether `epoch` starts part-way (at `start_sample > 0`).
    fn part_way(&self, epoch: u64) -> bool {
        epoch == self.start_epoch && self.start_sample > 0
    }

    /// Batches of this stream in `epoch`.
    pub fn steps_in(&self, epoch: u64) -> u64 {
        if self.part_way(epoch) {
            self.start_steps
        } else {
            self.steps
        }
    }

    /// The fewest batches of any stream in `epoch`.
    pub fn min_steps_in(&self, epoch: u64) -> u64 {
        if self.part_way(epoch) {
            self.start_min_steps
        } else {
            self.min_steps
        }
    }

    /// Whether the batch at `(epoch, step)` is the last of its epoch in this stream.
    pub fn ends_epoch(&self, epoch: u64, step: u64) -> bool {
        self.known == 1 && step + 1 >= self.steps_in(epoch)
    }

    /// Whether the batch at `(epoch, step)` is the last of the stream.
    pub fn ends_stream(&self, epoch: u64, step: u64) -> bool {
        self.ends_epoch(epoch, step) && self.epochs > 0 && epoch + 1 >= self.epochs
    }

    /// The samples of `epoch` the whole job has consumed once every stream has taken its
    /// first `steps` batches of it (data-parallel ranks step together): the epoch's
    /// first sample plus `steps` global batches, at most the epoch. Keyframes are dealt
    /// round-robin, so those samples are exactly the epoch's first ones in its order.
    pub fn consumed(&self, epoch: u64, steps: u64) -> u64 {
        let first = if self.part_way(epoch) {
            self.start_sample.min(self.samples)
        } else {
            0
        };
        first
            + steps
                .saturating_mul(self.global_batch)
                .min(self.samples - first)
    }

    /// The step of this stream at which a resume by `sample` of `epoch` continues: the
    /// step boundary at that sample, or 0 when it falls inside a step (the pipeline then
    /// starts the epoch there, see `ResumeRequest`).
    pub fn step_at(&self, epoch: u64, sample: u64) -> u64 {
        let first = if self.part_way(epoch) {
            self.start_sample
        } else {
            0
        };
        match sample.checked_sub(first) {
            Some(taken) if self.global_batch > 0 && taken.is_multiple_of(self.global_batch) => {
                taken / self.global_batch
            }
            Some(taken) if self.global_batch > 0 && sample == self.samples => {
                taken.div_ceil(self.global_batch)
            }
            _ => 0,
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn a_schedule_says_which_batches_end_an_epoch_and_the_stream() {
        let reply = ScheduleReply {
            known: 1,
            steps: 3,
            min_steps: 2,
            epochs: 2,
            ..ScheduleReply::default()
        };
        assert!(!reply.ends_epoch(0, 1) && reply.ends_epoch(0, 2));
        assert!(!reply.ends_stream(0, 2) && !reply.ends_stream(1, 1));
        assert!(reply.ends_stream(1, 2));
        let endless = ScheduleReply { epochs: 0, ..reply };
        assert!(endless.ends_epoch(7, 2) && !endless.ends_stream(7, 2));
        assert!(!ScheduleReply::default().ends_epoch(0, 0));
    }

    #[test]
    fn a_schedule_counts_what_the_job_consumed_and_the_part_way_epoch() {
        // 22 samples an epoch, 2 ranks of batches of 3: 6 a step. Epoch 4 resumed at 10.
        let reply = ScheduleReply {
            known: 1,
            steps: 4,
            min_steps: 3,
            samples: 22,
            global_batch: 6,
            start_epoch: 4,
            start_sample: 10,
            start_steps: 2,
            start_min_steps: 2,
            ..ScheduleReply::default()
        };
        assert_eq!(reply.consumed(3, 0), 0);
        assert_eq!(reply.consumed(3, 2), 12);
        assert_eq!(reply.consumed(3, 4), 22, "at most the epoch");
        assert_eq!(reply.consumed(4, 0), 10);
        assert_eq!(reply.consumed(4, 1), 16);
        assert_eq!(reply.consumed(4, 2), 22);
        assert_eq!((reply.steps_in(4), reply.steps_in(5)), (2, 4));
        assert_eq!((reply.min_steps_in(4), reply.min_steps_in(0)), (2, 3));
        assert!(reply.ends_epoch(4, 1) && !reply.ends_epoch(5, 1));
        assert_eq!(reply.step_at(3, 12), 2);
        assert_eq!(reply.step_at(3, 22), 4);
        assert_eq!(
            reply.step_at(3, 13),
            0,
            "inside a step: the epoch starts there"
        );
        assert_eq!(reply.step_at(4, 16), 1);
    }

    /// The offsets `BATCH_FORMAT.md` documents and the Python package mirrors.
    #[test]
    fn reply_layouts_match_the_documented_offsets() {
        use std::mem::{offset_of, size_of};
        assert_eq!(size_of::<ScheduleReply>(), 128);
        assert_eq!(offset_of!(ScheduleReply, start_min_steps), 88);
        assert_eq!(offset_of!(ScheduleReply, seed), 96);
        assert_eq!(offset_of!(ScheduleReply, host_rank), 104);
        assert_eq!(offset_of!(ScheduleReply, host_count), 108);
        assert_eq!(offset_of!(ScheduleReply, keyframes), 112);
        assert_eq!(offset_of!(ScheduleReply, plan_digest), 120);
        assert_eq!(size_of::<ResumeReply>(), 48);
        assert_eq!(offset_of!(ResumeReply, epoch), 32);
        assert_eq!(size_of::<ResumeRequest>(), 40);
        assert_eq!(
            [
                ResumeReply::NO_SUCH_STREAM,
                ResumeReply::OUT_OF_RANGE,
                ResumeReply::OTHER_JOB_SIZE,
                ResumeReply::RUN_COMPLETE
            ],
            [1, 2, 3, 4]
        );
    }
}
