//! Ingest throughput on the sample drives: the index pass (one scan of the file:
//! decompression, stamps, transforms, calibrations) and random access to every sweep
//! (read + decode), as a table; then `Dataset::open` of 1, 10, 100 and 1 000 hard links
//! of a sample drive (with its sidecar): cold (no index cache) on 1 and 2 threads, files
//! being indexed in parallel, and warm (every file's index in the cache) on 2.
//!
//! `cargo bench -p superflow-pipeline --bench ingest` (add `-- --runs N`, default 5;
//! `-- --datasets-only` for the second table alone).

#[allow(dead_code)]
#[path = "../../tests/src/bench/common.rs"]
mod common;

use common::{DRIVES, arg_count, drive_path, flag, median};
use std::path::{Path, PathBuf};
use std::time::Instant;
use superflow_pipeline::drive::{Dataset, Drive, IngestConfig};
use superflow_pipeline::source::ChunkCache;

fn main() -> anyhow::Result<()> {
    let runs = arg_count("--runs")?.unwrap_or(5);
    if !flag("--datasets-only") {
        drives(runs)?;
    }
    datasets(runs)
}

/// Index and random-access throughput of each sample drive, on one thread.
fn drives(runs: usize) -> anyhow::Result<()> {
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

/// `Dataset::open` of many drives: 1, 10, 100 and 1 000 hard links of `street_ros2` and
/// its labels sidecar, cold on 1 and 2 threads and warm on 2.
fn datasets(runs: usize) -> anyhow::Result<()> {
    let dir = std::env::temp_dir().join(format!("superflow-ingest-bench-{}", std::process::id()));
    println!();
    println!(
        "Dataset::open of hard-linked street_ros2 drives (+ labels sidecar), median of {runs} runs"
    );
    println!(
        "| drives | files | MB | cold 1 thread ms | cold 2 threads ms | speed-up | warm 2 threads ms | cold / warm |"
    );
    println!("|---:|---:|---:|---:|---:|---:|---:|---:|");
    let cold = IngestConfig {
        index_cache: Some("off".into()),
        ..IngestConfig::default()
    };
    for count in [1usize, 10, 100, 1000] {
        let inputs = linked(&dir, count)?;
        let bytes: u64 = std::fs::read_dir(&inputs[0])?
            .map(|e| Ok(e?.metadata()?.len()))
            .sum::<std::io::Result<u64>>()?;
        // A fresh cache for each size: making links changes the files' status-change
        // time, which the fingerprint holds.
        let warm = IngestConfig {
            index_cache: Some(dir.join(format!("cache-{count}"))),
            ..IngestConfig::default()
        };
        Dataset::open(&inputs, &warm)?;
        let mut medians = Vec::new();
        for (threads, config) in [(1, &cold), (2, &cold), (2, &warm)] {
            let pool = rayon::ThreadPoolBuilder::new()
                .num_threads(threads)
                .build()?;
            let mut times = Vec::new();
            for _ in 0..runs {
                let started = Instant::now();
                let dataset = pool.install(|| Dataset::open(&inputs, config))?;
                times.push(started.elapsed().as_secs_f64());
                anyhow::ensure!(dataset.drives.len() == count, "{count} drives expected");
            }
            medians.push(median(&times));
        }
        let (one, two, warm) = (medians[0], medians[1], medians[2]);
        println!(
            "| {count} | {} | {:.1} | {:.0} | {:.0} | {:.2} | {:.0} | {:.0} |",
            2 * count,
            bytes as f64 / 1e6,
            one * 1e3,
            two * 1e3,
            one / two,
            warm * 1e3,
            two / warm,
        );
    }
    std::fs::remove_dir_all(&dir)?;
    Ok(())
}

/// A fresh directory of `count` hard links of `street_ros2` and its labels sidecar.
fn linked(dir: &Path, count: usize) -> anyhow::Result<Vec<PathBuf>> {
    let sub = dir.join(count.to_string());
    let _ = std::fs::remove_dir_all(&sub);
    std::fs::create_dir_all(&sub)?;
    let drive = drive_path("street_ros2");
    let sidecar = drive.with_extension("labels.mcap");
    for i in 0..count {
        std::fs::hard_link(&drive, sub.join(format!("d{i:04}.mcap")))?;
        std::fs::hard_link(&sidecar, sub.join(format!("d{i:04}.labels.mcap")))?;
    }
    Ok(vec![sub])
}
