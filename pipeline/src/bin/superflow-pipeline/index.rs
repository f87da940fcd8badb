//! `index`: the drives indexed into the index cache ahead of training (with each drive's
//! camera scan, which the plan measures), with a summary: `seconds` is the opening of
//! the dataset, `plan seconds` the plan.

use crate::cli::Args;
use std::time::Instant;
use superflow_pipeline::fleet::{FleetReport, keyframes_per_drive, lidar_facts_of};
use superflow_pipeline::sample::plan::Plan;

pub fn run(args: &Args) -> anyhow::Result<()> {
    let config = args.config()?;
    let started = Instant::now();
    let dataset = crate::open::dataset(args)?;
    let seconds = started.elapsed().as_secs_f64();
    let planned = Instant::now();
    let (plan, scans) = Plan::with_counts(&dataset, &config.sample);
    let plan_seconds = planned.elapsed().as_secs_f64();
    let files: usize = dataset.drives.iter().map(|d| d.files.len()).sum();
    let damaged = dataset
        .drives
        .iter()
        .flat_map(|d| &d.files)
        .filter(|f| !f.damage.is_empty())
        .count();
    let skipped: u64 = dataset.drives.iter().map(|d| d.skipped.total()).sum();
    let unusable: Vec<String> = dataset
        .drives
        .iter()
        .filter_map(|d| d.check_sensors().err().map(|e| e.to_string()))
        .collect();
    for problem in &unusable {
        tracing::warn!("not trainable: {problem}");
    }
    let stats = dataset.indexed;
    let cache = config.ingest.index_cache();
    println!("drives          {}", dataset.drives.len());
    println!(
        "files           {files} ({:.2} GB)",
        dataset
            .drives
            .iter()
            .flat_map(|d| &d.files)
            .map(|f| f.len() as f64)
            .sum::<f64>()
            * 1e-9
    );
    println!("keyframes       {}", plan.keyframes.len());
    let fleet = FleetReport::new(
        &dataset,
        &keyframes_per_drive(&plan, dataset.drives.len()),
        &lidar_facts_of(&plan),
    );
    println!("samples/epoch   {}", fleet.samples_per_epoch);
    for line in fleet.lines() {
        println!("  {line}");
    }
    println!("not trainable   {} drives", unusable.len());
    println!("skipped         {skipped} messages");
    println!("damaged         {damaged} files");
    println!(
        "cache hits      {} of {files}{}",
        stats.from_cache,
        match stats.uncacheable {
            0 => String::new(),
            n => format!(" ({n} without a summary: indexed at every start)"),
        }
    );
    println!(
        "index cache     {}",
        cache.map_or_else(|| "off".to_string(), |c| c.dir().display().to_string())
    );
    println!(
        "seconds         {seconds:.3} ({:.2} GB scanned)",
        stats.bytes_scanned as f64 * 1e-9
    );
    println!(
        "plan seconds    {plan_seconds:.3} (camera scans: {} from the cache, {} measured, {} at the sweep stamp)",
        scans.from_cache, scans.measured, scans.at_stamp
    );
    Ok(())
}
