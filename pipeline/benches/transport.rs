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
//! repetitions). The measurement is `tests/src/bench/transport.rs`, shared with the
//! summary bench.

#[allow(dead_code)]
#[path = "../../tests/src/bench/common.rs"]
mod common;
#[allow(dead_code)]
#[path = "../../tests/src/bench/transport.rs"]
mod transport;

use common::{flag, percentile};
use transport::{
    KIB, MIB, fanout_reps, iceoryx2_run, latency_reps, release_shared_memory, size_label,
    socket_run,
};

fn main() -> anyhow::Result<()> {
    let quick = flag("--quick");
    let sizes = [KIB, 64 * KIB, MIB, 16 * MIB, 64 * MIB, 256 * MIB];
    println!("publish -> receive latency, one message in flight, 1 subscriber (µs)");
    println!("| payload | iceoryx2 median | iceoryx2 p99 | Unix socket median | Unix socket p99 |");
    println!("|---:|---:|---:|---:|---:|");
    for (k, &size) in sizes.iter().enumerate() {
        let n = latency_reps(size, quick);
        let (mut iox, _) = iceoryx2_run(size, n, 1, &format!("l{k}"))?;
        let mut sock = socket_run(size, n)?;
        iox.sort_by(f64::total_cmp);
        sock.sort_by(f64::total_cmp);
        let label = size_label(size);
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
        let (mut lat, producer_ms) = iceoryx2_run(
            32 * MIB,
            fanout_reps(quick),
            subscribers,
            &format!("f{subscribers}"),
        )?;
        lat.sort_by(f64::total_cmp);
        println!(
            "| {subscribers} | {producer_ms:.2} | {:.0} |",
            percentile(&lat, 0.5)
        );
    }
    let left = release_shared_memory();
    anyhow::ensure!(left.is_empty(), "left in /dev/shm: {left:?}");
    Ok(())
}
