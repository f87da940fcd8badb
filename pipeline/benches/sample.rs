//! Sample-building throughput on the sample drives with the default recipe (3 frames,
//! 3 of 6 cameras, 224×448 images, 2 earlier sweeps, class-map or SLIC superpixels,
//! cylindrical voxels and 5 UNet levels of maps): samples/s on one core and on all
//! cores, and where the time goes (CPU time per sample by stage).
//!
//! `cargo bench -p superflow-pipeline --bench sample` (add `-- --samples N`, default 48).

use rayon::prelude::*;
use std::path::PathBuf;
use std::time::Instant;
use superflow_pipeline::drive::{Dataset, IngestConfig};
use superflow_pipeline::sample::builder::StageTimes;
use superflow_pipeline::sample::recipe::SuperpixelSource;
use superflow_pipeline::sample::{SampleBuilder, SampleConfig};

fn arg(name: &str, default: usize) -> usize {
    let args: Vec<String> = std::env::args().collect();
    args.iter()
        .position(|a| a == name)
        .and_then(|i| args.get(i + 1))
        .and_then(|r| r.parse().ok())
        .unwrap_or(default)
        .max(1)
}

/// Builds `n` samples (epoch-major over the plan) on `threads` threads; returns
/// samples/s and the summed stage times.
fn run(builder: &SampleBuilder<'_>, n: usize, threads: usize) -> anyhow::Result<(f64, StageTimes)> {
    let pool = rayon::ThreadPoolBuilder::new()
        .num_threads(threads)
        .build()?;
    let per_epoch = builder.plan().keyframes.len();
    let started = Instant::now();
    let times = pool.install(|| {
        (0..n)
            .into_par_iter()
            .map(|i| {
                builder
                    .build((i / per_epoch) as u64, (i % per_epoch) as u64)
                    .map(|s| s.times)
            })
            .collect::<Result<Vec<_>, _>>()
    })?;
    let secs = started.elapsed().as_secs_f64();
    let mut total = StageTimes::default();
    for t in &times {
        total.add(t);
    }
    Ok((n as f64 / secs, total))
}

fn main() -> anyhow::Result<()> {
    let n = arg("--samples", 48);
    let cores = std::thread::available_parallelism().map_or(1, |c| c.get());
    let root = PathBuf::from(env!("CARGO_MANIFEST_DIR")).join("..");
    println!("sample building, default recipe, {n} samples per run, {cores} cores");
    println!(
        "| drive | superpixels | samples/s 1 core | samples/s {cores} cores | decode ms | sweeps ms | images ms | projection ms | superpixels ms | voxels+maps ms |"
    );
    println!("|---|---|---:|---:|---:|---:|---:|---:|---:|---:|");
    for name in ["street_foxglove", "street_ros2"] {
        let path = root.join(format!("recordings/drives/{name}.mcap"));
        let dataset = Dataset::open(std::slice::from_ref(&path), &IngestConfig::default())?;
        for source in [SuperpixelSource::Channel, SuperpixelSource::Slic] {
            let config = SampleConfig {
                superpixels: source,
                ..SampleConfig::default()
            };
            let builder = SampleBuilder::new(&dataset, config)?;
            // Warm-up: page cache and allocator.
            run(&builder, builder.plan().keyframes.len(), cores)?;
            let (one, times) = run(&builder, n, 1)?;
            let (all, _) = run(&builder, n, cores)?;
            let ms = |ns: u64| ns as f64 / 1e6 / n as f64;
            println!(
                "| {name} | {} | {one:.1} | {all:.1} | {:.1} | {:.1} | {:.1} | {:.1} | {:.1} | {:.1} |",
                match source {
                    SuperpixelSource::Slic => "SLIC",
                    _ => "class map",
                },
                ms(times.decode),
                ms(times.sweeps),
                ms(times.images),
                ms(times.projection),
                ms(times.superpixels),
                ms(times.voxels),
            );
        }
    }
    println!("stage columns: CPU time per sample on 1 core");
    Ok(())
}
