//! The control server (request-response on `superflow/<run>/control`): a subscriber
//! asks to resume its stream at `(epoch, step)`; an accepted request moves the stream's
//! cursor and bumps its generation, so batches built for the old position are dropped.
//! The reply names the sequence number and publisher of the first batch at the new
//! position.
//!
//! The schedule server (request-response on `superflow/<run>/schedule`, its own thread
//! and node: it answers while the publisher waits on a full queue) tells a subscriber
//! how many batches an epoch of its stream has and how many epochs the run serves, so it
//! knows which batch ends an epoch and which ends the stream.

use super::{Cursors, Metrics, Mode, Schedule, ServiceConfig, ServiceError};
use iceoryx2::port::server::Server;
use iceoryx2::prelude::*;
use std::sync::atomic::{AtomicBool, Ordering};
use std::time::Duration;
use superflow_schemas::service::{
    self as names, ResumeReply, ResumeRequest, ScheduleReply, ScheduleRequest,
};

/// The server of a run's control service.
pub(super) struct ControlServer {
    server: Server<ipc::Service, ResumeRequest, (), ResumeReply, ()>,
    /// Publisher id of each stream, sent back in the reply.
    publishers: Vec<u128>,
    _service: names::ControlService,
}

/// What a resume request is checked against and acts on.
pub(super) struct ResumeContext<'a> {
    pub config: &'a ServiceConfig,
    pub schedule: &'a Schedule,
    pub cursors: &'a Cursors,
    pub metrics: &'a Metrics,
}

impl ControlServer {
    /// Opens the control service of `run` and its server; `publishers` are the ids of
    /// the streams' publishers.
    pub fn open(
        node: &Node<ipc::Service>,
        run: &str,
        publishers: Vec<u128>,
    ) -> Result<Self, ServiceError> {
        let service = names::open_control_service(node, run)?;
        let server = service
            .server_builder()
            .create()
            .map_err(ServiceError::ipc("control server"))?;
        Ok(Self {
            server,
            publishers,
            _service: service,
        })
    }

    /// Answers every pending resume request; `sequence` is the sequence number of the
    /// next batch published.
    pub fn answer_pending(&self, streams: &ResumeContext<'_>, sequence: u64) {
        loop {
            let request = match self.server.receive() {
                Ok(Some(r)) => r,
                Ok(None) => return,
                Err(e) => {
                    tracing::warn!("control service: {e:?}");
                    return;
                }
            };
            let ask = *request.payload();
            let publisher = self.publishers.get(ask.rank as usize).copied().unwrap_or(0);
            let reply = ResumeReply {
                next_sequence: sequence,
                publisher_lo: publisher as u64,
                publisher_hi: (publisher >> 64) as u64,
                ..decide(&ask, streams)
            };
            match request.loan_uninit() {
                Ok(response) => {
                    if let Err(e) = response.write_payload(reply).send() {
                        tracing::warn!("control reply: {e:?}");
                    }
                }
                Err(e) => tracing::warn!("control reply: {e:?}"),
            }
        }
    }
}

/// Accepts (and carries out) or refuses one request: `accepted` and `reason` of the
/// reply.
fn decide(ask: &ResumeRequest, streams: &ResumeContext<'_>) -> ResumeReply {
    let config = streams.config;
    let wants_broadcast = ask.broadcast == 1;
    let refused = |reason| ResumeReply {
        accepted: 0,
        reason,
        ..Default::default()
    };
    if wants_broadcast != (config.mode == Mode::Broadcast) || ask.rank >= config.streams() {
        return refused(1);
    }
    if (config.epochs > 0 && ask.epoch >= config.epochs)
        || ask.step > streams.schedule.steps(ask.rank as usize)
    {
        return refused(2);
    }
    streams
        .cursors
        .resume(ask.rank as usize, (ask.epoch, ask.step));
    streams.metrics.resumes.fetch_add(1, Ordering::Relaxed);
    tracing::info!(
        rank = ask.rank,
        epoch = ask.epoch,
        step = ask.step,
        "resume requested"
    );
    ResumeReply {
        accepted: 1,
        reason: 0,
        ..Default::default()
    }
}

/// What the schedule server answers: the reply of each stream.
pub(super) struct ScheduleAnswers<'a> {
    pub iox: &'a iceoryx2::config::Config,
    pub run: &'a str,
    pub broadcast: bool,
    pub replies: Vec<ScheduleReply>,
}

impl ScheduleAnswers<'_> {
    /// The replies of `schedule`'s streams (`publishers`: their publisher ids).
    pub fn replies(
        config: &ServiceConfig,
        schedule: &Schedule,
        publishers: &[u128],
    ) -> Vec<ScheduleReply> {
        publishers
            .iter()
            .enumerate()
            .map(|(rank, publisher)| ScheduleReply {
                known: 1,
                reserved: 0,
                steps: schedule.steps(rank),
                min_steps: schedule.min_steps(),
                epochs: config.epochs,
                publisher_lo: *publisher as u64,
                publisher_hi: (*publisher >> 64) as u64,
            })
            .collect()
    }

    /// The answer to `ask`.
    fn answer(&self, ask: &ScheduleRequest) -> ScheduleReply {
        match self.replies.get(ask.rank as usize) {
            Some(reply) if (ask.broadcast == 1) == self.broadcast => *reply,
            _ => ScheduleReply::default(),
        }
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
        let node = NodeBuilder::new()
            .config(self.iox)
            .signal_handling_mode(SignalHandlingMode::Disabled)
            .create::<ipc::Service>()
            .map_err(ServiceError::ipc("creating the schedule server's node"))?;
        let service = names::open_schedule_service(&node, self.run)?;
        let server = service
            .server_builder()
            .create()
            .map_err(ServiceError::ipc("schedule server"))?;
        while !stop.load(Ordering::SeqCst) {
            loop {
                let request = match server.receive() {
                    Ok(Some(r)) => r,
                    Ok(None) => break,
                    Err(e) => {
                        tracing::warn!("schedule service: {e:?}");
                        break;
                    }
                };
                let reply = self.answer(request.payload());
                match request.loan_uninit() {
                    Ok(response) => {
                        if let Err(e) = response.write_payload(reply).send() {
                            tracing::warn!("schedule reply: {e:?}");
                        }
                    }
                    Err(e) => tracing::warn!("schedule reply: {e:?}"),
                }
            }
            std::thread::sleep(Duration::from_millis(10));
        }
        Ok(())
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn resumes_are_checked_then_move_the_cursor() {
        let config = ServiceConfig {
            mode: Mode::Shard,
            world_size: 2,
            epochs: 3,
            ..ServiceConfig::default()
        };
        let schedule = Schedule::new(16, 4, 2, 0);
        let cursors = Cursors::new(2, (0, 0));
        let metrics = Metrics::default();
        let streams = ResumeContext {
            config: &config,
            schedule: &schedule,
            cursors: &cursors,
            metrics: &metrics,
        };
        let ask = |rank, broadcast, epoch, step| ResumeRequest {
            rank,
            broadcast,
            epoch,
            step,
        };
        assert_eq!(decide(&ask(0, 1, 0, 0), &streams).reason, 1);
        assert_eq!(decide(&ask(2, 0, 0, 0), &streams).reason, 1);
        assert_eq!(decide(&ask(1, 0, 3, 0), &streams).reason, 2);
        assert_eq!(decide(&ask(1, 0, 0, 3), &streams).reason, 2);
        assert_eq!(cursors.position(1), (0, 0, 0));
        let reply = decide(&ask(1, 0, 2, 1), &streams);
        assert_eq!((reply.accepted, reply.reason), (1, 0));
        assert_eq!(cursors.position(1), (2, 1, 1));
        assert!(!cursors.is_current(1, 0));
        assert_eq!(metrics.resumes.load(Ordering::Relaxed), 1);
    }

    #[test]
    fn schedules_name_each_streams_epoch_length() {
        let config = ServiceConfig {
            mode: Mode::Shard,
            world_size: 2,
            epochs: 3,
            ..ServiceConfig::default()
        };
        // 7 keyframes, batches of 2, 2 ranks: 4 and 3 keyframes, 2 batches each.
        let schedule = Schedule::new(7, 2, 2, 0);
        let iox = iceoryx2::config::Config::default();
        let answers = ScheduleAnswers {
            iox: &iox,
            run: "r",
            broadcast: false,
            replies: ScheduleAnswers::replies(&config, &schedule, &[5, 6]),
        };
        let ask = |rank, broadcast| answers.answer(&ScheduleRequest { rank, broadcast });
        let reply = ask(1, 0);
        assert_eq!((reply.known, reply.steps, reply.min_steps), (1, 2, 2));
        assert_eq!((reply.epochs, reply.publisher()), (3, 6));
        assert_eq!(ask(2, 0).known, 0);
        assert_eq!(ask(0, 1).known, 0);
        let uneven = Schedule::new(7, 1, 2, 0);
        let replies = ScheduleAnswers::replies(&config, &uneven, &[5, 6]);
        assert_eq!((replies[0].steps, replies[1].steps), (4, 3));
        assert_eq!(replies[0].min_steps, 3);
    }
}
