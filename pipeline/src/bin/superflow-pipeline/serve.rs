//! The service (no subcommand): batches streamed over iceoryx2 until the epochs are done
//! or a signal stops it, with Prometheus metrics on `--metrics-addr`.

use crate::cli::Args;
use anyhow::Context as _;
use std::sync::Arc;
use std::sync::atomic::{AtomicBool, Ordering};
use superflow_pipeline::fleet::{FleetReport, keyframes_per_drive, lidar_facts_of};
use superflow_pipeline::publish::Metrics;
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
    let builder = SampleBuilder::new(&dataset, config.sample.clone())?;
    tracing::info!(
        keyframes = builder.plan().keyframes.len(),
        samples_per_epoch = builder.epoch_len(),
        skipped_at_edges = builder.plan().skipped_at_edges,
        "plan"
    );
    FleetReport::new(
        &dataset,
        &keyframes_per_drive(builder.plan(), dataset.drives.len()),
        &lidar_facts_of(builder.plan()),
    )
    .log();
    let stop = Arc::new(AtomicBool::new(false));
    let runtime = tokio::runtime::Builder::new_multi_thread()
        .worker_threads(1)
        .enable_all()
        .build()?;
    // Signals and the metrics endpoint run on tokio; building and publishing on their
    // own threads (rayon, and this one).
    // Handlers are installed before anything is published, so a signal never takes
    // the default action (which would leave shared memory behind).
    let (int, term) = runtime.block_on(async {
        use tokio::signal::unix::{SignalKind, signal};
        (
            signal(SignalKind::interrupt()),
            signal(SignalKind::terminate()),
        )
    });
    let (int, term) = (
        int.context("installing the SIGINT handler")?,
        term.context("installing the SIGTERM handler")?,
    );
    runtime.spawn(wait_for_signals(int, term, stop.clone()));
    if let Some(addr) = args.metrics_addr {
        let listener = runtime
            .block_on(tokio::net::TcpListener::bind(addr))
            .with_context(|| format!("binding the metrics address {addr}"))?;
        tracing::info!(%addr, "metrics at http://{addr}/metrics");
        runtime.spawn(serve_metrics(listener, metrics.clone()));
    }
    let result = superflow_pipeline::publish::serve(
        &builder,
        &args.run,
        &config.service,
        &iox,
        args.start(),
        &stop,
        &metrics,
    );
    runtime.shutdown_timeout(std::time::Duration::from_millis(100));
    Ok(result?)
}

async fn wait_for_signals(
    mut int: tokio::signal::unix::Signal,
    mut term: tokio::signal::unix::Signal,
    stop: Arc<AtomicBool>,
) {
    let name = tokio::select! {
        _ = int.recv() => "SIGINT",
        _ = term.recv() => "SIGTERM",
    };
    // Stop first: logging can fail (a closed stderr) and must not keep us running.
    stop.store(true, Ordering::SeqCst);
    tracing::info!("{name}: finishing the batch in flight, releasing shared memory");
}

async fn serve_metrics(listener: tokio::net::TcpListener, metrics: Arc<Metrics>) {
    use tokio::io::{AsyncReadExt, AsyncWriteExt};
    loop {
        let Ok((mut socket, _)) = listener.accept().await else {
            continue;
        };
        let metrics = metrics.clone();
        tokio::spawn(async move {
            let mut request = [0u8; 1024];
            let _ = socket.read(&mut request).await;
            let body = metrics.prometheus();
            let response = format!(
                "HTTP/1.1 200 OK\r\nContent-Type: text/plain; version=0.0.4\r\nContent-Length: {}\r\nConnection: close\r\n\r\n{body}",
                body.len()
            );
            let _ = socket.write_all(response.as_bytes()).await;
        });
    }
}
