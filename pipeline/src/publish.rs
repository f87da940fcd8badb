//! The service: an endless (or bounded) stream of batches over iceoryx2.
//!
//! * [`Schedule`] says which keyframes form batch `step` of `epoch` for stream `rank`:
//!   the epoch's seeded shuffle, dealt round-robin to `host_count × streams` global
//!   ranks (host `h` owns global ranks `h·streams .. (h+1)·streams`), cut into batches
//!   of `batch_size` (the last one of an epoch may be short — no keyframe is dropped).
//!   Every host computes the same shuffle from the seed, so hosts get disjoint shares
//!   that together cover each epoch exactly once, without talking to each other. A
//!   sample's draws are keyed by its position in the epoch, so the same keyframe gets
//!   the same sample whatever the world size or host count.
//! * A producer thread builds batches ahead (`prefetch`) with rayon; the publisher loop
//!   (the calling thread) writes each one in place into a loaned iceoryx2 slice, sends
//!   it and wakes subscribers through the ready event.
//! * Backpressure never loses a batch: the service does not overflow and the publisher
//!   retries until a full subscriber has room. While it waits it checks, every
//!   `dead_node_check_ms`, whether the subscriber's process has died; a dead one is
//!   cleaned up (iceoryx2 dead-node detection) and skipped, the others keep receiving.
//! * A subscriber resumes through the control service: it names `(epoch, step)` and the
//!   next batch of its stream is that one.

use crate::batch::{BatchPlan, BatchShape};
use crate::sample::{Sample, SampleBuilder, SampleError};
use iceoryx2::node::NodeView as _;
use iceoryx2::port::{BackpressureAction, BackpressureInfo};
use iceoryx2::prelude::*;
use rayon::prelude::*;
use serde::{Deserialize, Serialize};
use std::collections::HashMap;
use std::sync::atomic::{AtomicBool, AtomicU64, Ordering};
use std::sync::mpsc::{RecvTimeoutError, SyncSender, sync_channel};
use std::sync::{Arc, Mutex};
use std::time::{Duration, Instant};
use superflow_schemas::batch::BatchMeta;
use superflow_schemas::service::{self as names, ResumeReply, ResumeRequest};

/// Broadcast (every subscriber sees every batch) or shard (each rank its share).
#[derive(Debug, Clone, Copy, PartialEq, Eq, Default, Serialize, Deserialize)]
#[serde(rename_all = "snake_case")]
pub enum Mode {
    /// One stream on `superflow/<run>/batches`.
    #[default]
    Broadcast,
    /// `world_size` streams on `superflow/<run>/rank/<r>`.
    Shard,
}

/// `[service]` of `pipeline.toml`.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(default, deny_unknown_fields)]
pub struct ServiceConfig {
    /// Broadcast or shard.
    pub mode: Mode,
    /// Ranks in shard mode (on this host).
    pub world_size: u32,
    /// This host's rank among `host_count` hosts (multi-host sharding).
    pub host_rank: u32,
    /// Hosts sharing each epoch; each runs its own pipeline with the same drives and
    /// configuration, and gets a disjoint share of every epoch's keyframes.
    pub host_count: u32,
    /// Samples per batch (4, the paper's per-GPU batch).
    pub batch_size: u32,
    /// Batches built ahead of the one being published.
    pub prefetch: u32,
    /// Epochs to stream; 0 streams forever.
    pub epochs: u64,
    /// How often a publisher waiting on a full subscriber checks whether it died, ms.
    pub dead_node_check_ms: u64,
    /// Subscribers each stream waits for before its first batch (a batch published to
    /// nobody would be lost); afterwards it waits whenever none is attached.
    pub min_subscribers: u32,
    /// After the last epoch: keep serving (resume requests) until every subscriber has
    /// left, at most this long, seconds.
    pub linger_secs: u64,
}

impl Default for ServiceConfig {
    fn default() -> Self {
        Self {
            mode: Mode::Broadcast,
            world_size: 1,
            host_rank: 0,
            host_count: 1,
            batch_size: 4,
            prefetch: 2,
            epochs: 0,
            dead_node_check_ms: 500,
            min_subscribers: 1,
            linger_secs: 600,
        }
    }
}

impl ServiceConfig {
    /// Checks ranges.
    pub fn validate(&self) -> Result<(), String> {
        if !(1..=1024).contains(&self.world_size) {
            return Err(format!(
                "service.world_size = {} must be 1..=1024",
                self.world_size
            ));
        }
        if !(1..=4096).contains(&self.host_count) {
            return Err(format!(
                "service.host_count = {} must be 1..=4096",
                self.host_count
            ));
        }
        if self.host_rank >= self.host_count {
            return Err(format!(
                "service.host_rank = {} must be below service.host_count = {}",
                self.host_rank, self.host_count
            ));
        }
        if self.mode == Mode::Broadcast && self.world_size != 1 {
            return Err("service.world_size > 1 needs mode = \"shard\"".into());
        }
        if !(1..=256).contains(&self.batch_size) {
            return Err(format!(
                "service.batch_size = {} must be 1..=256",
                self.batch_size
            ));
        }
        if !(1..=64).contains(&self.prefetch) {
            return Err(format!(
                "service.prefetch = {} must be 1..=64",
                self.prefetch
            ));
        }
        if self.min_subscribers as usize > superflow_schemas::service::qos::MAX_SUBSCRIBERS {
            return Err(format!(
                "service.min_subscribers = {} exceeds the {} subscribers a service admits",
                self.min_subscribers,
                superflow_schemas::service::qos::MAX_SUBSCRIBERS
            ));
        }
        if self.dead_node_check_ms == 0 {
            return Err("service.dead_node_check_ms must be > 0".into());
        }
        Ok(())
    }

    fn streams(&self) -> u32 {
        match self.mode {
            Mode::Broadcast => 1,
            Mode::Shard => self.world_size,
        }
    }
}

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

/// Counters of a running service, shared with the metrics endpoint and the log.
#[derive(Debug, Default)]
pub struct Metrics {
    /// Batches published.
    pub batches: AtomicU64,
    /// Samples published.
    pub samples: AtomicU64,
    /// Bytes of payload published.
    pub bytes: AtomicU64,
    /// Time the publisher waited for a prepared batch (producer too slow), ns.
    pub wait_for_build_nanos: AtomicU64,
    /// Time spent in `send` (backpressure: subscribers full), ns.
    pub backpressure_nanos: AtomicU64,
    /// Time writing batches into shared memory, ns.
    pub write_nanos: AtomicU64,
    /// CPU time building samples, by stage, ns.
    pub stage_decode_nanos: AtomicU64,
    /// See [`crate::sample::builder::StageTimes`].
    pub stage_sweeps_nanos: AtomicU64,
    /// See [`crate::sample::builder::StageTimes`].
    pub stage_images_nanos: AtomicU64,
    /// See [`crate::sample::builder::StageTimes`].
    pub stage_projection_nanos: AtomicU64,
    /// See [`crate::sample::builder::StageTimes`].
    pub stage_superpixels_nanos: AtomicU64,
    /// See [`crate::sample::builder::StageTimes`].
    pub stage_voxels_nanos: AtomicU64,
    /// Subscribers found dead and cleaned up.
    pub dead_subscribers: AtomicU64,
    /// Samples that could not be built (counted, logged, replaced by nothing: the batch
    /// is published short).
    pub failed_samples: AtomicU64,
    /// Resume requests accepted.
    pub resumes: AtomicU64,
    /// Messages skipped while indexing the drives.
    pub skipped_messages: AtomicU64,
}

impl Metrics {
    /// Adds one sample's CPU time per stage.
    pub fn add_stages(&self, t: &crate::sample::builder::StageTimes) {
        for (counter, nanos) in [
            (&self.stage_decode_nanos, t.decode),
            (&self.stage_sweeps_nanos, t.sweeps),
            (&self.stage_images_nanos, t.images),
            (&self.stage_projection_nanos, t.projection),
            (&self.stage_superpixels_nanos, t.superpixels),
            (&self.stage_voxels_nanos, t.voxels),
        ] {
            counter.fetch_add(nanos, Ordering::Relaxed);
        }
    }

    /// The counters in Prometheus text format.
    pub fn prometheus(&self) -> String {
        let counters: [(&str, &str, &AtomicU64); 15] = [
            (
                "superflow_batches_total",
                "Batches published",
                &self.batches,
            ),
            (
                "superflow_samples_total",
                "Samples published",
                &self.samples,
            ),
            (
                "superflow_payload_bytes_total",
                "Payload bytes published",
                &self.bytes,
            ),
            (
                "superflow_wait_for_build_seconds_total",
                "Publisher waiting for the producer",
                &self.wait_for_build_nanos,
            ),
            (
                "superflow_backpressure_seconds_total",
                "Publisher waiting for full subscribers",
                &self.backpressure_nanos,
            ),
            (
                "superflow_write_seconds_total",
                "Writing batches into shared memory",
                &self.write_nanos,
            ),
            (
                "superflow_stage_decode_seconds_total",
                "CPU time decoding sweeps and images",
                &self.stage_decode_nanos,
            ),
            (
                "superflow_stage_sweeps_seconds_total",
                "CPU time de-skewing and aligning sweeps",
                &self.stage_sweeps_nanos,
            ),
            (
                "superflow_stage_images_seconds_total",
                "CPU time resizing images",
                &self.stage_images_nanos,
            ),
            (
                "superflow_stage_projection_seconds_total",
                "CPU time projecting points",
                &self.stage_projection_nanos,
            ),
            (
                "superflow_stage_superpixels_seconds_total",
                "CPU time on superpixels",
                &self.stage_superpixels_nanos,
            ),
            (
                "superflow_stage_voxels_seconds_total",
                "CPU time on voxels and maps",
                &self.stage_voxels_nanos,
            ),
            (
                "superflow_dead_subscribers_total",
                "Dead subscribers cleaned up",
                &self.dead_subscribers,
            ),
            (
                "superflow_failed_samples_total",
                "Samples that could not be built",
                &self.failed_samples,
            ),
            (
                "superflow_resumes_total",
                "Resume requests accepted",
                &self.resumes,
            ),
        ];
        let mut out = String::new();
        for (name, help, value) in counters {
            let v = value.load(Ordering::Relaxed);
            let (kind, shown) = if name.ends_with("_seconds_total") {
                ("counter", format!("{}", v as f64 / 1e9))
            } else {
                ("counter", v.to_string())
            };
            out.push_str(&format!(
                "# HELP {name} {help}\n# TYPE {name} {kind}\n{name} {shown}\n"
            ));
        }
        let skipped = self.skipped_messages.load(Ordering::Relaxed);
        out.push_str(&format!(
            "# HELP superflow_skipped_messages Messages skipped while indexing\n# TYPE superflow_skipped_messages gauge\nsuperflow_skipped_messages {skipped}\n"
        ));
        out
    }
}

/// A failure of the service.
#[derive(Debug, thiserror::Error)]
pub enum ServiceError {
    /// iceoryx2 refused something.
    #[error("{0}")]
    Ipc(String),
    /// The configuration cannot be used.
    #[error("{0}")]
    Config(String),
    /// The dataset has no keyframe.
    #[error("the drives have no usable keyframe")]
    NoKeyframes,
}

fn ipc(what: &str) -> impl FnOnce(String) -> ServiceError + '_ {
    move |e| ServiceError::Ipc(format!("{what}: {e}"))
}

/// A batch built by the producer.
struct Prepared {
    stream: u32,
    generation: u64,
    epoch: u64,
    step: u64,
    samples: Vec<Sample>,
}

/// Per stream: service, publisher, notifier, and the subscriber → node map the
/// backpressure handler consults.
struct StreamPorts<'a> {
    service: names::BatchService,
    publisher: iceoryx2::port::publisher::Publisher<
        ipc::Service,
        [u8],
        superflow_schemas::batch::BatchHeader,
    >,
    notifier: iceoryx2::port::notifier::Notifier<ipc::Service>,
    owners: Arc<Mutex<HashMap<u128, u128>>>,
    name: String,
    published: std::cell::Cell<bool>,
    _ready: names::ReadyService,
    _lifetime: std::marker::PhantomData<&'a ()>,
}

/// Where each stream is, and a generation counter bumped by every resume so batches
/// prepared for the old position are dropped.
#[derive(Debug)]
struct Cursors {
    positions: Vec<(u64, u64)>,
    generations: Vec<u64>,
}

/// Runs the service until the configured epochs are published and every subscriber has
/// left (or `linger_secs` passed), or until `stop` is set.
pub fn serve(
    builder: &SampleBuilder<'_>,
    run: &str,
    config: &ServiceConfig,
    iox: &iceoryx2::config::Config,
    start: (u64, u64),
    stop: &Arc<AtomicBool>,
    metrics: &Arc<Metrics>,
) -> Result<(), ServiceError> {
    config.validate().map_err(ServiceError::Config)?;
    let keyframes = builder.plan().keyframes.len();
    if keyframes == 0 {
        return Err(ServiceError::NoKeyframes);
    }
    let streams = config.streams();
    let total = streams as usize * config.host_count as usize;
    if total > keyframes {
        return Err(ServiceError::Config(format!(
            "{streams} stream(s) on each of {} host(s) exceed the {keyframes} keyframes of the drives: some ranks would get nothing",
            config.host_count
        )));
    }
    let schedule = Schedule::for_host(
        keyframes,
        config.batch_size as usize,
        streams as usize,
        (config.host_rank, config.host_count),
        builder.config().seed,
    );
    let node = NodeBuilder::new()
        .config(iox)
        .signal_handling_mode(SignalHandlingMode::Disabled)
        .create::<ipc::Service>()
        .map_err(|e| ServiceError::Ipc(format!("creating the iceoryx2 node: {e:?}")))?;
    // Clean up what earlier crashed processes left behind before joining.
    let cleaned = node.try_cleanup_dead_nodes();
    if cleaned.cleanups > 0 {
        tracing::warn!(
            nodes = cleaned.cleanups,
            "cleaned up dead iceoryx2 nodes of earlier processes"
        );
    }
    let service_names: Vec<String> = match config.mode {
        Mode::Broadcast => {
            vec![names::batches_service(run).map_err(|e| ServiceError::Config(e.to_string()))?]
        }
        Mode::Shard => (0..streams)
            .map(|r| names::rank_service(run, r))
            .collect::<Result<_, _>>()
            .map_err(|e| ServiceError::Config(e.to_string()))?,
    };
    let cursors = Arc::new(Mutex::new(Cursors {
        positions: vec![start; streams as usize],
        generations: vec![0; streams as usize],
    }));
    let mut out = Vec::new();
    for name in &service_names {
        let service = names::open_batch_service(&node, name).map_err(ipc(name))?;
        let ready = names::open_ready_service(&node, name).map_err(ipc(name))?;
        let notifier = ready
            .notifier_builder()
            .create()
            .map_err(|e| ServiceError::Ipc(format!("{name}: notifier: {e:?}")))?;
        let owners: Arc<Mutex<HashMap<u128, u128>>> = Arc::default();
        let handler = dead_subscriber_handler(
            iox.clone(),
            owners.clone(),
            Duration::from_millis(config.dead_node_check_ms),
            stop.clone(),
            metrics.clone(),
        );
        let publisher = service
            .publisher_builder()
            .initial_max_slice_len(32 << 20)
            .allocation_strategy(AllocationStrategy::PowerOfTwo)
            .backpressure_strategy(BackpressureStrategy::RetryUntilDelivered)
            .set_backpressure_handler(handler)
            .create()
            .map_err(|e| ServiceError::Ipc(format!("{name}: publisher: {e:?}")))?;
        out.push(StreamPorts {
            service,
            publisher,
            notifier,
            owners,
            name: name.clone(),
            published: std::cell::Cell::new(false),
            _ready: ready,
            _lifetime: std::marker::PhantomData,
        });
    }
    let publisher_ids: Vec<u128> = out.iter().map(|s| s.publisher.id().value()).collect();
    let control = names::open_control_service(&node, run).map_err(ipc("control"))?;
    let server = control
        .server_builder()
        .create()
        .map_err(|e| ServiceError::Ipc(format!("control server: {e:?}")))?;
    tracing::info!(
        services = %service_names.join(", "),
        keyframes,
        host = config.host_rank,
        hosts = config.host_count,
        steps_per_epoch = schedule.steps(0),
        batch_size = config.batch_size,
        "publishing"
    );

    let (tx, rx) = sync_channel::<Prepared>(config.prefetch as usize);
    let producer_done = AtomicBool::new(false);
    let producer_idle = AtomicBool::new(false);
    let shape = BatchShape::of(builder.config());
    let bar = indicatif::ProgressBar::new_spinner();
    bar.set_style(
        indicatif::ProgressStyle::with_template("{spinner} {msg}")
            .unwrap_or_else(|_| indicatif::ProgressStyle::default_spinner()),
    );
    let result = std::thread::scope(|scope| {
        scope.spawn(|| {
            produce(
                builder,
                &schedule,
                config,
                &cursors,
                &tx,
                stop,
                &producer_idle,
                metrics,
            );
            producer_done.store(true, Ordering::SeqCst);
            drop(tx);
        });
        let mut sequence = 0u64;
        let mut last_log = Instant::now();
        let mut finished_at: Option<Instant> = None;
        let result: Result<(), ServiceError> = loop {
            if stop.load(Ordering::SeqCst) {
                break Ok(());
            }
            serve_control(
                &server,
                &publisher_ids,
                &cursors,
                &schedule,
                config,
                sequence,
                metrics,
            );
            let waited = Instant::now();
            // Read before waiting: the producer turns idle only after its last send, so
            // idle-then-timeout means every prepared batch was taken.
            let idle_before = producer_idle.load(Ordering::SeqCst);
            let prepared = match rx.recv_timeout(Duration::from_millis(20)) {
                Ok(p) => p,
                Err(RecvTimeoutError::Timeout) => {
                    let done = config.epochs > 0
                        && idle_before
                        && cursors
                            .lock()
                            .map(|c| c.positions.iter().all(|(e, _)| *e >= config.epochs))
                            .unwrap_or(true);
                    if !done {
                        finished_at = None;
                        metrics
                            .wait_for_build_nanos
                            .fetch_add(waited.elapsed().as_nanos() as u64, Ordering::Relaxed);
                        continue;
                    }
                    // All epochs published: serve resume requests while subscribers
                    // are attached, then end.
                    let since = *finished_at.get_or_insert_with(Instant::now);
                    let attached: usize = out
                        .iter()
                        .map(|s| s.service.dynamic_config().number_of_subscribers())
                        .sum();
                    if attached == 0 || since.elapsed() > Duration::from_secs(config.linger_secs) {
                        tracing::info!(
                            batches = sequence,
                            "all epochs published; every subscriber has left"
                        );
                        break Ok(());
                    }
                    let _ = node.try_cleanup_dead_nodes();
                    continue;
                }
                Err(RecvTimeoutError::Disconnected) => break Ok(()),
            };
            metrics
                .wait_for_build_nanos
                .fetch_add(waited.elapsed().as_nanos() as u64, Ordering::Relaxed);
            {
                let c = cursors.lock().unwrap_or_else(|e| e.into_inner());
                if c.generations[prepared.stream as usize] != prepared.generation {
                    continue; // built for a position a resume request replaced
                }
            }
            let stream = &out[prepared.stream as usize];
            let span = tracing::info_span!("publish", service = %stream.name, epoch = prepared.epoch, step = prepared.step, sequence);
            let _entered = span.enter();
            // Never publish into the void: wait for the subscribers.
            let required = if stream.published.get() {
                1
            } else {
                config.min_subscribers.max(1) as usize
            };
            let mut announced = false;
            while stream.service.dynamic_config().number_of_subscribers() < required
                && !stop.load(Ordering::SeqCst)
            {
                if !announced {
                    tracing::info!(service = %stream.name, required, "waiting for subscribers");
                    announced = true;
                }
                serve_control(
                    &server,
                    &publisher_ids,
                    &cursors,
                    &schedule,
                    config,
                    sequence,
                    metrics,
                );
                let _ = node.try_cleanup_dead_nodes();
                std::thread::sleep(Duration::from_millis(20));
            }
            if stop.load(Ordering::SeqCst) {
                break Ok(());
            }
            {
                let c = cursors.lock().unwrap_or_else(|e| e.into_inner());
                if c.generations[prepared.stream as usize] != prepared.generation {
                    continue;
                }
            }
            stream.published.set(true);
            match publish(
                stream,
                &prepared,
                shape,
                run,
                schedule.seed(),
                sequence,
                metrics,
                stop,
            ) {
                Ok(()) => {
                    sequence += 1;
                    bar.set_message(format!(
                        "{} batches, {} samples, epoch {} step {} on {}",
                        metrics.batches.load(Ordering::Relaxed),
                        metrics.samples.load(Ordering::Relaxed),
                        prepared.epoch,
                        prepared.step,
                        stream.name
                    ));
                    bar.tick();
                }
                Err(e) => break Err(e),
            }
            if last_log.elapsed() > Duration::from_secs(10) {
                last_log = Instant::now();
                log_counters(metrics);
            }
        };
        stop.store(true, Ordering::SeqCst);
        // Unblock the producer if it waits on a full channel.
        while rx.try_recv().is_ok() {}
        drop(rx);
        result
    });
    bar.finish_and_clear();
    log_counters(metrics);
    tracing::debug!(
        producer_done = producer_done.load(Ordering::SeqCst),
        "service stopped"
    );
    result
}

fn log_counters(metrics: &Metrics) {
    tracing::info!(
        batches = metrics.batches.load(Ordering::Relaxed),
        samples = metrics.samples.load(Ordering::Relaxed),
        backpressure_secs = metrics.backpressure_nanos.load(Ordering::Relaxed) as f64 / 1e9,
        wait_for_build_secs = metrics.wait_for_build_nanos.load(Ordering::Relaxed) as f64 / 1e9,
        dead_subscribers = metrics.dead_subscribers.load(Ordering::Relaxed),
        failed_samples = metrics.failed_samples.load(Ordering::Relaxed),
        "counters"
    );
}

/// The backpressure handler of a publisher: keep retrying a full subscriber (never drop
/// a batch for a live one), but every `check` look for dead nodes; when the waiting
/// subscriber's node is dead, clean it up and skip it. Gives up (and the batch is lost
/// for nobody alive) only when the service is stopping.
fn dead_subscriber_handler(
    iox: iceoryx2::config::Config,
    owners: Arc<Mutex<HashMap<u128, u128>>>,
    check: Duration,
    stop: Arc<AtomicBool>,
    metrics: Arc<Metrics>,
) -> impl Fn(&BackpressureInfo) -> BackpressureAction + Send + 'static {
    let last_check = Mutex::new(Duration::ZERO);
    move |info: &BackpressureInfo| {
        if stop.load(Ordering::SeqCst) {
            return BackpressureAction::DiscardData;
        }
        let mut last = last_check.lock().unwrap_or_else(|e| e.into_inner());
        if info.elapsed_time < *last {
            *last = Duration::ZERO; // a new delivery started
        }
        if info.elapsed_time < *last + check {
            std::thread::sleep(Duration::from_micros(200));
            return BackpressureAction::Retry;
        }
        *last = info.elapsed_time;
        let owner = owners
            .lock()
            .unwrap_or_else(|e| e.into_inner())
            .get(&info.receiver_port_id)
            .copied();
        let mut dead_owner = false;
        let mut cleaned = 0;
        let _ = Node::<ipc::Service>::list(&iox, |state| {
            if let NodeState::Dead(view) = state {
                let id = view.id().value();
                if Some(id) == owner {
                    dead_owner = true;
                }
                if view.try_remove_stale_resources().is_ok() {
                    cleaned += 1;
                }
            }
            CallbackProgression::Continue
        });
        if cleaned > 0 {
            tracing::warn!(nodes = cleaned, "cleaned up dead iceoryx2 nodes");
        }
        if dead_owner {
            metrics.dead_subscribers.fetch_add(1, Ordering::Relaxed);
            tracing::warn!(
                subscriber = info.receiver_port_id,
                "a subscriber died with a full queue: cleaned up, the stream goes on for the others"
            );
            BackpressureAction::DiscardData
        } else {
            tracing::debug!(
                subscriber = info.receiver_port_id,
                waited_ms = info.elapsed_time.as_millis() as u64,
                "waiting for a full subscriber"
            );
            BackpressureAction::Retry
        }
    }
}

/// Builds batches ahead, stream by stream in turn, from each stream's cursor.
#[allow(clippy::too_many_arguments)]
fn produce(
    builder: &SampleBuilder<'_>,
    schedule: &Schedule,
    config: &ServiceConfig,
    cursors: &Mutex<Cursors>,
    tx: &SyncSender<Prepared>,
    stop: &AtomicBool,
    idle: &AtomicBool,
    metrics: &Metrics,
) {
    let streams = config.streams() as usize;
    let mut orders: HashMap<u64, Vec<u32>> = HashMap::new();
    let mut finished = vec![false; streams];
    let mut stream = 0usize;
    while !stop.load(Ordering::SeqCst) {
        let (epoch, step, generation) = {
            let c = cursors.lock().unwrap_or_else(|e| e.into_inner());
            let (e, s) = c.positions[stream];
            (e, s, c.generations[stream])
        };
        if config.epochs > 0 && epoch >= config.epochs {
            finished[stream] = true;
            if finished.iter().all(|f| *f) {
                // Every stream is done: idle until a resume request rewinds one (the
                // publisher decides when the service ends).
                idle.store(true, Ordering::SeqCst);
                std::thread::sleep(Duration::from_millis(10));
                finished.iter_mut().for_each(|f| *f = false);
            }
            stream = (stream + 1) % streams;
            continue;
        }
        idle.store(false, Ordering::SeqCst);
        finished[stream] = false;
        if orders.len() > 4 {
            orders.retain(|e, _| *e + 1 >= epoch);
        }
        let order = orders
            .entry(epoch)
            .or_insert_with(|| builder.plan().epoch_order(schedule.seed(), epoch));
        let Some(slots) = schedule.batch(order, stream, step) else {
            // Past the epoch's end: next epoch.
            if let Ok(mut c) = cursors.lock()
                && c.generations[stream] == generation
            {
                c.positions[stream] = (epoch + 1, 0);
            }
            continue;
        };
        let span = tracing::debug_span!("build batch", stream, epoch, step);
        let _entered = span.enter();
        let built: Vec<Result<Sample, SampleError>> = slots
            .par_iter()
            .map(|&(keyframe, index)| builder.build_keyframe(keyframe as usize, epoch, index))
            .collect();
        let mut samples = Vec::with_capacity(built.len());
        for (result, (keyframe, _)) in built.into_iter().zip(&slots) {
            match result {
                Ok(sample) => {
                    metrics.add_stages(&sample.times);
                    samples.push(sample);
                }
                Err(e) => {
                    metrics.failed_samples.fetch_add(1, Ordering::Relaxed);
                    tracing::error!(keyframe, epoch, "sample lost: {e}");
                }
            }
        }
        // Advance this stream unless a resume moved it meanwhile.
        let current = {
            let mut c = cursors.lock().unwrap_or_else(|e| e.into_inner());
            if c.generations[stream] == generation {
                c.positions[stream] = (epoch, step + 1);
                true
            } else {
                false
            }
        };
        if current && !samples.is_empty() {
            let prepared = Prepared {
                stream: stream as u32,
                generation,
                epoch,
                step,
                samples,
            };
            if tx.send(prepared).is_err() {
                return;
            }
        }
        stream = (stream + 1) % streams;
    }
}

/// Answers pending resume requests.
fn serve_control(
    server: &iceoryx2::port::server::Server<ipc::Service, ResumeRequest, (), ResumeReply, ()>,
    publishers: &[u128],
    cursors: &Mutex<Cursors>,
    schedule: &Schedule,
    config: &ServiceConfig,
    sequence: u64,
    metrics: &Metrics,
) {
    loop {
        let request = match server.receive() {
            Ok(Some(r)) => r,
            Ok(None) => return,
            Err(e) => {
                tracing::warn!("control service: {e:?}");
                return;
            }
        };
        let ask = *request.payload();
        let publisher = publishers.get(ask.rank as usize).copied().unwrap_or(0);
        let id = |mut reply: ResumeReply| {
            reply.publisher_lo = publisher as u64;
            reply.publisher_hi = (publisher >> 64) as u64;
            reply
        };
        let wants_broadcast = ask.broadcast == 1;
        let reply = if wants_broadcast != (config.mode == Mode::Broadcast)
            || ask.rank >= config.streams()
        {
            id(ResumeReply {
                accepted: 0,
                reason: 1,
                next_sequence: sequence,
                ..Default::default()
            })
        } else if (config.epochs > 0 && ask.epoch >= config.epochs)
            || ask.step > schedule.steps(ask.rank as usize)
        {
            id(ResumeReply {
                accepted: 0,
                reason: 2,
                next_sequence: sequence,
                ..Default::default()
            })
        } else {
            let mut c = cursors.lock().unwrap_or_else(|e| e.into_inner());
            c.positions[ask.rank as usize] = (ask.epoch, ask.step);
            c.generations[ask.rank as usize] += 1;
            metrics.resumes.fetch_add(1, Ordering::Relaxed);
            tracing::info!(
                rank = ask.rank,
                epoch = ask.epoch,
                step = ask.step,
                "resume requested"
            );
            id(ResumeReply {
                accepted: 1,
                reason: 0,
                next_sequence: sequence,
                ..Default::default()
            })
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

#[allow(clippy::too_many_arguments)]
fn publish(
    stream: &StreamPorts<'_>,
    prepared: &Prepared,
    shape: BatchShape,
    run: &str,
    seed: u64,
    sequence: u64,
    metrics: &Metrics,
    stop: &AtomicBool,
) -> Result<(), ServiceError> {
    let _ = stop;
    let t = Instant::now();
    let plan = BatchPlan::new(&prepared.samples, shape)
        .map_err(|e| ServiceError::Config(format!("{}: {e}", stream.name)))?;
    let meta = BatchMeta {
        run: run.to_string(),
        epoch: prepared.epoch,
        step: prepared.step,
        seed,
        sequence,
        created_unix_nanos: std::time::SystemTime::now()
            .duration_since(std::time::UNIX_EPOCH)
            .map_or(0, |d| d.as_nanos() as u64),
        sample_count: prepared.samples.len() as u32,
        flags: 0,
    };
    let header = plan
        .layout()
        .header(&meta)
        .map_err(|e| ServiceError::Config(format!("{}: {e}", stream.name)))?;
    let len = plan.layout().payload_len();
    let sample = stream
        .publisher
        .loan_slice_uninit(len)
        .map_err(|e| ServiceError::Ipc(format!("{}: loaning {len} bytes: {e:?}", stream.name)))?;
    let mut sample = sample.write_from_fn(|_| 0u8);
    *sample.user_header_mut() = header;
    plan.write_zeroed(&prepared.samples, sample.payload_mut())
        .map_err(|e| ServiceError::Config(format!("{}: {e}", stream.name)))?;
    metrics
        .write_nanos
        .fetch_add(t.elapsed().as_nanos() as u64, Ordering::Relaxed);
    // Who owns which subscriber port, for the dead-subscriber check.
    {
        let mut owners = stream.owners.lock().unwrap_or_else(|e| e.into_inner());
        owners.clear();
        stream.service.dynamic_config().list_subscribers(|details| {
            owners.insert(details.subscriber_id.value(), details.node_id.value());
            CallbackProgression::Continue
        });
    }
    let t = Instant::now();
    let delivered = sample
        .send()
        .map_err(|e| ServiceError::Ipc(format!("{}: send: {e:?}", stream.name)))?;
    metrics
        .backpressure_nanos
        .fetch_add(t.elapsed().as_nanos() as u64, Ordering::Relaxed);
    if let Err(e) = stream.notifier.notify() {
        tracing::warn!("{}: notify: {e:?}", stream.name);
    }
    metrics.batches.fetch_add(1, Ordering::Relaxed);
    metrics
        .samples
        .fetch_add(prepared.samples.len() as u64, Ordering::Relaxed);
    metrics.bytes.fetch_add(len as u64, Ordering::Relaxed);
    tracing::debug!(delivered, bytes = len, "published");
    Ok(())
}

#[cfg(test)]
mod tests {
    use super::*;

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
        assert!(bad.validate().unwrap_err().contains("host_rank"));
        bad.host_rank = 1;
        assert!(bad.validate().is_ok());
    }
}
