//! The control server (request-response on `superflow/<run>/control`): a subscriber
//! asks to resume its stream at a position of an epoch — by the samples of the epoch the
//! whole job had consumed (what checkpoints keep; it holds across a change of the job's
//! size), or by its own step; an accepted request moves the stream's cursor and bumps
//! its generation, so batches built for the old position are dropped. A sample that
//! falls inside a step of this pipeline's schedule (the checkpoint was written by a job
//! of another size) makes that epoch start there for every stream
//! ([`Schedule::rebase`]): each rank of the resumed job asks for the same sample. The
//! reply names the position, and the sequence number and publisher of the first batch
//! there. It answers from a thread and node of its own: a publisher waiting on one
//! rank's full queue (that rank waits for the others in a collective) never keeps
//! another rank's resume request from its answer.
//!
//! The schedule server (request-response on `superflow/<run>/schedule`, its own thread
//! and node: it answers while the publisher waits on a full queue) tells a subscriber
//! how many batches an epoch of its stream has and how many epochs the run serves, so it
//! knows which batch ends an epoch and which ends the stream.

use super::config::{Mode, ServiceConfig};
use super::cursors::Cursors;
use super::error::ServiceError;
use super::metrics::Metrics;
use super::plan_id::PlanId;
use super::schedule::Schedule;
use iceoryx2::prelude::*;
use std::sync::atomic::{AtomicBool, Ordering};
use std::time::Duration;
use superflow_schemas::service::{
    self as names, ResumeReply, ResumeRequest, ScheduleReply, ScheduleRequest, UNKNOWN,
};

/// What a resume request is checked against and acts on.
pub(super) struct ResumeContext<'a> {
    pub config: &'a ServiceConfig,
    pub schedule: &'a Schedule,
    pub cursors: &'a Cursors,
    pub metrics: &'a Metrics,
}

/// The control server's thread: answers resume requests until the service stops.
pub(super) struct ControlAnswers<'a> {
    pub iox: &'a iceoryx2::config::Config,
    pub run: &'a str,
    /// Publisher id of each stream, sent back in the reply.
    pub publishers: Vec<u128>,
    pub streams: ResumeContext<'a>,
}

impl ControlAnswers<'_> {
    /// Answers resume requests until `stop`; a service that cannot be set up is logged
    /// (trainers then cannot resume and say so).
    pub fn serve(&self, stop: &AtomicBool) {
        if let Err(e) = self.serve_until(stop) {
            tracing::error!(
                "control service of run {}: {e}; subscribers cannot ask to resume",
                self.run
            );
        }
    }

    fn serve_until(&self, stop: &AtomicBool) -> Result<(), ServiceError> {
        serve_requests(
            self.iox,
            "control",
            |node| names::open_control_service(node, self.run),
            stop,
            |ask: &ResumeRequest| {
                let publisher = self.publishers.get(ask.rank as usize).copied().unwrap_or(0);
                ResumeReply {
                    publisher_lo: publisher as u64,
                    publisher_hi: (publisher >> 64) as u64,
                    ..decide(ask, &self.streams)
                }
            },
        )
    }
}

/// Answers the requests of a run's request-response service (`what`: its name in logs)
/// from a node of its own, every few milliseconds until `stop`; each reply is
/// `answer(request)`.
fn serve_requests<Req, Resp>(
    iox: &iceoryx2::config::Config,
    what: &str,
    open: impl FnOnce(
        &Node<ipc::Service>,
    ) -> Result<
        iceoryx2::service::port_factory::request_response::PortFactory<
            ipc::Service,
            Req,
            (),
            Resp,
            (),
        >,
        superflow_schemas::service::ServiceSetupError,
    >,
    stop: &AtomicBool,
    mut answer: impl FnMut(&Req) -> Resp,
) -> Result<(), ServiceError>
where
    Req: std::fmt::Debug + ZeroCopySend + Copy,
    Resp: std::fmt::Debug + ZeroCopySend + Copy,
{
    let node = NodeBuilder::new()
        .config(iox)
        .signal_handling_mode(SignalHandlingMode::Disabled)
        .create::<ipc::Service>()
        .map_err(ServiceError::ipc(format!(
            "creating the {what} server's node"
        )))?;
    let service = open(&node)?;
    let server = service
        .server_builder()
        .create()
        .map_err(ServiceError::ipc(format!("{what} server")))?;
    while !stop.load(Ordering::SeqCst) {
        loop {
            let request = match server.receive() {
                Ok(Some(r)) => r,
                Ok(None) => break,
                Err(e) => {
                    tracing::warn!("{what} service: {e:?}");
                    break;
                }
            };
            let reply = answer(request.payload());
            match request.loan_uninit() {
                Ok(response) => {
                    if let Err(e) = response.write_payload(reply).send() {
                        tracing::warn!("{what} reply: {e:?}");
                    }
                }
                Err(e) => tracing::warn!("{what} reply: {e:?}"),
            }
        }
        std::thread::sleep(Duration::from_millis(5));
    }
    Ok(())
}

/// Accepts (and carries out) or refuses one request: `accepted`, `reason`, `epoch`,
/// `step` and `next_sequence` of the reply.
///
/// A position at or past the end of the configured epochs — epoch `E` or later, or the
/// end of epoch `E - 1` (its last step + 1, or all its samples) — is refused as the run
/// being complete ([`ResumeReply::RUN_COMPLETE`], the reply's `epoch` is `E`): what a
/// requeued job of a finished run asks for, to be told apart from a position that does
/// not exist ([`ResumeReply::OUT_OF_RANGE`]: a step or sample beyond its epoch's end).
/// The end of an earlier epoch is accepted: the stream goes on with the next one.
fn decide(ask: &ResumeRequest, streams: &ResumeContext<'_>) -> ResumeReply {
    let config = streams.config;
    let schedule = streams.schedule;
    let wants_broadcast = ask.broadcast == 1;
    let refused = |reason| ResumeReply {
        accepted: 0,
        reason,
        ..Default::default()
    };
    let complete = ResumeReply {
        epoch: config.epochs,
        ..refused(ResumeReply::RUN_COMPLETE)
    };
    let last_epoch = config.epochs > 0 && ask.epoch == config.epochs - 1;
    if wants_broadcast != (config.mode == Mode::Broadcast) || ask.rank >= config.streams() {
        return refused(ResumeReply::NO_SUCH_STREAM);
    }
    if config.epochs > 0 && ask.epoch >= config.epochs {
        return complete;
    }
    let step = if ask.sample == UNKNOWN {
        if ask.global_batch != UNKNOWN && ask.global_batch != schedule.global_batch() as u64 {
            return refused(ResumeReply::OTHER_JOB_SIZE);
        }
        let steps = schedule.steps(ask.epoch, ask.rank as usize);
        if ask.step > steps {
            return refused(ResumeReply::OUT_OF_RANGE);
        }
        if last_epoch && ask.step == steps {
            return complete;
        }
        ask.step
    } else {
        let Ok(sample) = usize::try_from(ask.sample) else {
            return refused(ResumeReply::OUT_OF_RANGE);
        };
        if sample > schedule.samples() {
            return refused(ResumeReply::OUT_OF_RANGE);
        }
        if last_epoch && sample == schedule.samples() {
            return complete;
        }
        match schedule.step_at(ask.epoch, sample) {
            Some(step) => step,
            None => {
                let (epoch, first) = schedule.start();
                if first > 0 && (epoch, first) != (ask.epoch, sample) {
                    tracing::warn!(
                        epoch,
                        sample = first,
                        "the epoch that started part-way moves: streams that did not ask to resume continue on the new schedule"
                    );
                }
                schedule.rebase(ask.epoch, sample);
                tracing::info!(
                    epoch = ask.epoch,
                    sample,
                    samples_per_step = schedule.global_batch(),
                    "a job of another size resumes: the epoch continues at this sample, dealt to this job's ranks"
                );
                0
            }
        }
    };
    let next_sequence = streams.cursors.resume(ask.rank as usize, (ask.epoch, step));
    streams.metrics.resumes.fetch_add(1, Ordering::Relaxed);
    tracing::info!(
        rank = ask.rank,
        epoch = ask.epoch,
        step,
        sample = schedule.consumed(ask.epoch, step),
        "resume requested"
    );
    ResumeReply {
        accepted: 1,
        reason: 0,
        next_sequence,
        epoch: ask.epoch,
        step,
        ..Default::default()
    }
}

/// What the schedule server answers, from the run's schedule at the time of asking (a
/// resume by sample may move the epoch that starts part-way).
pub(super) struct ScheduleAnswers<'a> {
    pub iox: &'a iceoryx2::config::Config,
    pub run: &'a str,
    pub config: &'a ServiceConfig,
    pub schedule: &'a Schedule,
    /// The plan served, the same on every host of the job when they are set up alike.
    pub plan: PlanId,
    /// The publisher id of each stream.
    pub publishers: Vec<u128>,
}

impl ScheduleAnswers<'_> {
    /// The reply for stream `rank`.
    fn reply(&self, rank: usize) -> ScheduleReply {
        let Some(publisher) = self.publishers.get(rank) else {
            return ScheduleReply::default();
        };
        let schedule = self.schedule;
        let (start_epoch, start_sample) = schedule.start();
        // An epoch without a part-way start: any other than `start_epoch`.
        let whole = start_epoch.wrapping_add(1);
        ScheduleReply {
            known: 1,
            reserved: 0,
            steps: schedule.steps(whole, rank),
            min_steps: schedule.min_steps(whole),
            epochs: self.config.epochs,
            publisher_lo: *publisher as u64,
            publisher_hi: (*publisher >> 64) as u64,
            samples: schedule.samples() as u64,
            global_batch: schedule.global_batch() as u64,
            start_epoch,
            start_sample: start_sample as u64,
            start_steps: schedule.steps(start_epoch, rank),
            start_min_steps: schedule.min_steps(start_epoch),
            seed: self.plan.seed,
            host_rank: self.config.host_rank,
            host_count: self.config.host_count,
            keyframes: self.plan.keyframes,
            plan_digest: self.plan.digest,
        }
    }

    /// The answer to `ask`.
    fn answer(&self, ask: &ScheduleRequest) -> ScheduleReply {
        if (ask.broadcast == 1) != (self.config.mode == Mode::Broadcast) {
            return ScheduleReply::default();
        }
        self.reply(ask.rank as usize)
    }

    /// Answers schedule requests until `stop`; a service that cannot be set up is
    /// logged (subscribers then cannot tell where epochs end, and wait as before).
    pub fn serve(&self, stop: &AtomicBool) {
        if let Err(e) = self.serve_until(stop) {
            tracing::warn!(
                "schedule service of run {}: {e}; subscribers will not know where epochs end",
                self.run
            );
        }
    }

    fn serve_until(&self, stop: &AtomicBool) -> Result<(), ServiceError> {
        serve_requests(
            self.iox,
            "schedule",
            |node| names::open_schedule_service(node, self.run),
            stop,
            |ask: &ScheduleRequest| self.answer(ask),
        )
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    fn sharded(world_size: u32, epochs: u64) -> ServiceConfig {
        ServiceConfig {
            mode: Mode::Shard,
            world_size,
            epochs,
            ..ServiceConfig::default()
        }
    }

    #[test]
    fn resumes_are_checked_then_move_the_cursor() {
        let config = sharded(2, 3);
        let schedule = Schedule::new(16, 4, 2, 0);
        let cursors = Cursors::new(2, (0, 0));
        let metrics = Metrics::default();
        let streams = ResumeContext {
            config: &config,
            schedule: &schedule,
            cursors: &cursors,
            metrics: &metrics,
        };
        let ask = |rank, broadcast, epoch, step| {
            ResumeRequest::at_step(rank, broadcast == 1, epoch, step)
        };
        // 16 samples, batches of 4, 2 ranks: 2 steps per epoch per rank.
        assert_eq!(decide(&ask(0, 1, 0, 0), &streams).reason, 1);
        assert_eq!(decide(&ask(2, 0, 0, 0), &streams).reason, 1);
        // Past the last epoch: the run is complete, the reply names its epochs.
        let done = decide(&ask(1, 0, 3, 0), &streams);
        assert_eq!((done.accepted, done.reason, done.epoch), (0, 4, 3));
        assert_eq!(decide(&ask(1, 0, 0, 3), &streams).reason, 2);
        // A step saved by a job of another size: resume by sample instead.
        let other_size = ResumeRequest {
            global_batch: 12,
            ..ask(1, 0, 0, 1)
        };
        assert_eq!(decide(&other_size, &streams).reason, 3);
        assert_eq!(cursors.position(1), (0, 0, 0));
        let reply = decide(&ask(1, 0, 2, 1), &streams);
        assert_eq!((reply.accepted, reply.reason), (1, 0));
        assert_eq!((reply.epoch, reply.step), (2, 1));
        assert_eq!(cursors.position(1), (2, 1, 1));
        assert!(!cursors.is_current(1, 0));
        assert_eq!(metrics.resumes.load(Ordering::Relaxed), 1);
    }

    #[test]
    fn a_resume_by_sample_maps_to_a_step_or_starts_the_epoch_there() {
        // 16 samples an epoch, batches of 2, 2 ranks: 4 a step.
        let config = sharded(2, 3);
        let schedule = Schedule::new(16, 2, 2, 0);
        let cursors = Cursors::new(2, (0, 0));
        let metrics = Metrics::default();
        let streams = ResumeContext {
            config: &config,
            schedule: &schedule,
            cursors: &cursors,
            metrics: &metrics,
        };
        let by_sample = |rank, epoch, sample| ResumeRequest {
            sample,
            global_batch: 6,
            ..ResumeRequest::at_step(rank, false, epoch, 0)
        };
        // On a step boundary: that step.
        let reply = decide(&by_sample(0, 1, 8), &streams);
        assert_eq!((reply.accepted, reply.epoch, reply.step), (1, 1, 2));
        assert_eq!(schedule.start(), (0, 0));
        // Inside a step (a job of 3 ranks saved it): epoch 1 starts at sample 6 for
        // every stream; each rank asking for it gets step 0.
        for rank in 0..2 {
            let reply = decide(&by_sample(rank, 1, 6), &streams);
            assert_eq!((reply.accepted, reply.epoch, reply.step), (1, 1, 0));
        }
        assert_eq!(schedule.start(), (1, 6));
        assert_eq!(schedule.steps(1, 0) + schedule.steps(1, 1), 6);
        assert_eq!(decide(&by_sample(0, 1, 17), &streams).reason, 2);
        // The whole epoch consumed: past its end, the next epoch follows.
        let reply = decide(&by_sample(1, 1, 16), &streams);
        assert_eq!((reply.accepted, reply.step), (1, 3));
    }

    #[test]
    fn schedules_name_each_streams_epoch_length() {
        let config = sharded(2, 3);
        // 7 samples, batches of 2, 2 ranks: 4 and 3 samples, 2 batches each.
        let schedule = Schedule::new(7, 2, 2, 0);
        let iox = iceoryx2::config::Config::default();
        let answers = ScheduleAnswers {
            iox: &iox,
            run: "r",
            config: &config,
            schedule: &schedule,
            plan: PlanId {
                seed: 11,
                keyframes: 7,
                digest: 0xD1,
            },
            publishers: vec![5, 6],
        };
        let ask = |rank, broadcast| answers.answer(&ScheduleRequest { rank, broadcast });
        let reply = ask(1, 0);
        assert_eq!((reply.known, reply.steps, reply.min_steps), (1, 2, 2));
        assert_eq!((reply.epochs, reply.publisher()), (3, 6));
        assert_eq!((reply.samples, reply.global_batch), (7, 4));
        assert_eq!(
            (reply.seed, reply.keyframes, reply.plan_digest),
            (11, 7, 0xD1)
        );
        assert_eq!((reply.host_rank, reply.host_count), (0, 1));
        assert_eq!(ask(2, 0).known, 0);
        assert_eq!(ask(0, 1).known, 0);
        let uneven = Schedule::new(7, 1, 2, 0);
        let answers = ScheduleAnswers {
            schedule: &uneven,
            ..answers
        };
        let replies: Vec<ScheduleReply> = (0..2).map(|r| answers.reply(r)).collect();
        assert_eq!((replies[0].steps, replies[1].steps), (4, 3));
        assert_eq!(replies[0].min_steps, 3);
        // Epoch 2 resumed at sample 4: 3 samples left, 2 and 1.
        uneven.rebase(2, 4);
        let reply = answers.reply(1);
        assert_eq!((reply.start_epoch, reply.start_sample), (2, 4));
        assert_eq!(
            (reply.start_steps, reply.start_min_steps, reply.steps),
            (1, 1, 3)
        );
        assert_eq!(reply.consumed(2, 1), 6);
    }

    /// A finished run's requeued job asks for the position after its last batch: by
    /// step, by sample, or an epoch past the end. Each is "run complete" (reason 4, the
    /// epochs in the reply), not a bad position; the end of an earlier epoch is accepted
    /// (the next epoch follows), a step beyond an epoch's end is still reason 2.
    #[test]
    fn a_resume_at_the_end_of_the_last_epoch_is_run_complete() {
        // 16 samples an epoch, batches of 2, 2 ranks: 4 steps per rank, 4 samples a step.
        let config = sharded(2, 3);
        let schedule = Schedule::new(16, 2, 2, 0);
        let cursors = Cursors::new(2, (0, 0));
        let metrics = Metrics::default();
        let streams = ResumeContext {
            config: &config,
            schedule: &schedule,
            cursors: &cursors,
            metrics: &metrics,
        };
        let by_step = |epoch, step| ResumeRequest::at_step(1, false, epoch, step);
        let by_sample = |epoch, sample| ResumeRequest {
            sample,
            global_batch: 4,
            ..ResumeRequest::at_step(0, false, epoch, UNKNOWN)
        };
        for ask in [
            by_step(2, 4),
            by_sample(2, 16),
            by_step(3, 0),
            by_sample(7, 0),
        ] {
            let reply = decide(&ask, &streams);
            assert_eq!(
                (reply.accepted, reply.reason, reply.epoch),
                (0, ResumeReply::RUN_COMPLETE, 3),
                "{ask:?}"
            );
        }
        // Out of range, whatever the epoch.
        assert_eq!(decide(&by_step(2, 5), &streams).reason, 2);
        assert_eq!(decide(&by_step(1, 5), &streams).reason, 2);
        assert_eq!(decide(&by_sample(2, 17), &streams).reason, 2);
        assert_eq!(cursors.position(0), (0, 0, 0), "nothing moved");
        assert_eq!(metrics.resumes.load(Ordering::Relaxed), 0);
        // The end of an earlier epoch, and the last batch of the last: accepted.
        let reply = decide(&by_step(1, 4), &streams);
        assert_eq!((reply.accepted, reply.epoch, reply.step), (1, 1, 4));
        let reply = decide(&by_step(2, 3), &streams);
        assert_eq!((reply.accepted, reply.epoch, reply.step), (1, 2, 3));
        let reply = decide(&by_sample(1, 16), &streams);
        assert_eq!((reply.accepted, reply.epoch, reply.step), (1, 1, 4));
        // An endless run is never complete.
        let endless = sharded(2, 0);
        let streams = ResumeContext {
            config: &endless,
            ..streams
        };
        assert_eq!(decide(&by_step(9, 4), &streams).accepted, 1);
    }
}
