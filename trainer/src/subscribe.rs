//! Receiving batches: a subscriber on the run's broadcast service or on one rank's
//! shard, woken by the ready event; and the resume request of the control service.
//!
//! A [`Received`] batch holds its iceoryx2 sample, and a [`BatchView`] of it borrows it:
//! the compiler keeps every view from outliving the sample, so nothing here can read
//! memory the pipeline has reused (the Python package gets the same guarantee at run
//! time, by handing a sample back only once its last view is gone).

use iceoryx2::port::listener::Listener;
use iceoryx2::port::subscriber::Subscriber;
use iceoryx2::prelude::*;
use iceoryx2::sample::Sample;
use std::time::{Duration, Instant};
use superflow_schemas::batch::{BatchError, BatchHeader, BatchView};
pub use superflow_schemas::service::ResumeAt;
use superflow_schemas::service::{
    self as names, IpcError, ResumeReply, ScheduleReply, ScheduleRequest, ServiceSetupError,
};

/// Which stream to read.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum Target {
    /// `superflow/<run>/batches`: every batch.
    Broadcast,
    /// `superflow/<run>/rank/<r>`: this rank's share.
    Rank(u32),
}

/// A subscription failure.
#[derive(Debug, thiserror::Error)]
pub enum SubscribeError {
    /// iceoryx2 refused something (the node, a port, a receive, a request).
    #[error(transparent)]
    Ipc(#[from] IpcError),
    /// A service could not be opened or created (name, or iceoryx2 refused).
    #[error(transparent)]
    Setup(#[from] ServiceSetupError),
    /// The run name is not valid.
    #[error(transparent)]
    Name(#[from] BatchError),
    /// No answer to a resume request in time.
    #[error("the pipeline of run `{run}` did not answer the resume request within {waited:?}")]
    NoAnswer {
        /// The run.
        run: String,
        /// How long we waited.
        waited: Duration,
    },
}

impl SubscribeError {
    /// Wraps an iceoryx2 error with what was being done.
    fn ipc<E: std::error::Error + Send + Sync + 'static>(
        what: impl Into<String>,
    ) -> impl FnOnce(E) -> Self {
        let wrap = IpcError::doing(what);
        move |source| Self::Ipc(wrap(source))
    }
}

/// One received batch: header and payload stay in shared memory while this lives.
pub struct Received {
    sample: Sample<ipc::Service, [u8], BatchHeader>,
}

impl std::fmt::Debug for Received {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        write!(f, "Received({} bytes)", self.sample.payload().len())
    }
}

impl Received {
    /// The batch, validated (`schemas/BATCH_FORMAT.md` rules 1–3).
    pub fn view(&self) -> Result<BatchView<'_>, BatchError> {
        BatchView::new(self.sample.user_header(), self.sample.payload())
    }

    /// Id of the publisher that sent it.
    pub fn origin(&self) -> u128 {
        self.sample.origin().value()
    }

    /// The raw header.
    pub fn header(&self) -> &BatchHeader {
        self.sample.user_header()
    }

    /// The raw payload.
    pub fn payload(&self) -> &[u8] {
        self.sample.payload()
    }
}

/// A subscriber to one stream of a run.
pub struct Subscription {
    run: String,
    target: Target,
    node: Node<ipc::Service>,
    subscriber: Subscriber<ipc::Service, [u8], BatchHeader>,
    listener: Listener<ipc::Service>,
    stash: std::cell::RefCell<Option<Received>>,
    /// After a resume: batches of that publisher numbered below this belong to the old
    /// position (one may still be on its way when the answer comes) and are dropped.
    floor: std::cell::Cell<Option<(u128, u64)>>,
    service: names::BatchService,
    _ready: names::ReadyService,
}

impl std::fmt::Debug for Subscription {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        write!(f, "Subscription({} {:?})", self.run, self.target)
    }
}

impl Subscription {
    /// Subscribes to `target` of `run` with a receive queue of `buffer` batches (at most
    /// [`names::qos::MAX_BUFFER`]); the service is created if the pipeline is not up
    /// yet, and the pipeline publishes once its subscribers are there.
    pub fn open(
        run: &str,
        target: Target,
        iox: &iceoryx2::config::Config,
        buffer: usize,
    ) -> Result<Self, SubscribeError> {
        let name = match target {
            Target::Broadcast => names::batches_service(run)?,
            Target::Rank(r) => names::rank_service(run, r)?,
        };
        let node = NodeBuilder::new()
            .config(iox)
            .create::<ipc::Service>()
            .map_err(SubscribeError::ipc("creating the iceoryx2 node"))?;
        let service = names::open_batch_service(&node, &name)?;
        let ready = names::open_ready_service(&node, &name)?;
        let listener = ready
            .listener_builder()
            .create()
            .map_err(SubscribeError::ipc(format!("{name}: listener")))?;
        let subscriber = service
            .subscriber_builder()
            .buffer_size(buffer.clamp(1, names::qos::MAX_BUFFER))
            .create()
            .map_err(SubscribeError::ipc(format!("{name}: subscriber")))?;
        Ok(Self {
            run: run.to_string(),
            target,
            node,
            subscriber,
            listener,
            stash: std::cell::RefCell::new(None),
            floor: std::cell::Cell::new(None),
            service,
            _ready: ready,
        })
    }

    /// Whether a pipeline is publishing on this stream. Dead publishers are cleaned up
    /// first (iceoryx2 dead-node detection), so a killed pipeline shows as gone.
    pub fn pipeline_attached(&self) -> bool {
        let _ = self.node.try_cleanup_dead_nodes();
        self.service.dynamic_config().number_of_publishers() > 0
    }

    /// The next batch, waiting at most `timeout` (blocked on the ready event, woken by
    /// each publish); `None` when nothing arrived in time.
    pub fn receive(&self, timeout: Duration) -> Result<Option<Received>, SubscribeError> {
        if let Some(stashed) = self.stash.borrow_mut().take() {
            return Ok(Some(stashed));
        }
        let deadline = Instant::now() + timeout;
        loop {
            match self.subscriber.receive() {
                Ok(Some(sample)) => {
                    let received = Received { sample };
                    if !self.before_floor(&received) {
                        return Ok(Some(received));
                    }
                    continue;
                }
                Ok(None) => {}
                Err(e) => return Err(SubscribeError::ipc("receive")(e)),
            }
            let now = Instant::now();
            if now >= deadline {
                return Ok(None);
            }
            // Bounded slices: a wake-up sent before this listener existed is not lost.
            let slice = (deadline - now).min(Duration::from_millis(100));
            self.listener
                .timed_wait(|_| {}, slice)
                .map_err(SubscribeError::ipc("waiting for the ready event"))?;
        }
    }

    /// Asks the pipeline to continue this stream at `at`. When accepted, the next
    /// [`Subscription::receive`] returns the batch at the reply's `(epoch, step)`: batches
    /// of the old position still queued are dropped (they are told apart by the reply's
    /// sequence number). While waiting for the answer the queue keeps being drained, so a
    /// pipeline blocked on this subscriber's full queue can get to the request.
    pub fn resume(&self, at: ResumeAt, timeout: Duration) -> Result<ResumeReply, SubscribeError> {
        let control = names::open_control_service(&self.node, &self.run)?;
        let client = control
            .client_builder()
            .create()
            .map_err(SubscribeError::ipc("control client"))?;
        let rank = match self.target {
            Target::Broadcast => 0,
            Target::Rank(r) => r,
        };
        let request = at.request(rank, self.target == Target::Broadcast);
        // The step the answer will name, to keep its first batch should it arrive before
        // the answer: a resume by sample is a step boundary of the pipeline's schedule,
        // or step 0 of an epoch made to start there.
        let step = match at {
            ResumeAt::Step { step, .. } => step,
            ResumeAt::Sample { epoch, sample, .. } => self
                .schedule(Duration::from_secs(2))?
                .filter(|s| s.known == 1)
                .map_or(0, |s| s.step_at(epoch, sample)),
        };
        let epoch = at.epoch();
        let wanted = |r: &Received| {
            let h = r.header();
            (h.epoch, h.step) == (epoch, step)
        };
        self.stash.borrow_mut().take();
        let started = Instant::now();
        // The server may not have connected to this fresh client yet (or the pipeline
        // is restarting): resend until one answers.
        while started.elapsed() < timeout {
            let pending = client
                .send_copy(request)
                .map_err(SubscribeError::ipc("resume request"))?;
            let attempt = Instant::now();
            while attempt.elapsed() < Duration::from_millis(500) && started.elapsed() < timeout {
                let reply = match pending.receive() {
                    Ok(Some(reply)) => Some(*reply.payload()),
                    Ok(None) => None,
                    Err(e) => return Err(SubscribeError::ipc("resume reply")(e)),
                };
                let mut stash = self.stash.borrow_mut();
                if let Some(reply) = reply {
                    if reply.accepted == 1 {
                        self.floor
                            .set(Some((reply.publisher(), reply.next_sequence)));
                        // Everything published before the reply is older than it.
                        let new = |r: &Received| {
                            r.origin() == reply.publisher()
                                && r.header().sequence >= reply.next_sequence
                        };
                        if stash.as_ref().is_some_and(|s| !new(s)) {
                            stash.take();
                        }
                        while stash.is_none() {
                            match self.subscriber.receive() {
                                Ok(Some(sample)) => {
                                    let r = Received { sample };
                                    if new(&r) {
                                        *stash = Some(r);
                                    }
                                }
                                Ok(None) => break,
                                Err(e) => {
                                    return Err(SubscribeError::ipc("receive")(e));
                                }
                            }
                        }
                    }
                    return Ok(reply);
                }
                // No answer yet: keep the queue moving; keep only a batch at the asked
                // position (it may already be the answer's first batch).
                match self.subscriber.receive() {
                    Ok(Some(sample)) => {
                        let r = Received { sample };
                        if wanted(&r) {
                            *stash = Some(r);
                        }
                    }
                    Ok(None) => std::thread::sleep(Duration::from_millis(2)),
                    Err(e) => return Err(SubscribeError::ipc("receive")(e)),
                }
            }
        }
        Err(SubscribeError::NoAnswer {
            run: self.run.clone(),
            waited: timeout,
        })
    }

    /// Whether `received` is a batch of the position a resume left (its publisher's, numbered
    /// below the resume's first batch).
    fn before_floor(&self, received: &Received) -> bool {
        self.floor.get().is_some_and(|(publisher, first)| {
            received.origin() == publisher && received.header().sequence < first
        })
    }

    /// Asks the pipeline how this stream is scheduled (batches per epoch, epochs served:
    /// where the epochs and the stream end); `None` when no pipeline answers within
    /// `timeout`. The batch queue is left alone: the pipeline answers from a thread of
    /// its own, even while its publisher waits on this subscriber's full queue.
    pub fn schedule(&self, timeout: Duration) -> Result<Option<ScheduleReply>, SubscribeError> {
        let service = names::open_schedule_service(&self.node, &self.run)?;
        let client = service
            .client_builder()
            .create()
            .map_err(SubscribeError::ipc("schedule client"))?;
        let request = ScheduleRequest {
            rank: match self.target {
                Target::Broadcast => 0,
                Target::Rank(r) => r,
            },
            broadcast: u32::from(self.target == Target::Broadcast),
        };
        let started = Instant::now();
        // A fresh client may not be connected to the server yet: resend until one answers.
        while started.elapsed() < timeout {
            let pending = client
                .send_copy(request)
                .map_err(SubscribeError::ipc("schedule request"))?;
            let attempt = Instant::now();
            while attempt.elapsed() < Duration::from_millis(500) && started.elapsed() < timeout {
                match pending.receive() {
                    Ok(Some(reply)) => return Ok(Some(*reply.payload())),
                    Ok(None) => std::thread::sleep(Duration::from_millis(5)),
                    Err(e) => return Err(SubscribeError::ipc("schedule reply")(e)),
                }
            }
        }
        Ok(None)
    }
}
