//! Ingest throughput on the sample drives: the index pass (one scan of the file:
//! decompression, stamps, transforms, calibrations) and random access to every sweep
//! (read + decode), as a table.
//!
//! `cargo bench -p superflow-pipeline --bench ingest` (add `-- --runs N`, default 5).

use std::path::PathBuf;
use std::time::{Duration, Instant};
use superflow_pipeline::drive::{Drive, IngestConfig};
use superflow_pipeline::source::ChunkCache;

fn median(mut v: Vec<Duration>) -> Duration {
    v.sort();
    v[v.len() / 2]
}

fn main() -> anyhow::Result<()> {
    let args: Vec<String> = std::env::args().collect();
    let runs = args
        .iter()
        .position(|a| a == "--runs")
        .and_then(|i| args.get(i + 1))
        .and_then(|r| r.parse().ok())
        .unwrap_or(5usize)
        .max(1);
    let root = PathBuf::from(env!("CARGO_MANIFEST_DIR")).join("..");
    println!("ingest throughput, median of {runs} runs, 1 thread");
    println!(
        "| drive | MB | index ms | index MB/s | sweeps | points | read+decode sweeps/s | decode Mpoints/s |"
    );
    println!("|---|---:|---:|---:|---:|---:|---:|---:|");
    for name in ["street_foxglove", "street_ros2"] {
        let path = root.join(format!("recordings/drives/{name}.mcap"));
        let bytes = std::fs::metadata(&path)?.len() as f64;
        let mut index_times = Vec::new();
        let mut drive = None;
        for _ in 0..runs {
            let started = Instant::now();
            drive = Some(Drive::open(
                std::slice::from_ref(&path),
                &IngestConfig::default(),
            )?);
            index_times.push(started.elapsed());
        }
        let drive = drive.ok_or_else(|| anyhow::anyhow!("no run"))?;
        let lidar = drive
            .lidar
            .as_ref()
            .ok_or_else(|| anyhow::anyhow!("{name}: no LiDAR"))?;
        let mut decode_times = Vec::new();
        let mut total_points = 0usize;
        for _ in 0..runs {
            let mut cache = ChunkCache::new(4);
            total_points = 0;
            let started = Instant::now();
            for sweep in &lidar.sweeps {
                let cloud = drive.read_sweep(sweep, &mut cache)?;
                total_points += cloud.cloud.len();
            }
            decode_times.push(started.elapsed());
        }
        let index = median(index_times).as_secs_f64();
        let decode = median(decode_times).as_secs_f64();
        println!(
            "| {name} | {:.1} | {:.1} | {:.0} | {} | {} | {:.0} | {:.1} |",
            bytes / 1e6,
            index * 1e3,
            bytes / 1e6 / index,
            lidar.sweeps.len(),
            total_points,
            lidar.sweeps.len() as f64 / decode,
            total_points as f64 / 1e6 / decode,
        );
    }
    Ok(())
}
