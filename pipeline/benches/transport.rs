//! Delivery over iceoryx2 shared memory versus a Unix socket, and the cost of fan-out.
//!
//! * publish→receive latency (median, p99) for payloads of 1 KiB to 256 MiB: iceoryx2
//!   (loaned slice, `send`, event wake-up, `receive` — the subscriber blocks on the
//!   event like a trainer does) against the same bytes written through a Unix stream
//!   socket and read into the receiver's buffer (one copy each way);
//! * producer time per batch (loan + write + send of a 32 MiB batch) with 1, 2 and 4
//!   subscribers.
//!
//! Subscribers are threads of this process, each with its own iceoryx2 node (the same
//! shared-memory path as separate processes). Clocks: one `Instant` base.
//!
//! `cargo bench -p superflow-pipeline --bench transport` (add `-- --quick` for fewer
//! repetitions).

use iceoryx2::prelude::*;
use std::io::{Read, Write};
use std::os::unix::net::UnixStream;
use std::sync::{Arc, Barrier};
use std::time::{Duration, Instant};

const KIB: usize = 1024;
const MIB: usize = 1024 * 1024;

fn percentile(sorted: &[f64], p: f64) -> f64 {
    sorted[((sorted.len() - 1) as f64 * p).round() as usize]
}

fn config(tag: &str) -> anyhow::Result<iceoryx2::config::Config> {
    superflow_schemas::service::iceoryx2_config(Some(&format!(
        "sfbench{}{tag}",
        std::process::id()
    )))
    .map_err(|e| anyhow::anyhow!(e))
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

/// iceoryx2 latencies (µs) of `reps` payloads of `size` bytes to `subscribers` threads;
/// also returns the producer's time per batch (ms) for loan + fill + send.
fn iceoryx2_run(
    size: usize,
    reps: usize,
    subscribers: usize,
    tag: &str,
) -> anyhow::Result<(Vec<f64>, f64)> {
    let cfg = config(tag)?;
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
        std::thread::sleep(Duration::from_micros(if size > 8 * MIB {
            2000
        } else {
            200
        }));
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
fn socket_run(size: usize, reps: usize) -> anyhow::Result<Vec<f64>> {
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
        std::thread::sleep(Duration::from_micros(if size > 8 * MIB {
            2000
        } else {
            200
        }));
    }
    receiver
        .join()
        .map_err(|_| anyhow::anyhow!("receiver panicked"))?
}

fn main() -> anyhow::Result<()> {
    let quick = std::env::args().any(|a| a == "--quick");
    let sizes = [KIB, 64 * KIB, MIB, 16 * MIB, 64 * MIB, 256 * MIB];
    let reps = |size: usize| {
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
    };
    println!("publish -> receive latency, one message in flight, 1 subscriber (µs)");
    println!("| payload | iceoryx2 median | iceoryx2 p99 | Unix socket median | Unix socket p99 |");
    println!("|---:|---:|---:|---:|---:|");
    for (k, &size) in sizes.iter().enumerate() {
        let n = reps(size);
        let (mut iox, _) = iceoryx2_run(size, n, 1, &format!("l{k}"))?;
        let mut sock = socket_run(size, n)?;
        iox.sort_by(f64::total_cmp);
        sock.sort_by(f64::total_cmp);
        let label = if size >= MIB {
            format!("{} MiB", size / MIB)
        } else {
            format!("{} KiB", size / KIB)
        };
        println!(
            "| {label} | {:.0} | {:.0} | {:.0} | {:.0} |",
            percentile(&iox, 0.5),
            percentile(&iox, 0.99),
            percentile(&sock, 0.5),
            percentile(&sock, 0.99)
        );
    }
    println!();
    println!("producer time per 32 MiB batch (loan + write every byte + send + notify)");
    println!("| subscribers | ms per batch | median latency µs |");
    println!("|---:|---:|---:|");
    for subscribers in [1usize, 2, 4] {
        let n = if quick { 10 } else { 40 };
        let (mut lat, producer_ms) =
            iceoryx2_run(32 * MIB, n, subscribers, &format!("f{subscribers}"))?;
        lat.sort_by(f64::total_cmp);
        println!(
            "| {subscribers} | {producer_ms:.2} | {:.0} |",
            percentile(&lat, 0.5)
        );
    }
    Ok(())
}
