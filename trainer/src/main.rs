//! `superflow-trainer`: subscribes to a run's batches and trains the 3D network with the
//! SuperFlow losses (burn). See the crate README section in the workspace README.

use anyhow::Context as _;
use clap::Parser;
use indicatif::{ProgressBar, ProgressStyle};
use std::path::PathBuf;
use std::sync::Arc;
use std::sync::atomic::{AtomicI32, Ordering};
use std::time::{Duration, Instant};
use superflow_trainer::config::TrainerConfig;
use superflow_trainer::metrics::{self, MetricsWriter, StepRecord};
use superflow_trainer::sparse::UNetPreset;
use superflow_trainer::subscribe::{Received, Subscription, Target};
use superflow_trainer::train::Trainer;
use superflow_trainer::vit::VitPreset;

/// Trains a 3D network on SuperFlow batches received over shared memory.
#[derive(Debug, Parser)]
#[command(version, about)]
struct Args {
    /// Run name of the pipeline to subscribe to.
    #[arg(long, default_value = "default")]
    run: String,
    /// Data-parallel rank (shard mode) ...
    #[arg(long)]
    rank: Option<u32>,
    /// ... out of this many ranks.
    #[arg(long)]
    world_size: Option<u32>,
    /// trainer.toml (networks, losses, optimizer, checkpoints); flags override it.
    #[arg(long)]
    config: Option<PathBuf>,
    /// Optimizer steps of the run (also the one-cycle schedule's length) [default: the
    /// config's `optim.steps`].
    #[arg(long)]
    steps: Option<u64>,
    /// 3D network: minkunet34, minkunet18, tiny.
    #[arg(long)]
    unet: Option<UNetPreset>,
    /// 2D network size without weights: tiny, small, base, large.
    #[arg(long)]
    vit: Option<VitPreset>,
    /// DINOv2 weights (safetensors) for the frozen 2D network.
    #[arg(long)]
    image_weights: Option<PathBuf>,
    /// Superpixel pooling at every n-th pixel (1 = all, as the official code).
    #[arg(long)]
    pixel_stride: Option<usize>,
    /// Peak learning rate.
    #[arg(long)]
    lr: Option<f64>,
    /// Seed of the initial weights.
    #[arg(long)]
    seed: Option<u64>,
    /// Compute backend: flex (CPU), wgpu (build with --features wgpu), cuda (--features cuda).
    #[arg(long, default_value = "flex")]
    backend: String,
    /// GPU index for cuda (wgpu takes the best adapter; set CUBECL_WGPU_DEFAULT_DEVICE to
    /// choose another).
    #[arg(long, default_value_t = 0)]
    device_index: usize,
    /// Output directory: checkpoints/, metrics.jsonl, losses.svg [default: runs/<run>
    /// or runs/<run>-rank<r>].
    #[arg(long)]
    out: Option<PathBuf>,
    /// Save a checkpoint every this many steps (0 = only at the end).
    #[arg(long)]
    checkpoint_every: Option<u64>,
    /// Continue from the newest checkpoint in the output directory, asking the pipeline
    /// for the batch that follows it.
    #[arg(long)]
    resume: bool,
    /// Write losses.svg (the loss curves) at the end.
    #[arg(long)]
    plot: bool,
    /// Give up when no batch arrives for this long, seconds.
    #[arg(long, default_value_t = 300)]
    timeout_secs: u64,
    /// Isolates this deployment's iceoryx2 resources (also `SUPERFLOW_IOX_PREFIX`).
    #[arg(long, env = "SUPERFLOW_IOX_PREFIX")]
    iox_prefix: Option<String>,
}

impl Args {
    fn config(&self) -> anyhow::Result<TrainerConfig> {
        let mut c = match &self.config {
            Some(path) => TrainerConfig::load(path)?,
            None => TrainerConfig::default(),
        };
        if let Some(v) = self.steps {
            c.optim.steps = v;
        }
        if let Some(v) = self.unet {
            c.model.unet = v;
        }
        if let Some(v) = self.vit {
            c.model.vit = v;
        }
        if let Some(v) = &self.image_weights {
            c.model.image_weights = Some(v.clone());
        }
        if let Some(v) = self.pixel_stride {
            c.loss.pixel_stride = v;
        }
        if let Some(v) = self.lr {
            c.optim.lr = v;
        }
        if let Some(v) = self.seed {
            c.model.seed = v;
        }
        if let Some(v) = self.checkpoint_every {
            c.checkpoint.every = v;
        }
        c.validate()
            .map_err(|e| anyhow::anyhow!("configuration: {e}"))?;
        Ok(c)
    }

    fn out_dir(&self) -> PathBuf {
        self.out.clone().unwrap_or_else(|| {
            let name = match self.rank {
                Some(r) => format!("{}-rank{r}", self.run),
                None => self.run.clone(),
            };
            PathBuf::from("runs").join(name)
        })
    }
}

#[cfg_attr(not(feature = "cuda"), allow(unused_variables))]
fn device(backend: &str, index: usize) -> anyhow::Result<burn::tensor::Device> {
    match backend {
        "flex" => Ok(burn::tensor::Device::flex()),
        // wgpu picks the best adapter (override with CUBECL_WGPU_DEFAULT_DEVICE).
        #[cfg(feature = "wgpu")]
        "wgpu" => Ok(burn::tensor::Device::wgpu(
            burn::tensor::DeviceKind::DefaultDevice,
        )),
        #[cfg(feature = "cuda")]
        "cuda" => Ok(burn::tensor::Device::cuda(index)),
        "wgpu" | "cuda" => {
            anyhow::bail!("backend {backend} is not compiled in: build with `--features {backend}`")
        }
        other => anyhow::bail!("unknown backend {other:?} (flex, wgpu, cuda)"),
    }
}

/// Watches SIGTERM and SIGINT (on a thread of its own): the first sets the returned
/// number (15 or 2) — the trainer checkpoints after the step in progress and exits
/// with 128 + the signal — and a second one exits at once.
fn watch_signals() -> anyhow::Result<Arc<AtomicI32>> {
    use tokio::signal::unix::{SignalKind, signal};
    let caught = Arc::new(AtomicI32::new(0));
    let runtime = tokio::runtime::Builder::new_current_thread()
        .enable_io()
        .build()?;
    let (mut term, mut int) = runtime.block_on(async {
        Ok::<_, std::io::Error>((
            signal(SignalKind::terminate())?,
            signal(SignalKind::interrupt())?,
        ))
    })?;
    let flag = caught.clone();
    std::thread::Builder::new()
        .name("signals".into())
        .spawn(move || {
            runtime.block_on(async move {
                loop {
                    let n = tokio::select! {
                        _ = term.recv() => 15,
                        _ = int.recv() => 2,
                    };
                    if flag.swap(n, Ordering::SeqCst) != 0 {
                        eprintln!("superflow-trainer: second signal, exiting without a checkpoint");
                        std::process::exit(128 + n);
                    }
                    tracing::warn!(
                        signal = n,
                        "stopping: a checkpoint is written after the step in progress (signal again to exit at once)"
                    );
                }
            });
        })?;
    Ok(caught)
}

/// Waits for the next batch; says when no pipeline publishes and keeps waiting for one
/// to come back, up to `timeout`. `None` once a stop signal was caught.
fn next_batch(
    subscription: &Subscription,
    run: &str,
    timeout: Duration,
    stop: &AtomicI32,
) -> anyhow::Result<Option<Received>> {
    let t = Instant::now();
    let mut gone_reported = false;
    loop {
        if stop.load(Ordering::SeqCst) != 0 {
            return Ok(None);
        }
        if let Some(batch) = subscription.receive(Duration::from_secs(2))? {
            if gone_reported {
                tracing::info!(run, "a pipeline is publishing again");
            }
            return Ok(Some(batch));
        }
        let attached = subscription.pipeline_attached();
        if !attached && !gone_reported {
            tracing::warn!(
                run,
                "no pipeline is publishing; waiting for it to come back"
            );
            gone_reported = true;
        } else if attached && gone_reported {
            tracing::info!(run, "a pipeline is publishing again");
            gone_reported = false;
        }
        if t.elapsed() > timeout {
            anyhow::bail!(
                "no batch from run {run} within {} s (is superflow-pipeline running with --run {run}?)",
                timeout.as_secs()
            );
        }
    }
}

/// Trains; `Some(code)` when stopped early by a signal (after a checkpoint).
fn run(args: &Args) -> anyhow::Result<Option<i32>> {
    if let (Some(rank), Some(world)) = (args.rank, args.world_size)
        && rank >= world
    {
        anyhow::bail!("--rank {rank} is not below --world-size {world}");
    }
    let config = args.config()?;
    let iox = superflow_schemas::service::iceoryx2_config(args.iox_prefix.as_deref())
        .map_err(|e| anyhow::anyhow!(e))?;
    let stop = watch_signals().context("installing the SIGTERM/SIGINT handlers")?;
    let target = args.rank.map_or(Target::Broadcast, Target::Rank);
    let subscription = Subscription::open(&args.run, target, &iox, 2)
        .with_context(|| format!("subscribing to run {}", args.run))?;
    let out = args.out_dir();
    let ckpt_dir = config
        .checkpoint
        .dir
        .clone()
        .unwrap_or_else(|| out.join("checkpoints"));
    let steps = config.optim.steps;
    let every = config.checkpoint.every;
    let device = device(&args.backend, args.device_index)?;
    tracing::info!(backend = %args.backend, ?device, "compute device");
    let mut trainer = Trainer::new(config, &device)?;

    let metrics_path = out.join("metrics.jsonl");
    let mut resumed_at = None;
    if args.resume {
        match trainer.restore_latest(&ckpt_dir)? {
            Some(state) => {
                let reply = subscription
                    .resume(
                        state.next_epoch,
                        state.next_batch,
                        Duration::from_secs(args.timeout_secs),
                    )
                    .with_context(|| format!("asking run {} to resume", args.run))?;
                if reply.accepted != 1 {
                    anyhow::bail!(
                        "the pipeline refused to resume run {} at epoch {} batch {} (reason {}): \
                         is it the same recording and configuration?",
                        args.run,
                        state.next_epoch,
                        state.next_batch,
                        reply.reason
                    );
                }
                tracing::info!(
                    step = state.step,
                    epoch = state.next_epoch,
                    batch = state.next_batch,
                    "resuming: the pipeline continues at the checkpoint's next batch"
                );
                let redone = metrics::truncate_after(&metrics_path, state.step)?;
                if redone > 0 {
                    tracing::warn!(
                        steps = redone,
                        after = state.step,
                        "steps trained after the checkpoint are lost and will be redone on the same batches; their metrics lines are dropped"
                    );
                }
                resumed_at = Some((state.next_epoch, state.next_batch));
            }
            None => {
                tracing::warn!(dir = %ckpt_dir.display(), "--resume: no checkpoint yet, starting fresh")
            }
        }
    } else if superflow_trainer::checkpoint::latest(&ckpt_dir)?.is_some() {
        anyhow::bail!(
            "{} already holds checkpoints: pass --resume to continue that run, or choose another --out",
            ckpt_dir.display()
        );
    } else if metrics_path.exists() {
        std::fs::remove_file(&metrics_path)
            .with_context(|| format!("replacing {}", metrics_path.display()))?;
    }
    let mut metrics = MetricsWriter::open(&metrics_path)?;

    let bar = ProgressBar::new(steps);
    bar.set_style(
        ProgressStyle::with_template(
            "{spinner} step {pos}/{len} [{elapsed_precise}<{eta_precise}] {msg}",
        )
        .unwrap_or_else(|_| ProgressStyle::default_bar()),
    );
    bar.set_position(trainer.step_count());
    let started = Instant::now();
    let (mut waiting, mut computing) = (0.0_f64, 0.0_f64);
    let mut last = None;
    // The stream position of the next batch to train on, once known, and the pipeline
    // (publisher) that sends it.
    let mut expected: Option<(u64, u64)> = resumed_at;
    let mut origin: Option<u128> = None;
    let mut skipped = 0u64;
    tracing::info!(run = %args.run, ?target, steps, out = %out.display(), "training");
    while trainer.step_count() < steps {
        let t = Instant::now();
        let Some(batch) = next_batch(
            &subscription,
            &args.run,
            Duration::from_secs(args.timeout_secs),
            &stop,
        )?
        else {
            break;
        };
        let position = (batch.header().epoch, batch.header().step);
        let restarted = origin.is_some_and(|o| o != batch.origin());
        // Broadcast: another trainer's resume moved the shared stream past this one.
        let gap = |next: (u64, u64)| position.0 == next.0 && position.1 > next.1;
        if let Some(next) = expected
            && position != next
            && (restarted || gap(next))
        {
            // A new pipeline (the old one died and was restarted) began elsewhere, or
            // the stream jumped ahead: ask it to continue where this trainer is.
            tracing::warn!(
                got_epoch = position.0,
                got_batch = position.1,
                epoch = next.0,
                batch = next.1,
                restarted,
                "the stream is not at this trainer's next batch (a restarted pipeline, or another trainer's resume); asking it to continue there"
            );
            drop(batch);
            let reply = subscription
                .resume(next.0, next.1, Duration::from_secs(args.timeout_secs))
                .with_context(|| format!("asking run {} to resume", args.run))?;
            if reply.accepted != 1 {
                anyhow::bail!(
                    "the restarted pipeline of run {} refused to continue at epoch {} batch {} (reason {})",
                    args.run,
                    next.0,
                    next.1,
                    reply.reason
                );
            }
            origin = Some(reply.publisher());
            continue;
        }
        if expected.is_some_and(|next| position < next) {
            // Broadcast: another subscriber rewound the shared stream (its resume).
            skipped += 1;
            tracing::warn!(
                epoch = position.0,
                batch = position.1,
                skipped,
                "already trained on this batch: skipped"
            );
            continue;
        }
        origin = Some(batch.origin());
        let wait = t.elapsed().as_secs_f64();
        let view = batch.view().context("invalid batch")?;
        let meta = view.meta().clone();
        let outcome = trainer.step(&view).with_context(|| {
            format!(
                "step {} (epoch {}, batch {})",
                trainer.step_count() + 1,
                meta.epoch,
                meta.step
            )
        })?;
        drop(view);
        drop(batch);
        waiting += wait;
        computing += outcome.seconds;
        let next = (meta.epoch, meta.step + 1);
        expected = Some(next);
        let record = StepRecord {
            step: trainer.step_count(),
            epoch: meta.epoch,
            batch: meta.step,
            loss: outcome.losses.total,
            l_sc: outcome.losses.sc,
            l_tc: outcome.losses.tc,
            l_d2s: outcome.losses.d2s,
            lr: outcome.lr,
            wait_ms: wait * 1e3,
            step_ms: outcome.seconds * 1e3,
            samples_per_s: meta.sample_count as f64 / (wait + outcome.seconds).max(1e-9),
            samples: meta.sample_count as usize,
            points: outcome.counts[0],
            pairings: outcome.counts[1],
            voxels: outcome.counts[2],
            sample_ids: outcome.sample_ids.clone(),
        };
        metrics.write(&record)?;
        tracing::info!(
            step = record.step,
            epoch = meta.epoch,
            batch = meta.step,
            loss = format_args!("{:.4}", record.loss),
            l_sc = format_args!("{:.4}", record.l_sc),
            l_tc = format_args!("{:.4}", record.l_tc),
            l_d2s = format_args!("{:.4}", record.l_d2s),
            lr = format_args!("{:.2e}", record.lr),
            wait_ms = format_args!("{:.1}", record.wait_ms),
            step_ms = format_args!("{:.1}", record.step_ms),
            vit_ms = format_args!("{:.1}", outcome.phases.vit * 1e3),
            forward_ms = format_args!("{:.1}", outcome.phases.forward * 1e3),
            backward_ms = format_args!("{:.1}", outcome.phases.backward * 1e3),
            "step"
        );
        bar.set_position(record.step);
        bar.set_message(format!("loss {:.4}", record.loss));
        let stopping = stop.load(Ordering::SeqCst) != 0;
        if every > 0 && record.step.is_multiple_of(every) && record.step < steps && !stopping {
            let dir = trainer.save_checkpoint(&ckpt_dir, &args.run, next, &outcome.losses)?;
            tracing::info!(checkpoint = %dir.display(), "checkpoint saved");
        }
        last = Some(outcome.losses);
        if stopping {
            break;
        }
    }
    bar.finish_and_clear();
    let signal = stop.load(Ordering::SeqCst);
    if let (Some(losses), Some(next)) = (last, expected) {
        let dir = trainer.save_checkpoint(&ckpt_dir, &args.run, next, &losses)?;
        if signal != 0 {
            tracing::warn!(
                checkpoint = %dir.display(),
                step = trainer.step_count(),
                "stopped by a signal; checkpoint saved: continue with --resume"
            );
        } else {
            tracing::info!(checkpoint = %dir.display(), "final checkpoint saved");
        }
    }
    if signal != 0 {
        return Ok(Some(128 + signal));
    }
    if args.plot {
        let svg = out.join("losses.svg");
        metrics::plot_svg(&metrics::read(&metrics_path)?, &svg)?;
        tracing::info!(plot = %svg.display(), "loss curves written");
    }
    let total = started.elapsed().as_secs_f64();
    tracing::info!(
        steps = trainer.step_count(),
        seconds = format_args!("{total:.1}"),
        data_stall_fraction = format_args!("{:.3}", waiting / total.max(1e-9)),
        compute_fraction = format_args!("{:.3}", computing / total.max(1e-9)),
        metrics = %metrics_path.display(),
        "done training"
    );
    Ok(None)
}

fn main() -> std::process::ExitCode {
    tracing_subscriber::fmt()
        .with_writer(std::io::stderr)
        // Colour only on a terminal: logs redirected to files stay plain text.
        .with_ansi(std::io::IsTerminal::is_terminal(&std::io::stderr()))
        .with_env_filter(
            tracing_subscriber::EnvFilter::try_from_default_env().unwrap_or_else(|_| "info".into()),
        )
        .init();
    match run(&Args::parse()) {
        Ok(None) => std::process::ExitCode::SUCCESS,
        // Stopped by a signal after checkpointing: not done, so not success.
        Ok(Some(code)) => std::process::ExitCode::from(code as u8),
        Err(err) => {
            eprintln!("superflow-trainer: {err:#}");
            std::process::ExitCode::from(1)
        }
    }
}
