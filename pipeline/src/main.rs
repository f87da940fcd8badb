//! `superflow-pipeline`: the producer process.
//!
//! * `superflow-pipeline --mcap <drives>... [--run NAME] [--config pipeline.toml]` — the
//!   service: streams SuperFlow batches over iceoryx2 (broadcast or shard), with
//!   backpressure, dead-subscriber cleanup, resume requests and Prometheus metrics.
//! * `superflow-pipeline inspect --mcap <drives>... [--json]` — what the drives hold.
//! * `superflow-pipeline sample --mcap <drive> --index K --out DIR [--no-augment]` — one
//!   sample written as `.npy` arrays, `sample.json` and overlay PNGs.

use anyhow::{Context as _, bail};
use clap::{Parser, Subcommand};
use std::path::PathBuf;
use std::sync::Arc;
use std::sync::atomic::{AtomicBool, Ordering};
use superflow_pipeline::config::PipelineConfig;
use superflow_pipeline::drive::Dataset;
use superflow_pipeline::inspect::InspectReport;
use superflow_pipeline::publish::{Metrics, Mode};
use superflow_pipeline::sample::SampleBuilder;

/// mimalloc, keeping freed pages for the next sample (see `superflow_pipeline::memory`).
#[global_allocator]
static ALLOCATOR: superflow_pipeline::memory::Allocator = superflow_pipeline::memory::Allocator;
use superflow_pipeline::sample::export::write_sample;

/// Streams SuperFlow training batches from recorded drives to trainers over shared memory.
#[derive(Debug, Parser)]
#[command(version, about)]
struct Args {
    /// MCAP files or directories of them (searched for `*.mcap`).
    #[arg(long, num_args = 1.., global = true)]
    mcap: Vec<PathBuf>,
    /// Configuration file (TOML); defaults are the paper's.
    #[arg(long, global = true)]
    config: Option<PathBuf>,
    /// Run name: the services are `superflow/<run>/...`.
    #[arg(long, default_value = "default")]
    run: String,
    /// Stream mode (overrides `[service] mode`): `broadcast` or `shard`.
    #[arg(long)]
    mode: Option<String>,
    /// Ranks in shard mode (overrides `[service] world_size`).
    #[arg(long)]
    world_size: Option<u32>,
    /// This host's rank for multi-host sharding (overrides `[service] host_rank`):
    /// host h of N gets a disjoint share of every epoch's keyframes.
    #[arg(long, env = "SUPERFLOW_HOST_RANK")]
    host_rank: Option<u32>,
    /// Hosts sharing each epoch, each running its own pipeline on the same drives and
    /// configuration (overrides `[service] host_count`).
    #[arg(long, env = "SUPERFLOW_HOST_COUNT")]
    host_count: Option<u32>,
    /// Samples per batch (overrides `[service] batch_size`).
    #[arg(long)]
    batch_size: Option<u32>,
    /// Epochs to stream, 0 = forever (overrides `[service] epochs`).
    #[arg(long)]
    epochs: Option<u64>,
    /// Subscribers to wait for before the first batch of each stream (overrides
    /// `[service] min_subscribers`).
    #[arg(long)]
    subscribers: Option<u32>,
    /// Start at this epoch ...
    #[arg(long, default_value_t = 0)]
    start_epoch: u64,
    /// ... and this step of it (nothing before it is built).
    #[arg(long, default_value_t = 0)]
    start_step: u64,
    /// Serve Prometheus text metrics on this address (e.g. 127.0.0.1:9464).
    #[arg(long)]
    metrics_addr: Option<std::net::SocketAddr>,
    /// Isolates this deployment's iceoryx2 resources (also `SUPERFLOW_IOX_PREFIX`).
    #[arg(long, env = "SUPERFLOW_IOX_PREFIX")]
    iox_prefix: Option<String>,
    #[command(subcommand)]
    command: Option<Command>,
}

#[derive(Debug, Subcommand)]
enum Command {
    /// Lists what the drives hold: dialect, channels and roles, cameras, frame tree,
    /// time span, usable keyframes, per-point labels (`[labels]` of the configuration)
    /// and skipped messages.
    Inspect {
        /// Print the stable JSON report (`superflow.inspect/1`) instead of text.
        #[arg(long)]
        json: bool,
    },
    /// Builds one sample and writes it as `.npy` arrays, `sample.json` and PNGs of each
    /// chosen image with the projected points coloured by depth and by superpixel.
    Sample {
        /// Keyframe number in the plan (drive and time order; `inspect` counts them).
        #[arg(long, default_value_t = 0)]
        index: usize,
        /// Epoch of the random draws (cameras, flips, augmentation).
        #[arg(long, default_value_t = 0)]
        epoch: u64,
        /// Output directory.
        #[arg(long)]
        out: PathBuf,
        /// Keep points in their LiDAR frame (no 3D augmentation).
        #[arg(long)]
        no_augment: bool,
    },
    /// Runs SLIC once on every camera image of each drive, with the configuration's
    /// recipe, and writes the labels to `<drive>.slic.mcap` beside it; samples then
    /// read them instead of running SLIC per image and epoch (drives with class maps
    /// do not need this).
    Superpixels {
        /// Rewrite a sidecar that exists (else one written with the same settings is
        /// kept, and one with other settings is an error).
        #[arg(long)]
        force: bool,
    },
    /// Builds one batch (keyframes `index..index + batch-size` of the plan) and writes it
    /// to a file exactly as it goes on the wire: the `BatchHeader` bytes, then the
    /// payload (`schemas/BATCH_FORMAT.md`). Benchmarks and offline tools read it.
    Batch {
        /// First keyframe of the batch.
        #[arg(long, default_value_t = 0)]
        index: usize,
        /// Samples in the batch [default: the service's batch size].
        #[arg(long)]
        batch_size: Option<usize>,
        /// Epoch of the random draws.
        #[arg(long, default_value_t = 0)]
        epoch: u64,
        /// Output file.
        #[arg(long)]
        out: PathBuf,
    },
}

fn load_config(args: &Args) -> anyhow::Result<PipelineConfig> {
    Ok(match &args.config {
        Some(path) => PipelineConfig::load(path)?,
        None => PipelineConfig::default(),
    })
}

fn open(args: &Args) -> anyhow::Result<Dataset> {
    if args.mcap.is_empty() {
        bail!("no input: pass --mcap <file or directory>...");
    }
    let config = load_config(args)?;
    let bar = indicatif::ProgressBar::new(0).with_style(
        indicatif::ProgressStyle::with_template(
            "indexing {bar:40} {bytes}/{total_bytes} ({bytes_per_sec})",
        )
        .unwrap_or_else(|_| indicatif::ProgressStyle::default_bar()),
    );
    let dataset = Dataset::open_with_progress(&args.mcap, &config.ingest, |done, total| {
        bar.set_length(total);
        bar.set_position(done);
    });
    bar.finish_and_clear();
    Ok(dataset?)
}

/// The `superpixels` command: a SLIC sidecar for every drive that lacks a current one.
fn write_slic_sidecars(
    dataset: &Dataset,
    config: &superflow_pipeline::sample::SampleConfig,
    force: bool,
) -> anyhow::Result<()> {
    use superflow_pipeline::sample::recipe::SuperpixelSource;
    use superflow_pipeline::sample::sidecar;
    for drive in &dataset.drives {
        let path = sidecar::sidecar_path(drive)
            .with_context(|| format!("{}: no file to put a sidecar beside", drive.file_list()))?;
        if path.exists() && !force {
            if sidecar::sidecar_matches(drive, config) {
                println!("{}: up to date", path.display());
                continue;
            }
            bail!(
                "{} exists with other settings (or other cameras); rerun with --force to rewrite it",
                path.display()
            );
        }
        let has_class_maps = drive.cameras.iter().all(|c| !c.superpixels.is_empty());
        if has_class_maps && config.superpixels != SuperpixelSource::Slic {
            println!(
                "{}: note: every camera has class maps, which samples use under superpixels = {}; \
                 the SLIC sidecar serves superpixels = \"slic\"",
                drive.file_list(),
                serde_json::to_string(&config.superpixels)?
            );
        }
        let images: usize = drive.cameras.iter().map(|c| c.frames.len()).sum();
        let bar = indicatif::ProgressBar::new(images as u64).with_style(
            indicatif::ProgressStyle::with_template(
                "SLIC {bar:40} {pos}/{len} images ({per_sec}, {eta} left)",
            )
            .unwrap_or_else(|_| indicatif::ProgressStyle::default_bar()),
        );
        let started = std::time::Instant::now();
        let summary = sidecar::write_sidecar(drive, config, &path, &|| bar.inc(1))?;
        bar.finish_and_clear();
        let secs = started.elapsed().as_secs_f64();
        println!(
            "{}: {} label maps ({:.1} MB) in {secs:.1} s ({:.1} ms an image)",
            summary.path.display(),
            summary.images,
            summary.bytes as f64 / 1e6,
            1e3 * secs / summary.images.max(1) as f64
        );
        if let Some(first) = summary.skipped.first() {
            println!(
                "  {} images skipped (they do not decode; a sample that needs one fails as it \
                 would without the sidecar); first: {first}",
                summary.skipped.len()
            );
        }
    }
    Ok(())
}

fn run(args: &Args) -> anyhow::Result<()> {
    match &args.command {
        Some(Command::Inspect { json }) => {
            let labels = load_config(args)?.labels;
            let dataset = open(args)?;
            let report = InspectReport::with_labels(&dataset, &labels);
            if *json {
                println!("{}", serde_json::to_string_pretty(&report)?);
            } else {
                print!("{}", report.to_text());
            }
            Ok(())
        }
        Some(Command::Superpixels { force }) => {
            let config = load_config(args)?.sample;
            let dataset = open(args)?;
            write_slic_sidecars(&dataset, &config, *force)
        }
        Some(Command::Sample {
            index,
            epoch,
            out,
            no_augment,
        }) => {
            let mut config = load_config(args)?.sample;
            if *no_augment {
                config.augment.enabled = false;
            }
            let dataset = open(args)?;
            let builder = SampleBuilder::new(&dataset, config)?;
            let plan = builder.plan();
            let key = plan.keyframes.get(*index).with_context(|| {
                format!(
                    "keyframe {index} requested; the drives have {} keyframes (0..{})",
                    plan.keyframes.len(),
                    plan.keyframes.len()
                )
            })?;
            let files = dataset.drives[key.drive as usize].file_list();
            let sample = {
                let _span = tracing::info_span!("build sample", keyframe = index).entered();
                builder.build_keyframe(*index, *epoch, *index as u64)?
            };
            let written = write_sample(&sample, builder.config(), &files, out)?;
            let frame = &sample.frames[sample.key_frame];
            tracing::info!(
                keyframe = index,
                sweep = key.sweep,
                cameras = %sample.cameras.join(","),
                points = frame.cloud.xyz.len(),
                pairings = frame.cloud.pairings.len(),
                dense_points = sample.dense.xyz.len(),
                voxels = frame.cloud.voxels.coords.len(),
                "sample built"
            );
            println!("wrote {} files to {}", written.len(), out.display());
            Ok(())
        }
        Some(Command::Batch {
            index,
            batch_size,
            epoch,
            out,
        }) => write_batch_file(args, *index, *batch_size, *epoch, out),
        None => serve(args),
    }
}

fn write_batch_file(
    args: &Args,
    index: usize,
    batch_size: Option<usize>,
    epoch: u64,
    out: &std::path::Path,
) -> anyhow::Result<()> {
    use superflow_pipeline::batch::{BatchShape, batch_bytes};
    use superflow_schemas::batch::BatchMeta;
    let config = load_config(args)?;
    let size = batch_size
        .unwrap_or(config.service.batch_size as usize)
        .max(1);
    let dataset = open(args)?;
    let builder = SampleBuilder::new(&dataset, config.sample)?;
    let keyframes = builder.plan().keyframes.len();
    if index + size > keyframes {
        bail!(
            "keyframes {index}..{} requested; the drives have {keyframes}",
            index + size
        );
    }
    let samples = (index..index + size)
        .map(|k| builder.build_keyframe(k, epoch, k as u64))
        .collect::<Result<Vec<_>, _>>()?;
    let c = builder.config();
    let meta = BatchMeta {
        run: args.run.clone(),
        epoch,
        step: 0,
        seed: c.seed,
        sequence: 0,
        created_unix_nanos: 0,
        sample_count: size as u32,
        flags: 0,
    };
    let bytes = batch_bytes(&samples, BatchShape::of(c), &meta)?;
    std::fs::write(out, &bytes).with_context(|| format!("writing {}", out.display()))?;
    println!(
        "wrote a batch of {size} samples ({} bytes) to {}",
        bytes.len(),
        out.display()
    );
    Ok(())
}

fn serve(args: &Args) -> anyhow::Result<()> {
    let mut config = load_config(args)?;
    if let Some(mode) = &args.mode {
        config.service.mode = match mode.as_str() {
            "broadcast" => Mode::Broadcast,
            "shard" => Mode::Shard,
            other => bail!("--mode {other}: expected broadcast or shard"),
        };
    }
    if let Some(w) = args.world_size {
        config.service.world_size = w;
        if w > 1 && args.mode.is_none() {
            config.service.mode = Mode::Shard;
        }
    }
    if let Some(b) = args.batch_size {
        config.service.batch_size = b;
    }
    if let Some(h) = args.host_rank {
        config.service.host_rank = h;
    }
    if let Some(n) = args.host_count {
        config.service.host_count = n;
    }
    if let Some(e) = args.epochs {
        config.service.epochs = e;
    }
    if let Some(n) = args.subscribers {
        config.service.min_subscribers = n;
    }
    config.service.validate()?;
    superflow_schemas::service::batches_service(&args.run)?;
    let iox = superflow_schemas::service::iceoryx2_config(args.iox_prefix.as_deref())?;
    let dataset = open(args)?;
    dataset
        .check_sensors()
        .context("the drives cannot be trained on")?;
    let metrics = Arc::new(Metrics::default());
    for drive in InspectReport::new(&dataset).drives {
        metrics
            .skipped_messages
            .fetch_add(drive.skipped.total(), Ordering::Relaxed);
        tracing::info!(
            files = drive.files.len(),
            sweeps = drive.lidar_sweeps,
            cameras = drive.cameras.len(),
            skipped = drive.skipped.total(),
            "drive indexed"
        );
    }
    let builder = SampleBuilder::new(&dataset, config.sample.clone())?;
    tracing::info!(
        keyframes = builder.plan().keyframes.len(),
        skipped_at_edges = builder.plan().skipped_at_edges,
        "plan"
    );
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
        (args.start_epoch, args.start_step),
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

fn main() -> std::process::ExitCode {
    superflow_pipeline::memory::keep_freed_pages();
    tracing_subscriber::fmt()
        .with_writer(std::io::stderr)
        // Colour only on a terminal: logs redirected to files stay plain text.
        .with_ansi(std::io::IsTerminal::is_terminal(&std::io::stderr()))
        .with_env_filter(
            tracing_subscriber::EnvFilter::try_from_default_env().unwrap_or_else(|_| "info".into()),
        )
        .init();
    match run(&Args::parse()) {
        Ok(()) => std::process::ExitCode::SUCCESS,
        Err(err) => {
            eprintln!("superflow-pipeline: {err:#}");
            std::process::ExitCode::from(2)
        }
    }
}
