//! The iceoryx2 ports of one stream: the batch service with its publisher (lossless,
//! with the dead-subscriber backpressure handler), the ready event's notifier, and
//! publishing one prepared batch in place into a loaned shared-memory slice.

use super::config::ServiceConfig;
use super::error::ServiceError;
use super::metrics::Metrics;
use super::producer::Prepared;
use crate::batch::{BatchPlan, BatchShape};
use iceoryx2::node::NodeView as _;
use iceoryx2::port::{BackpressureAction, BackpressureInfo};
use iceoryx2::prelude::*;
use std::collections::HashMap;
use std::sync::atomic::{AtomicBool, Ordering};
use std::sync::{Arc, Mutex};
use std::time::{Duration, Instant};
use superflow_schemas::batch::{BatchHeader, BatchMeta};
use superflow_schemas::service as names;

/// Per stream: service, publisher, notifier, and the subscriber → node map the
/// backpressure handler consults.
pub(super) struct StreamPorts {
    service: names::BatchService,
    publisher: iceoryx2::port::publisher::Publisher<ipc::Service, [u8], BatchHeader>,
    notifier: iceoryx2::port::notifier::Notifier<ipc::Service>,
    owners: Owners,
    /// The batch service's name.
    pub name: String,
    /// Whether a batch was published on it (the first waits for `min_subscribers`).
    pub published: std::cell::Cell<bool>,
    _ready: names::ReadyService,
}

/// Payload bytes loaned for a lost batch: the smallest slice iceoryx2 hands out.
const LOST_PAYLOAD_LEN: usize = 0;

/// Who owns which subscriber port: subscriber port id → node id.
type Owners = Arc<Mutex<HashMap<u128, u128>>>;

/// The identity of a published batch, for its [`BatchMeta`].
pub(super) struct Stamp<'a> {
    pub run: &'a str,
    pub seed: u64,
    pub sequence: u64,
}

impl StreamPorts {
    /// Opens the batch service `name`, its ready event, a notifier and a publisher.
    pub fn open(
        node: &Node<ipc::Service>,
        name: &str,
        iox: &iceoryx2::config::Config,
        config: &ServiceConfig,
        stop: &Arc<AtomicBool>,
        metrics: &Arc<Metrics>,
    ) -> Result<Self, ServiceError> {
        let service = names::open_batch_service(node, name)?;
        let ready = names::open_ready_service(node, name)?;
        let notifier = ready
            .notifier_builder()
            .create()
            .map_err(ServiceError::ipc(format!("{name}: notifier")))?;
        let owners: Owners = Arc::default();
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
            .map_err(ServiceError::ipc(format!("{name}: publisher")))?;
        Ok(Self {
            service,
            publisher,
            notifier,
            owners,
            name: name.to_string(),
            published: std::cell::Cell::new(false),
            _ready: ready,
        })
    }

    /// The publisher's id.
    pub fn publisher_id(&self) -> u128 {
        self.publisher.id().value()
    }

    /// Subscribers attached now.
    pub fn subscribers(&self) -> usize {
        self.service.dynamic_config().number_of_subscribers()
    }

    /// Writes `prepared` into a loaned slice, sends it (waiting on full subscribers,
    /// see [`dead_subscriber_handler`]) and wakes the subscribers. A batch without a
    /// sample (every one failed) goes out lost: its header at its place in the stream,
    /// flag `BATCH_LOST`, nothing in it.
    pub fn publish(
        &self,
        prepared: &Prepared,
        shape: BatchShape,
        stamp: &Stamp<'_>,
        metrics: &Metrics,
    ) -> Result<(), ServiceError> {
        let batch_error = |source| ServiceError::Batch {
            service: self.name.clone(),
            source,
        };
        let t = Instant::now();
        let meta = BatchMeta {
            run: stamp.run.to_string(),
            epoch: prepared.epoch,
            step: prepared.step,
            seed: stamp.seed,
            sequence: stamp.sequence,
            created_unix_nanos: std::time::SystemTime::now()
                .duration_since(std::time::UNIX_EPOCH)
                .map_or(0, |d| d.as_nanos() as u64),
            sample_count: prepared.samples.len() as u32,
            flags: 0,
        };
        let lost = prepared.samples.is_empty();
        let (sample, len) = if lost {
            let header = BatchHeader::lost(&meta).map_err(batch_error)?;
            let mut sample = self.loan(LOST_PAYLOAD_LEN)?.write_from_fn(|_| 0u8);
            *sample.user_header_mut() = header;
            (sample, LOST_PAYLOAD_LEN)
        } else {
            let plan = BatchPlan::new(&prepared.samples, shape).map_err(batch_error)?;
            let header = plan.layout().header(&meta).map_err(batch_error)?;
            let len = plan.layout().payload_len();
            let mut sample = self.loan(len)?.write_from_fn(|_| 0u8);
            *sample.user_header_mut() = header;
            plan.write_zeroed(&prepared.samples, sample.payload_mut())
                .map_err(batch_error)?;
            (sample, len)
        };
        metrics
            .write_nanos
            .fetch_add(t.elapsed().as_nanos() as u64, Ordering::Relaxed);
        self.record_owners();
        let t = Instant::now();
        let delivered = sample
            .send()
            .map_err(ServiceError::ipc(format!("{}: send", self.name)))?;
        metrics
            .backpressure_nanos
            .fetch_add(t.elapsed().as_nanos() as u64, Ordering::Relaxed);
        if let Err(e) = self.notifier.notify() {
            tracing::warn!("{}: notify: {e:?}", self.name);
        }
        metrics.batches.fetch_add(1, Ordering::Relaxed);
        metrics
            .samples
            .fetch_add(prepared.samples.len() as u64, Ordering::Relaxed);
        metrics.bytes.fetch_add(len as u64, Ordering::Relaxed);
        if lost {
            metrics.lost_batches.fetch_add(1, Ordering::Relaxed);
            tracing::error!(
                epoch = prepared.epoch,
                step = prepared.step,
                stream = %self.name,
                failed = prepared.failed,
                "batch lost: all {} of its samples failed to build; published empty (BATCH_LOST) so that subscribers keep their place in the epoch",
                prepared.failed
            );
        }
        tracing::debug!(delivered, bytes = len, lost, "published");
        Ok(())
    }

    /// A slice of `len` bytes of shared memory for the next batch.
    fn loan(
        &self,
        len: usize,
    ) -> Result<
        iceoryx2::sample_mut_uninit::SampleMutUninit<
            ipc::Service,
            [std::mem::MaybeUninit<u8>],
            BatchHeader,
        >,
        ServiceError,
    > {
        self.publisher
            .loan_slice_uninit(len)
            .map_err(ServiceError::ipc(format!(
                "{}: loaning {len} bytes",
                self.name
            )))
    }

    /// Who owns which subscriber port, for the dead-subscriber check.
    fn record_owners(&self) {
        let mut owners = self.owners.lock().unwrap_or_else(|e| e.into_inner());
        owners.clear();
        self.service.dynamic_config().list_subscribers(|details| {
            owners.insert(details.subscriber_id.value(), details.node_id.value());
            CallbackProgression::Continue
        });
    }
}

/// The backpressure handler of a publisher: keep retrying a full subscriber (never drop
/// a batch for a live one), but every `check` look for dead nodes; when the waiting
/// subscriber's node is dead, clean it up and skip it. Gives up (and the batch is lost
/// for nobody alive) only when the service is stopping.
fn dead_subscriber_handler(
    iox: iceoryx2::config::Config,
    owners: Owners,
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
        if owner_died(&iox, owner) {
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

/// Cleans up every dead node; whether `owner` was one of them.
fn owner_died(iox: &iceoryx2::config::Config, owner: Option<u128>) -> bool {
    let mut dead_owner = false;
    let mut cleaned = 0;
    let _ = Node::<ipc::Service>::list(iox, |state| {
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
    dead_owner
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::sample::SampleConfig;
    use superflow_schemas::batch::{BATCH_LOST, BatchView};

    /// A batch whose samples all failed goes out lost: a subscriber receives its header
    /// at its place in the stream, with nothing in it, and the reader accepts it.
    #[test]
    fn a_batch_without_samples_is_published_lost() {
        let prefix = format!("sflostport{}", std::process::id());
        let iox = names::iceoryx2_config(Some(&prefix)).unwrap_or_else(|e| panic!("{e}"));
        let node = NodeBuilder::new()
            .config(&iox)
            .create::<ipc::Service>()
            .unwrap_or_else(|e| panic!("{e}"));
        let name = names::rank_service("lost", 1).unwrap_or_else(|e| panic!("{e}"));
        let stop = Arc::new(AtomicBool::new(false));
        let metrics = Arc::new(Metrics::default());
        let config = ServiceConfig::default();
        let ports = StreamPorts::open(&node, &name, &iox, &config, &stop, &metrics)
            .unwrap_or_else(|e| panic!("{e}"));
        let subscriber = names::open_batch_service(&node, &name)
            .unwrap_or_else(|e| panic!("{e}"))
            .subscriber_builder()
            .create()
            .unwrap_or_else(|e| panic!("{e}"));
        let prepared = Prepared {
            stream: 1,
            generation: 0,
            epoch: 3,
            step: 2,
            samples: Vec::new(),
            failed: 4,
        };
        let stamp = Stamp {
            run: "lost",
            seed: 5,
            sequence: 17,
        };
        let shape = BatchShape::of(&SampleConfig::default());
        ports
            .publish(&prepared, shape, &stamp, &metrics)
            .unwrap_or_else(|e| panic!("{e}"));
        let received = subscriber
            .receive()
            .unwrap_or_else(|e| panic!("{e:?}"))
            .unwrap_or_else(|| panic!("the lost batch arrives"));
        let header = received.user_header();
        assert_eq!(
            (
                header.flags,
                header.section_count,
                header.sample_count,
                header.payload_len
            ),
            (BATCH_LOST, 0, 0, 0)
        );
        assert_eq!(received.payload().len(), LOST_PAYLOAD_LEN);
        let view = BatchView::new(header, received.payload()).unwrap_or_else(|e| panic!("{e}"));
        assert!(view.is_lost());
        let meta = view.meta();
        assert_eq!(
            (
                meta.epoch,
                meta.step,
                meta.seed,
                meta.sequence,
                meta.run.as_str()
            ),
            (3, 2, 5, 17, "lost")
        );
        assert_eq!(metrics.lost_batches.load(Ordering::Relaxed), 1);
        assert_eq!(metrics.batches.load(Ordering::Relaxed), 1);
        assert_eq!(metrics.samples.load(Ordering::Relaxed), 0);
        assert!(
            metrics
                .prometheus()
                .contains("superflow_lost_batches_total 1\n")
        );
    }
}
