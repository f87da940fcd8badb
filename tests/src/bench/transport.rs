//! Delivery over iceoryx2 shared memory versus a Unix socket, and the cost of fan-out.
//!
//! * [`iceoryx2_run`]: publish→receive latency (µs) of payloads sent to subscriber
//!   threads (loaned slice, `send`, event wake-up, `receive` — the subscriber blocks on
//!   the event like a trainer does), and the producer's time per message (loan + write
//!   every byte + send + notify);
//! * [`socket_run`]: the same bytes written through a Unix stream socket and read into
//!   the receiver's buffer (one copy each way).
//!
//! Subscribers are threads of this process, each with its own iceoryx2 node (the same
//! shared-memory path as separate processes). Clocks: one `Instant` base. Every run uses
//! the iceoryx2 prefix [`prefix`] of this process and a service of its own tag, and
//! drops all its ports and nodes before returning; [`release_shared_memory`] removes
//! what iceoryx2 keeps of the prefix after that.
//!
//! Used by `cargo bench -p superflow-pipeline --bench transport` (through `#[path]`) and
//! by the summary bench of `superflow-tests`.

use iceoryx2::prelude::*;
use std::io::{Read, Write};
use std::os::unix::net::UnixStream;
use std::sync::{Arc, Barrier};
use std::time::{Duration, Instant};

/// 1 KiB.
pub const KIB: usize = 1024;
/// 1 MiB.
pub const MIB: usize = 1024 * 1024;

/// The iceoryx2 prefix of this process's runs (`sfbench<pid>`), the streaming runs of
/// the trainer bench included.
pub fn prefix() -> String {
    format!("sfbench{}", std::process::id())
}

/// "1 KiB", "16 MiB", "34.9 MiB".
pub fn size_label(size: usize) -> String {
    if size.is_multiple_of(MIB) {
        format!("{} MiB", size / MIB)
    } else if size >= MIB {
        format!("{:.1} MiB", size as f64 / MIB as f64)
    } else {
        format!("{} KiB", size / KIB)
    }
}

/// Latency repetitions for a payload size (`quick`: a quarter, at least 3).
pub fn latency_reps(size: usize, quick: bool) -> usize {
    let r = if size <= MIB {
        300
    } else if size <= 16 * MIB {
        60
    } else if size <= 64 * MIB {
        20
    } else {
        8
    };
    if quick { (r / 4).max(3) } else { r }
}

/// Batches per fan-out run (`quick`: 10).
pub fn fanout_reps(quick: bool) -> usize {
    if quick { 10 } else { 40 }
}

/// The pause between two messages, so that one is in flight at a time.
fn gap(size: usize) -> Duration {
    Duration::from_micros(if size > 8 * MIB { 2000 } else { 200 })
}

fn config() -> anyhow::Result<iceoryx2::config::Config> {
    superflow_schemas::service::iceoryx2_config(Some(&prefix())).map_err(|e| anyhow::anyhow!(e))
}

fn node(config: &iceoryx2::config::Config) -> anyhow::Result<Node<ipc::Service>> {
    NodeBuilder::new()
        .config(config)
        .create::<ipc::Service>()
        .map_err(|e| anyhow::anyhow!("{e:?}"))
}

type Data =
    iceoryx2::service::port_factory::publish_subscribe::PortFactory<ipc::Service, [u8], u64>;
type Ready = iceoryx2::service::port_factory::event::PortFactory<ipc::Service>;

/// The lossless `[u8]` service (send time as user header) and its wake-up event.
fn open_services(node: &Node<ipc::Service>, name: &str) -> anyhow::Result<(Data, Ready)> {
    let service = node
        .service_builder(&name.try_into()?)
        .publish_subscribe::<[u8]>()
        .user_header::<u64>()
        .enable_safe_overflow(false)
        .subscriber_max_buffer_size(2)
        .max_subscribers(8)
        .open_or_create()
        .map_err(|e| anyhow::anyhow!("{e:?}"))?;
    let event = node
        .service_builder(&format!("{name}/ready").as_str().try_into()?)
        .event()
        .open_or_create()
        .map_err(|e| anyhow::anyhow!("{e:?}"))?;
    Ok((service, event))
}

/// iceoryx2 latencies (µs, every subscriber's) of `reps` payloads of `size` bytes to
/// `subscribers` threads, and the producer's time per message (ms) for loan + fill +
/// send + notify. `tag` makes the service unique to the run.
pub fn iceoryx2_run(
    size: usize,
    reps: usize,
    subscribers: usize,
    tag: &str,
) -> anyhow::Result<(Vec<f64>, f64)> {
    let cfg = config()?;
    let name = format!("bench/{tag}");
    let base = Instant::now();
    let ready = Arc::new(Barrier::new(subscribers + 1));
    let mut handles = Vec::new();
    for _ in 0..subscribers {
        let (cfg, name, ready) = (cfg.clone(), name.clone(), ready.clone());
        handles.push(std::thread::spawn(move || -> anyhow::Result<Vec<f64>> {
            let node = node(&cfg)?;
            let (service, event) = open_services(&node, &name)?;
            let subscriber = service
                .subscriber_builder()
                .buffer_size(2)
                .create()
                .map_err(|e| anyhow::anyhow!("{e:?}"))?;
            let listener = event
                .listener_builder()
                .create()
                .map_err(|e| anyhow::anyhow!("{e:?}"))?;
            ready.wait();
            let mut latencies = Vec::with_capacity(reps);
            while latencies.len() < reps {
                match subscriber.receive().map_err(|e| anyhow::anyhow!("{e:?}"))? {
                    Some(sample) => {
                        let now = base.elapsed().as_nanos() as u64;
                        let payload = sample.payload();
                        // Touch both ends: the bytes are there, not copied.
                        std::hint::black_box((payload[0], payload[payload.len() - 1]));
                        latencies.push((now - *sample.user_header()) as f64 / 1e3);
                    }
                    None => {
                        listener
                            .timed_wait(|_| {}, Duration::from_millis(100))
                            .map_err(|e| anyhow::anyhow!("{e:?}"))?;
                    }
                }
            }
            Ok(latencies)
        }));
    }
    let node = node(&cfg)?;
    let (service, event) = open_services(&node, &name)?;
    let publisher = service
        .publisher_builder()
        .initial_max_slice_len(size)
        .backpressure_strategy(BackpressureStrategy::RetryUntilDelivered)
        .create()
        .map_err(|e| anyhow::anyhow!("{e:?}"))?;
    let notifier = event
        .notifier_builder()
        .create()
        .map_err(|e| anyhow::anyhow!("{e:?}"))?;
    ready.wait();
    while service.dynamic_config().number_of_subscribers() < subscribers {
        std::thread::sleep(Duration::from_millis(1));
    }
    let mut producer = Duration::ZERO;
    for i in 0..reps {
        let t = Instant::now();
        let sample = publisher
            .loan_slice_uninit(size)
            .map_err(|e| anyhow::anyhow!("{e:?}"))?;
        // The producer writes every byte once (as the pipeline writes a batch).
        let mut sample = sample.write_from_fn(|j| (j + i) as u8);
        *sample.user_header_mut() = base.elapsed().as_nanos() as u64;
        sample.send().map_err(|e| anyhow::anyhow!("{e:?}"))?;
        notifier.notify().map_err(|e| anyhow::anyhow!("{e:?}"))?;
        producer += t.elapsed();
        // One message in flight at a time: latency, not throughput.
        std::thread::sleep(gap(size));
    }
    let mut all = Vec::new();
    for h in handles {
        all.extend(
            h.join()
                .map_err(|_| anyhow::anyhow!("subscriber panicked"))??,
        );
    }
    Ok((all, producer.as_secs_f64() * 1e3 / reps as f64))
}

/// Unix socket latencies (µs): the sender writes the bytes, the receiver reads them all.
pub fn socket_run(size: usize, reps: usize) -> anyhow::Result<Vec<f64>> {
    let (mut tx, mut rx) = UnixStream::pair()?;
    let base = Instant::now();
    let receiver = std::thread::spawn(move || -> anyhow::Result<Vec<f64>> {
        let mut buf = vec![0u8; size + 8];
        let mut latencies = Vec::with_capacity(reps);
        for _ in 0..reps {
            rx.read_exact(&mut buf)?;
            let now = base.elapsed().as_nanos() as u64;
            let sent = u64::from_le_bytes(buf[..8].try_into()?);
            latencies.push((now - sent) as f64 / 1e3);
        }
        Ok(latencies)
    });
    let mut message = vec![0u8; size + 8];
    for i in 0..reps {
        for (j, b) in message[8..].iter_mut().enumerate() {
            *b = (j + i) as u8;
        }
        let sent = base.elapsed().as_nanos() as u64;
        message[..8].copy_from_slice(&sent.to_le_bytes());
        tx.write_all(&message)?;
        std::thread::sleep(gap(size));
    }
    receiver
        .join()
        .map_err(|_| anyhow::anyhow!("receiver panicked"))?
}

/// The files of this process's prefix in /dev/shm: iceoryx2 removes a service's
/// shared memory with its last port but keeps the prefix's node-id counter
/// (`<prefix>_…global_mgmt`). Once no node of the prefix is left (every run has
/// returned), that file is removed too; returns what is still there (nothing, unless a
/// run leaked).
pub fn release_shared_memory() -> Vec<String> {
    let prefix = format!("{}_", prefix());
    let ours = || -> Vec<String> {
        std::fs::read_dir("/dev/shm")
            .map(|dir| {
                dir.filter_map(Result::ok)
                    .map(|e| e.file_name().to_string_lossy().into_owned())
                    .filter(|n| n.starts_with(&prefix))
                    .collect()
            })
            .unwrap_or_default()
    };
    for name in ours() {
        if name.ends_with(".global_mgmt") {
            let _ = std::fs::remove_file(std::path::Path::new("/dev/shm").join(name));
        }
    }
    ours()
}

/// What [`release_shared_memory`] found left, for a report: `none`, or the files.
pub fn left_in_shm(left: &[String]) -> String {
    if left.is_empty() {
        "none".to_owned()
    } else {
        left.join(", ")
    }
}

/// Prints a bench's report, writes it as `file` (see [`super::common::write_report`])
/// and fails the bench when shared memory was `left`.
pub fn publish_report(file: &str, report: &str, left: &[String]) -> anyhow::Result<()> {
    print!("\n{report}");
    super::common::write_report(file, report)?;
    anyhow::ensure!(left.is_empty(), "left in /dev/shm: {left:?}");
    Ok(())
}

/// A subscriber of run `run`'s broadcast batches under the iceoryx2 prefix `prefix`, with
/// the listener of their ready event, and the node and services that keep both open: how
/// a bench receives from the real `superflow-pipeline` service. Dropped in field order.
pub struct BatchReceiver {
    /// The batches.
    pub subscriber: iceoryx2::port::subscriber::Subscriber<
        ipc::Service,
        [u8],
        superflow_schemas::batch::BatchHeader,
    >,
    /// The ready event: woken when a batch was published.
    pub listener: iceoryx2::port::listener::Listener<ipc::Service>,
    _ready: superflow_schemas::service::ReadyService,
    _service: superflow_schemas::service::BatchService,
    _node: Node<ipc::Service>,
}

impl std::fmt::Debug for BatchReceiver {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.debug_struct("BatchReceiver").finish_non_exhaustive()
    }
}

impl BatchReceiver {
    /// Opens (or creates) the run's batch and ready services and subscribes, with a
    /// receive queue of `buffer` batches.
    pub fn open(prefix: &str, run: &str, buffer: usize) -> anyhow::Result<Self> {
        use superflow_schemas::service as names;
        let iox = names::iceoryx2_config(Some(prefix))?;
        let name = names::batches_service(run)?;
        let node = NodeBuilder::new()
            .config(&iox)
            .create::<ipc::Service>()
            .map_err(|e| anyhow::anyhow!("iceoryx2 node: {e:?}"))?;
        let service = names::open_batch_service(&node, &name)?;
        let ready = names::open_ready_service(&node, &name)?;
        let listener = ready
            .listener_builder()
            .create()
            .map_err(|e| anyhow::anyhow!("{name}: listener: {e:?}"))?;
        let subscriber = service
            .subscriber_builder()
            .buffer_size(buffer)
            .create()
            .map_err(|e| anyhow::anyhow!("{name}: subscriber: {e:?}"))?;
        Ok(Self {
            subscriber,
            listener,
            _ready: ready,
            _service: service,
            _node: node,
        })
    }
}
