//! `index`: the drives indexed into the index cache ahead of training (with each drive's
//! camera scan, which the plan measures), with a summary: `seconds` is the opening of
//! the dataset, `plan seconds` the plan.

use crate::cli::Args;
use anyhow::Context as _;
use std::time::Instant;
use superflow_pipeline::drive::{IngestConfig, index_cache};
use superflow_pipeline::fleet::{FleetReport, keyframes_per_drive, lidar_facts_of};
use superflow_pipeline::sample::plan::Plan;
use superflow_pipeline::sample::timing::SCAN_ENTRY;

pub fn run(args: &Args, prune: bool) -> anyhow::Result<()> {
    let config = args.config()?;
    if prune && args.mcap.is_empty() && args.dataset.is_empty() && config.dataset.is_empty() {
        return tidy(&config.ingest);
    }
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
        cache
            .as_ref()
            .map_or_else(|| "off".to_string(), |c| c.dir().display().to_string())
    );
    println!(
        "seconds         {seconds:.3} ({:.2} GB scanned)",
        stats.bytes_scanned as f64 * 1e-9
    );
    println!(
        "plan seconds    {plan_seconds:.3} (camera scans: {} from the cache, {} measured, {} at the sweep stamp)",
        scans.from_cache, scans.measured, scans.at_stamp
    );
    if prune {
        tidy(&config.ingest)?;
    } else if let Some(cache) = &cache {
        cache.upkeep_if_grown(); // the camera scans the plan stored
    }
    let (failed, _) = index_cache::stores();
    if failed > 0 {
        anyhow::bail!(
            "{failed} index cache entries could not be stored in {} (see the warning above): \
             the next start indexes those files again",
            cache.map_or_else(String::new, |c| c.dir().display().to_string())
        );
    }
    Ok(())
}

/// `--prune`: the cache's upkeep, removing what this build cannot use.
fn tidy(ingest: &IngestConfig) -> anyhow::Result<()> {
    let Some(cache) = ingest.index_cache() else {
        anyhow::bail!("--prune: the index cache is off");
    };
    cache.prepare()?;
    let done = cache
        .upkeep(Some(&[&index_cache::FILE_INDEX, &SCAN_ENTRY]))
        .with_context(|| format!("pruning the index cache {}", cache.dir().display()))?;
    println!(
        "pruned          {} unusable entries, {} evicted (bound {} MB), {} stale temporary files",
        done.unusable_removed,
        done.evicted,
        cache.access().max_bytes >> 20,
        done.temps_removed
    );
    println!(
        "cache left      {} entries, {:.1} MB",
        done.entries,
        done.bytes as f64 / f64::from(1 << 20)
    );
    Ok(())
}
