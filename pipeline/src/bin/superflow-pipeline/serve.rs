//! The service (no subcommand): batches streamed over iceoryx2 until the epochs are done
//! or a signal stops it, with Prometheus metrics on `--metrics-addr`.

use crate::cli::Args;
use anyhow::Context as _;
use std::sync::Arc;
use std::sync::atomic::{AtomicBool, Ordering};
use superflow_pipeline::fleet::{FleetReport, keyframes_per_drive, lidar_facts_of};
use superflow_pipeline::publish::{Metrics, SideTasks};
use superflow_pipeline::sample::SampleBuilder;

pub fn run(args: &Args) -> anyhow::Result<()> {
    let mut config = args.config()?;
    config.apply(&args.overrides()?);
    config.service.validate()?;
    superflow_schemas::service::batches_service(&args.run)?;
    let iox = superflow_schemas::service::iceoryx2_config(args.iox_prefix.as_deref())?;
    let dataset = crate::open::dataset(args)?;
    dataset
        .check_sensors()
        .context("the drives cannot be trained on")?;
    let metrics = Arc::new(Metrics::default());
    // Only what indexing already knows: a full report per drive would measure every
    // drive's camera timing again before the plan does.
    for drive in &dataset.drives {
        metrics
            .skipped_messages
            .fetch_add(drive.skipped.total(), Ordering::Relaxed);
        tracing::debug!(
            files = drive.files.len(),
            sweeps = drive.lidar.as_ref().map_or(0, |l| l.sweeps.len()),
            cameras = drive.cameras.len(),
            skipped = drive.skipped.total(),
            "drive indexed"
        );
    }
    let builder = SampleBuilder::new(&dataset, config.sample.clone())?
        .with_order(config.service.epoch_order())
        .keep_frames_for(config.service.positions_in_flight());
    tracing::info!(
        keyframes = builder.plan().keyframes.len(),
        samples_per_epoch = builder.epoch_len(),
        skipped_at_edges = builder.plan().skipped_at_edges,
        order = ?builder.mix().order,
        "plan"
    );
    FleetReport::new(
        &dataset,
        &keyframes_per_drive(builder.plan(), dataset.drives.len()),
        &lidar_facts_of(builder.plan()),
    )
    .log();
    let stop = Arc::new(AtomicBool::new(false));
    let side_tasks = SideTasks::start(stop.clone(), metrics.clone(), args.metrics_addr)?;
    let result = superflow_pipeline::publish::serve(
        &builder,
        &args.run,
        &config.service,
        &iox,
        args.start(),
        &stop,
        &metrics,
    );
    side_tasks.shutdown();
    Ok(result?)
}
