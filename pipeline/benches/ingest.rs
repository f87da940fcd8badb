//! Ingest throughput on the sample drives: the index pass (one scan of the file:
//! decompression, stamps, transforms, calibrations) and random access to every sweep
//! (read + decode), as a table.
//!
//! `cargo bench -p superflow-pipeline --bench ingest` (add `-- --runs N`, default 5).

#[allow(dead_code)]
#[path = "../../tests/src/bench/common.rs"]
mod common;

use common::{DRIVES, arg_count, drive_path, median};
use std::time::Instant;
use superflow_pipeline::drive::{Drive, IngestConfig};
use superflow_pipeline::source::ChunkCache;

fn main() -> anyhow::Result<()> {
    let runs = arg_count("--runs")?.unwrap_or(5);
    println!("ingest throughput, median of {runs} runs, 1 thread");
    println!(
        "| drive | MB | index ms | index MB/s | sweeps | points | read+decode sweeps/s | decode Mpoints/s |"
    );
    println!("|---|---:|---:|---:|---:|---:|---:|---:|");
    for name in DRIVES {
        let path = drive_path(name);
        let bytes = std::fs::metadata(&path)?.len() as f64;
        let mut index_times = Vec::new();
        let mut drive = None;
        for _ in 0..runs {
            let started = Instant::now();
            drive = Some(Drive::open(
                std::slice::from_ref(&path),
                &IngestConfig::default(),
            )?);
            index_times.push(started.elapsed().as_secs_f64());
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
            decode_times.push(started.elapsed().as_secs_f64());
        }
        let index = median(&index_times);
        let decode = median(&decode_times);
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
