//! [`serve`]: sets the service up (schedule, node, ports, control server), runs the
//! producer thread, and publishes what it builds until the epochs are done and the
//! subscribers gone, or until `stop`.

use super::config::{Mode, ServiceConfig};
use super::control::{ControlAnswers, ResumeContext, ScheduleAnswers};
use super::cursors::{Cursors, MAX_LEAD_STEPS};
use super::error::ServiceError;
use super::metrics::Metrics;
use super::metrics::log_counters;
use super::plan_id::PlanId;
use super::ports::{Stamp, StreamPorts};
use super::producer::{Prepared, Producer};
use super::schedule::Schedule;
use crate::batch::BatchShape;
use crate::sample::SampleBuilder;
use iceoryx2::prelude::*;
use std::collections::VecDeque;
use std::sync::atomic::{AtomicBool, Ordering};
use std::sync::mpsc::{Receiver, RecvTimeoutError, sync_channel};
use std::sync::{Arc, Mutex};
use std::time::{Duration, Instant};
use superflow_schemas::service::ResumeAt;
use superflow_schemas::service::{self as names, ServiceSetupError};

/// Runs the service until the configured epochs are published and every subscriber has
/// left (or `linger_secs` passed), or until `stop` is set.
pub fn serve(
    builder: &SampleBuilder<'_>,
    run: &str,
    config: &ServiceConfig,
    iox: &iceoryx2::config::Config,
    start: ResumeAt,
    stop: &Arc<AtomicBool>,
    metrics: &Arc<Metrics>,
) -> Result<(), ServiceError> {
    let schedule = schedule_of(builder, config)?;
    let start = match start {
        ResumeAt::Step { epoch, step } => (epoch, step),
        ResumeAt::Sample { epoch, sample, .. } => {
            let samples = schedule.samples();
            let sample = usize::try_from(sample)
                .ok()
                .filter(|&s| s <= samples)
                .ok_or(ServiceError::StartPastEpoch { sample, samples })?;
            schedule.rebase(epoch, sample);
            (epoch, 0)
        }
    };
    let node = open_node(iox)?;
    let mut streams = Vec::new();
    for name in service_names(run, config)? {
        streams.push(StreamPorts::open(&node, &name, iox, config, stop, metrics)?);
    }
    let publisher_ids: Vec<u128> = streams.iter().map(StreamPorts::publisher_id).collect();
    let plan = PlanId::of(builder);
    let schedule_answers = ScheduleAnswers {
        iox,
        run,
        config,
        schedule: &schedule,
        plan,
        publishers: publisher_ids.clone(),
    };
    tracing::info!(
        services = %streams.iter().map(|s| s.name.as_str()).collect::<Vec<_>>().join(", "),
        samples_per_epoch = builder.epoch_len(),
        host = config.host_rank,
        hosts = config.host_count,
        steps_per_epoch = schedule.steps(start.0.wrapping_add(1), 0),
        batch_size = config.batch_size,
        start_epoch = start.0,
        start_sample = schedule.consumed(start.0, start.1),
        seed = plan.seed,
        keyframes = plan.keyframes,
        plan_digest = format_args!("{:016x}", plan.digest),
        "publishing"
    );
    let cursors = Cursors::new(streams.len(), start);
    let idle = AtomicBool::new(false);
    let producer = Producer {
        builder,
        schedule: &schedule,
        config,
        cursors: &cursors,
        stop,
        idle: &idle,
        metrics,
        said: Mutex::default(),
    };
    let publisher = Publisher {
        run,
        config,
        node,
        streams,
        control: ControlAnswers {
            iox,
            run,
            publishers: publisher_ids,
            streams: ResumeContext {
                config,
                schedule: &schedule,
                cursors: &cursors,
                metrics,
            },
        },
        schedule: schedule_answers,
        resume: ResumeContext {
            config,
            schedule: &schedule,
            cursors: &cursors,
            metrics,
        },
        stop,
        metrics,
        shape: BatchShape::of(builder.config()),
        bar: progress_bar(),
    };
    publisher.run(&producer)
}

/// Validates `config` against the drives and deals their keyframes to this host.
fn schedule_of(
    builder: &SampleBuilder<'_>,
    config: &ServiceConfig,
) -> Result<Schedule, ServiceError> {
    config.validate()?;
    let keyframes = builder.epoch_len();
    if keyframes == 0 {
        return Err(ServiceError::NoKeyframes);
    }
    let streams = config.streams();
    if streams as usize * config.host_count as usize > keyframes {
        return Err(ServiceError::TooManyStreams {
            streams,
            hosts: config.host_count,
            keyframes,
        });
    }
    Ok(Schedule::for_host(
        keyframes,
        config.batch_size as usize,
        streams as usize,
        (config.host_rank, config.host_count),
        builder.config().seed,
    ))
}

/// This process's iceoryx2 node, after cleaning up what earlier crashed processes left
/// behind.
fn open_node(iox: &iceoryx2::config::Config) -> Result<Node<ipc::Service>, ServiceError> {
    let node = NodeBuilder::new()
        .config(iox)
        .signal_handling_mode(SignalHandlingMode::Disabled)
        .create::<ipc::Service>()
        .map_err(ServiceError::ipc("creating the iceoryx2 node"))?;
    let cleaned = node.try_cleanup_dead_nodes();
    if cleaned.cleanups > 0 {
        tracing::warn!(
            nodes = cleaned.cleanups,
            "cleaned up dead iceoryx2 nodes of earlier processes"
        );
    }
    Ok(node)
}

/// The batch services of `run`: the broadcast one, or one per rank.
fn service_names(run: &str, config: &ServiceConfig) -> Result<Vec<String>, ServiceError> {
    let names = match config.mode {
        Mode::Broadcast => vec![names::batches_service(run).map_err(ServiceSetupError::Run)?],
        Mode::Shard => (0..config.streams())
            .map(|r| names::rank_service(run, r))
            .collect::<Result<_, _>>()
            .map_err(ServiceSetupError::Run)?,
    };
    Ok(names)
}

fn progress_bar() -> indicatif::ProgressBar {
    let bar = indicatif::ProgressBar::new_spinner();
    bar.set_style(
        indicatif::ProgressStyle::with_template("{spinner} {msg}")
            .unwrap_or_else(|_| indicatif::ProgressStyle::default_spinner()),
    );
    bar
}

/// The publishing side of a running service (the calling thread).
struct Publisher<'a> {
    run: &'a str,
    config: &'a ServiceConfig,
    node: Node<ipc::Service>,
    streams: Vec<StreamPorts>,
    control: ControlAnswers<'a>,
    schedule: ScheduleAnswers<'a>,
    resume: ResumeContext<'a>,
    stop: &'a AtomicBool,
    metrics: &'a Metrics,
    shape: BatchShape,
    bar: indicatif::ProgressBar,
}

/// What became of one prepared batch.
enum Delivery {
    Sent,
    /// Built for a position a resume request replaced: dropped.
    Stale,
    /// `stop` was set while it waited for subscribers.
    Stopped,
}

impl Publisher<'_> {
    /// Runs `producer` on its own thread and publishes what it builds; stops it on the
    /// way out.
    fn run(&self, producer: &Producer<'_>) -> Result<(), ServiceError> {
        let (tx, rx) = sync_channel::<Prepared>(self.config.prefetch as usize);
        let producer_done = AtomicBool::new(false);
        let result = std::thread::scope(|scope| {
            let (schedule, control, stop) = (&self.schedule, &self.control, self.stop);
            scope.spawn(move || schedule.serve(stop));
            scope.spawn(move || control.serve(stop));
            scope.spawn(|| {
                producer.run(&tx);
                producer_done.store(true, Ordering::SeqCst);
                drop(tx);
            });
            let result = self.publish_all(&rx, producer.idle);
            self.stop.store(true, Ordering::SeqCst);
            // Unblock the producer if it waits on a full channel.
            while rx.try_recv().is_ok() {}
            drop(rx);
            result
        });
        self.bar.finish_and_clear();
        log_counters(self.metrics);
        tracing::debug!(
            producer_done = producer_done.load(Ordering::SeqCst),
            "service stopped"
        );
        result
    }

    /// The publisher loop: takes prepared batches and publishes them, each stream's in
    /// order, the stream furthest behind first, none more than `MAX_LEAD_STEPS` ahead of
    /// it; ends on `stop`, or once every epoch is published and the subscribers have
    /// left.
    fn publish_all(&self, rx: &Receiver<Prepared>, idle: &AtomicBool) -> Result<(), ServiceError> {
        let mut pending: Vec<VecDeque<Prepared>> =
            self.streams.iter().map(|_| VecDeque::new()).collect();
        let mut sent = 0u64;
        let mut last_log = Instant::now();
        let mut finished_at: Option<Instant> = None;
        let mut producer_gone = false;
        loop {
            if self.stop.load(Ordering::SeqCst) {
                return Ok(());
            }
            if let Some(stream) = self.next_deliverable(&mut pending) {
                let Some(prepared) = pending[stream].pop_front() else {
                    continue;
                };
                match self.deliver(&prepared)? {
                    Delivery::Sent => {
                        sent += 1;
                        self.show_progress(&prepared);
                    }
                    Delivery::Stale => {}
                    Delivery::Stopped => return Ok(()),
                }
                if last_log.elapsed() > Duration::from_secs(10) {
                    last_log = Instant::now();
                    log_counters(self.metrics);
                }
                continue;
            }
            if producer_gone {
                return Ok(());
            }
            let waited = Instant::now();
            // Read before waiting: the producer turns idle only after its last send, so
            // idle-then-timeout means every prepared batch was taken.
            let idle_before = idle.load(Ordering::SeqCst);
            match rx.recv_timeout(Duration::from_millis(20)) {
                Ok(prepared) => {
                    self.count_wait(waited);
                    pending[prepared.stream as usize].push_back(prepared);
                    while let Ok(more) = rx.try_recv() {
                        pending[more.stream as usize].push_back(more);
                    }
                }
                Err(RecvTimeoutError::Timeout) => {
                    let epochs = self.config.epochs;
                    let none_pending = pending.iter().all(VecDeque::is_empty);
                    if epochs > 0
                        && idle_before
                        && none_pending
                        && self.resume.cursors.all_past(epochs)
                    {
                        let since = *finished_at.get_or_insert_with(Instant::now);
                        if self.lingered(since, sent) {
                            return Ok(());
                        }
                    } else {
                        finished_at = None;
                        self.count_wait(waited);
                    }
                }
                Err(RecvTimeoutError::Disconnected) => producer_gone = true,
            }
        }
    }

    /// The stream whose next prepared batch goes now: the earliest in the run of the
    /// streams' next batches, unless it is `MAX_LEAD_STEPS` or more ahead of the stream
    /// furthest behind (its next batch prepared or still to build). Drops stale batches.
    fn next_deliverable(&self, pending: &mut [VecDeque<Prepared>]) -> Option<usize> {
        let cursors = self.resume.cursors;
        for queue in pending.iter_mut() {
            queue.retain(|p| cursors.is_current(p.stream as usize, p.generation));
        }
        let schedule = self.resume.schedule;
        let positions = cursors.positions();
        let frontier = |s: usize| {
            pending[s]
                .front()
                .map_or(positions[s], |p| (p.epoch, p.step))
        };
        let end = self.config.epochs;
        let slowest = (0..pending.len())
            .map(frontier)
            .filter(|(e, _)| end == 0 || *e < end)
            .map(|(e, s)| schedule.run_sample(e, s))
            .min();
        let (stream, at) = (0..pending.len())
            .filter_map(|s| {
                let p = pending[s].front()?;
                Some((s, schedule.run_sample(p.epoch, p.step)))
            })
            .min_by_key(|(_, at)| *at)?;
        let limit = slowest.map_or(u128::MAX, |slowest| {
            slowest + MAX_LEAD_STEPS * schedule.global_batch() as u128
        });
        (at < limit).then_some(stream)
    }

    /// All epochs are published (since `since`): serve resume requests while
    /// subscribers are attached; whether the service may end now.
    fn lingered(&self, since: Instant, sent: u64) -> bool {
        let attached: usize = self.streams.iter().map(StreamPorts::subscribers).sum();
        if attached == 0 || since.elapsed() > Duration::from_secs(self.config.linger_secs) {
            tracing::info!(
                batches = sent,
                "all epochs published; every subscriber has left"
            );
            return true;
        }
        let _ = self.node.try_cleanup_dead_nodes();
        false
    }

    /// Publishes one prepared batch once its stream has subscribers, unless a resume
    /// request made it stale meanwhile.
    fn deliver(&self, prepared: &Prepared) -> Result<Delivery, ServiceError> {
        let current = || {
            self.resume
                .cursors
                .is_current(prepared.stream as usize, prepared.generation)
        };
        if !current() {
            return Ok(Delivery::Stale);
        }
        let stream = &self.streams[prepared.stream as usize];
        let span = tracing::info_span!("publish", service = %stream.name, epoch = prepared.epoch, step = prepared.step);
        let _entered = span.enter();
        self.wait_for_subscribers(stream);
        if self.stop.load(Ordering::SeqCst) {
            return Ok(Delivery::Stopped);
        }
        // A resume may have come meanwhile: the sequence number is taken only while the
        // batch is still wanted.
        let Some(sequence) = self
            .resume
            .cursors
            .claim(prepared.stream as usize, prepared.generation)
        else {
            return Ok(Delivery::Stale);
        };
        stream.published.set(true);
        let stamp = Stamp {
            run: self.run,
            seed: self.resume.schedule.seed(),
            sequence,
        };
        stream.publish(prepared, self.shape, &stamp, self.metrics)?;
        Ok(Delivery::Sent)
    }

    /// Never publish into the void: waits until `stream` has its subscribers —
    /// `min_subscribers` before its first batch, then one.
    fn wait_for_subscribers(&self, stream: &StreamPorts) {
        let required = if stream.published.get() {
            1
        } else {
            self.config.min_subscribers.max(1) as usize
        };
        let mut announced = false;
        while stream.subscribers() < required && !self.stop.load(Ordering::SeqCst) {
            if !announced {
                tracing::info!(service = %stream.name, required, "waiting for subscribers");
                announced = true;
            }
            let _ = self.node.try_cleanup_dead_nodes();
            std::thread::sleep(Duration::from_millis(20));
        }
    }

    fn count_wait(&self, since: Instant) {
        self.metrics
            .wait_for_build_nanos
            .fetch_add(since.elapsed().as_nanos() as u64, Ordering::Relaxed);
    }

    fn show_progress(&self, prepared: &Prepared) {
        self.bar.set_message(format!(
            "{} batches, {} samples, epoch {} step {} on {}",
            self.metrics.batches.load(Ordering::Relaxed),
            self.metrics.samples.load(Ordering::Relaxed),
            prepared.epoch,
            prepared.step,
            self.streams[prepared.stream as usize].name
        ));
        self.bar.tick();
    }
}
