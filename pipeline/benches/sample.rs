//! Sample-building throughput on the sample drives with the default recipe (3 frames,
//! 3 of 6 cameras, 224×448 images, 2 earlier sweeps, class-map or SLIC superpixels,
//! cylindrical voxels and 5 UNet levels of maps): samples/s on one core and on all
//! cores, and where the time goes (CPU time per sample by stage).
//!
//! `cargo bench -p superflow-pipeline --bench sample` (add `-- --samples N`, default 48).
//! The measurement is `tests/src/bench/sample.rs`, shared with the summary bench.

#[allow(dead_code)]
#[path = "../../tests/src/bench/common.rs"]
mod common;
#[path = "../../tests/src/bench/sample.rs"]
mod sample;

use common::{DRIVES, arg_count, cores, drive_path};
use superflow_pipeline::drive::{Dataset, IngestConfig};
use superflow_pipeline::sample::recipe::SuperpixelSource;
use superflow_pipeline::sample::{SampleBuilder, SampleConfig};

/// The pipeline binary's allocator (see `superflow_pipeline::memory`).
#[global_allocator]
static ALLOCATOR: superflow_common::memory::Allocator = superflow_common::memory::Allocator;

fn main() -> anyhow::Result<()> {
    superflow_common::memory::keep_freed_pages();
    superflow_common::memory::small_pages_only();
    let n = arg_count("--samples")?.unwrap_or(48);
    let cores = cores();
    println!(
        "sample building, default recipe, {} rounds of {n} samples on 1 core then {cores}",
        sample::ROUNDS
    );
    println!(
        "| drive | superpixels | samples/s 1 core | samples/s {cores} cores | scaling | decode ms | sweeps ms | images ms | projection ms | superpixels ms | voxels+maps ms |"
    );
    println!("|---|---|---:|---:|---:|---:|---:|---:|---:|---:|---:|");
    for name in DRIVES {
        let path = drive_path(name);
        let dataset = Dataset::open(std::slice::from_ref(&path), &IngestConfig::default())?;
        for source in [SuperpixelSource::Channel, SuperpixelSource::Slic] {
            let config = SampleConfig {
                superpixels: source,
                ..SampleConfig::default()
            };
            let builder = SampleBuilder::new(&dataset, config)?;
            let run = sample::one_and_all(&builder, n, cores)?;
            let (one, all) = (run.one, run.all);
            println!(
                "| {name} | {} | {one:.1} | {all:.1} | {:.2}× | {} |",
                match source {
                    SuperpixelSource::Slic => "SLIC",
                    _ => "class map",
                },
                run.scaling,
                sample::stage_cells(&run.times, n * sample::ROUNDS),
            );
        }
    }
    println!("stage columns: CPU time per sample on 1 core");
    Ok(())
}
