//! `superflow-trainer`: subscribes to a run's batches and trains the 3D network with the
//! SuperFlow losses (burn). See the crate README section in the workspace README.

use anyhow::Context as _;
use clap::Parser;
use indicatif::{ProgressBar, ProgressStyle};
use std::path::PathBuf;
use std::sync::Arc;
use std::sync::atomic::{AtomicI32, Ordering};
use std::time::{Duration, Instant};
use superflow_schemas::batch::BatchMeta;
use superflow_trainer::config::TrainerConfig;
use superflow_trainer::loss::LossValues;
use superflow_trainer::metrics::{self, MetricsWriter, StepRecord};
use superflow_trainer::sparse::UNetPreset;
use superflow_trainer::stream::{Action, StreamPosition, StreamTracker};
use superflow_trainer::subscribe::{Received, Subscription, Target};
use superflow_trainer::train::{StepOutcome, Trainer};
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
        c.validate().context("configuration")?;
        Ok(c)
    }

    /// `--rank` must be below `--world-size`.
    fn check_rank(&self) -> anyhow::Result<()> {
        if let (Some(rank), Some(world)) = (self.rank, self.world_size)
            && rank >= world
        {
            anyhow::bail!("--rank {rank} is not below --world-size {world}");
        }
        Ok(())
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
        #[cfg(not(feature = "wgpu"))]
        "wgpu" => not_compiled_in(backend),
        #[cfg(not(feature = "cuda"))]
        "cuda" => not_compiled_in(backend),
        other => anyhow::bail!("unknown backend {other:?} (flex, wgpu, cuda)"),
    }
}

#[cfg(not(all(feature = "wgpu", feature = "cuda")))]
fn not_compiled_in(backend: &str) -> anyhow::Result<burn::tensor::Device> {
    anyhow::bail!("backend {backend} is not compiled in: build with `--features {backend}`")
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

/// The files of a run.
#[derive(Debug)]
struct RunPaths {
    /// Output directory.
    out: PathBuf,
    /// Checkpoint directory.
    checkpoints: PathBuf,
    /// `metrics.jsonl`.
    metrics: PathBuf,
}

impl RunPaths {
    fn new(args: &Args, config: &TrainerConfig) -> Self {
        let out = args.out_dir();
        let checkpoints = config
            .checkpoint
            .dir
            .clone()
            .unwrap_or_else(|| out.join("checkpoints"));
        let metrics = out.join("metrics.jsonl");
        Self {
            out,
            checkpoints,
            metrics,
        }
    }
}

/// Trains; `Some(code)` when stopped early by a signal (after a checkpoint).
fn run(args: &Args) -> anyhow::Result<Option<i32>> {
    args.check_rank()?;
    let config = args.config()?;
    let iox = superflow_schemas::service::iceoryx2_config(args.iox_prefix.as_deref())
        .map_err(|e| anyhow::anyhow!(e))?;
    let stop = watch_signals().context("installing the SIGTERM/SIGINT handlers")?;
    let target = args.rank.map_or(Target::Broadcast, Target::Rank);
    let subscription = Subscription::open(&args.run, target, &iox, 2)
        .with_context(|| format!("subscribing to run {}", args.run))?;
    let paths = RunPaths::new(args, &config);
    let (steps, every) = (config.optim.steps, config.checkpoint.every);
    let device = device(&args.backend, args.device_index)?;
    tracing::info!(backend = %args.backend, ?device, "compute device");
    let mut trainer = Trainer::new(config, &device)?;
    let resumed_at = if args.resume {
        resume(args, &mut trainer, &subscription, &paths)?
    } else {
        start_fresh(&paths)?;
        None
    };
    let metrics = MetricsWriter::open(&paths.metrics)?;
    let bar = progress_bar(steps, trainer.step_count());
    let mut session = Session {
        args,
        subscription,
        stop,
        trainer,
        metrics,
        stream: StreamTracker::new(resumed_at),
        bar,
        started: Instant::now(),
        waiting: 0.0,
        computing: 0.0,
        last: None,
        steps,
        every,
        paths,
    };
    tracing::info!(run = %args.run, ?target, steps, out = %session.paths.out.display(), "training");
    session.train()?;
    session.finish()
}

/// `--resume`: restores the newest checkpoint and asks the pipeline to continue at its
/// next batch (`None` when there is no checkpoint yet: a fresh start).
fn resume(
    args: &Args,
    trainer: &mut Trainer,
    subscription: &Subscription,
    paths: &RunPaths,
) -> anyhow::Result<Option<StreamPosition>> {
    let Some(state) = trainer.restore_latest(&paths.checkpoints)? else {
        tracing::warn!(dir = %paths.checkpoints.display(), "--resume: no checkpoint yet, starting fresh");
        return Ok(None);
    };
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
    let redone = metrics::truncate_after(&paths.metrics, state.step)?;
    if redone > 0 {
        tracing::warn!(
            steps = redone,
            after = state.step,
            "steps trained after the checkpoint are lost and will be redone on the same batches; their metrics lines are dropped"
        );
    }
    Ok(Some(state.next()))
}

/// A fresh run: refuses an output directory holding checkpoints, drops old metrics.
fn start_fresh(paths: &RunPaths) -> anyhow::Result<()> {
    if superflow_trainer::checkpoint::latest(&paths.checkpoints)?.is_some() {
        anyhow::bail!(
            "{} already holds checkpoints: pass --resume to continue that run, or choose another --out",
            paths.checkpoints.display()
        );
    }
    if paths.metrics.exists() {
        std::fs::remove_file(&paths.metrics)
            .with_context(|| format!("replacing {}", paths.metrics.display()))?;
    }
    Ok(())
}

fn progress_bar(steps: u64, position: u64) -> ProgressBar {
    let bar = ProgressBar::new(steps);
    bar.set_style(
        ProgressStyle::with_template(
            "{spinner} step {pos}/{len} [{elapsed_precise}<{eta_precise}] {msg}",
        )
        .unwrap_or_else(|_| ProgressStyle::default_bar()),
    );
    bar.set_position(position);
    bar
}

/// A run in progress: the stream, the trainer and what it writes.
struct Session<'a> {
    args: &'a Args,
    subscription: Subscription,
    stop: Arc<AtomicI32>,
    trainer: Trainer,
    metrics: MetricsWriter,
    stream: StreamTracker,
    bar: ProgressBar,
    started: Instant,
    /// Seconds spent waiting for batches, and computing steps.
    waiting: f64,
    computing: f64,
    /// The losses of the last step.
    last: Option<LossValues>,
    steps: u64,
    every: u64,
    paths: RunPaths,
}

impl Session<'_> {
    fn timeout(&self) -> Duration {
        Duration::from_secs(self.args.timeout_secs)
    }

    /// Steps until the run's length, the end of the stream or a stop signal.
    fn train(&mut self) -> anyhow::Result<()> {
        while self.trainer.step_count() < self.steps {
            let t = Instant::now();
            let Some(batch) = next_batch(
                &self.subscription,
                &self.args.run,
                self.timeout(),
                &self.stop,
            )?
            else {
                break;
            };
            let position = StreamPosition::new(batch.header().epoch, batch.header().step);
            match self.stream.classify(batch.origin(), position) {
                Action::Train => {}
                Action::Skip { skipped } => {
                    tracing::warn!(
                        epoch = position.epoch,
                        batch = position.batch,
                        skipped,
                        "already trained on this batch: skipped"
                    );
                    continue;
                }
                Action::Resume { at, restarted } => {
                    drop(batch);
                    self.continue_at(position, at, restarted)?;
                    continue;
                }
            }
            let wait = t.elapsed().as_secs_f64();
            if self.step(batch, wait)? {
                break;
            }
        }
        Ok(())
    }

    /// The stream is not at this trainer's next batch `at` (a new pipeline, the old one
    /// died and was restarted, began elsewhere, or the stream jumped ahead): asks it to
    /// continue there.
    fn continue_at(
        &mut self,
        got: StreamPosition,
        at: StreamPosition,
        restarted: bool,
    ) -> anyhow::Result<()> {
        tracing::warn!(
            got_epoch = got.epoch,
            got_batch = got.batch,
            epoch = at.epoch,
            batch = at.batch,
            restarted,
            "the stream is not at this trainer's next batch (a restarted pipeline, or another trainer's resume); asking it to continue there"
        );
        let run = &self.args.run;
        let reply = self
            .subscription
            .resume(at.epoch, at.batch, self.timeout())
            .with_context(|| format!("asking run {run} to resume"))?;
        if reply.accepted != 1 {
            anyhow::bail!(
                "the restarted pipeline of run {run} refused to continue at epoch {} batch {} (reason {})",
                at.epoch,
                at.batch,
                reply.reason
            );
        }
        self.stream.resumed(reply.publisher());
        Ok(())
    }

    /// One step on `batch` (waited for `wait` seconds): metrics, log, progress and the
    /// periodic checkpoint. `true` when a stop signal was caught: the run ends here.
    fn step(&mut self, batch: Received, wait: f64) -> anyhow::Result<bool> {
        let view = batch.view().context("invalid batch")?;
        let meta = view.meta().clone();
        let outcome = self.trainer.step(&view).with_context(|| {
            format!(
                "step {} (epoch {}, batch {})",
                self.trainer.step_count() + 1,
                meta.epoch,
                meta.step
            )
        })?;
        drop(view);
        drop(batch);
        self.waiting += wait;
        self.computing += outcome.seconds;
        self.stream
            .trained(StreamPosition::new(meta.epoch, meta.step));
        let record = step_record(self.trainer.step_count(), &meta, &outcome, wait);
        self.metrics.write(&record)?;
        log_step(&record, &outcome);
        self.bar.set_position(record.step);
        self.bar.set_message(format!("loss {:.4}", record.loss));
        let stopping = self.stop.load(Ordering::SeqCst) != 0;
        let periodic = self.every > 0 && record.step.is_multiple_of(self.every);
        if periodic && record.step < self.steps && !stopping {
            let dir = self.save_checkpoint(&outcome.losses)?;
            tracing::info!(checkpoint = %dir.display(), "checkpoint saved");
        }
        self.last = Some(outcome.losses);
        Ok(stopping)
    }

    fn save_checkpoint(&self, losses: &LossValues) -> anyhow::Result<PathBuf> {
        let next = self
            .stream
            .next()
            .context("a checkpoint before the first step")?;
        Ok(self
            .trainer
            .save_checkpoint(&self.paths.checkpoints, &self.args.run, next, losses)?)
    }

    /// The final checkpoint, the plot and the summary; `Some(128 + signal)` when stopped
    /// by a signal.
    fn finish(self) -> anyhow::Result<Option<i32>> {
        self.bar.finish_and_clear();
        let signal = self.stop.load(Ordering::SeqCst);
        if let Some(losses) = &self.last
            && self.stream.next().is_some()
        {
            let dir = self.save_checkpoint(losses)?;
            if signal != 0 {
                tracing::warn!(
                    checkpoint = %dir.display(),
                    step = self.trainer.step_count(),
                    "stopped by a signal; checkpoint saved: continue with --resume"
                );
            } else {
                tracing::info!(checkpoint = %dir.display(), "final checkpoint saved");
            }
        }
        if signal != 0 {
            return Ok(Some(128 + signal));
        }
        if self.args.plot {
            let svg = self.paths.out.join("losses.svg");
            metrics::plot_svg(&metrics::read(&self.paths.metrics)?, &svg)?;
            tracing::info!(plot = %svg.display(), "loss curves written");
        }
        let total = self.started.elapsed().as_secs_f64();
        tracing::info!(
            steps = self.trainer.step_count(),
            seconds = format_args!("{total:.1}"),
            data_stall_fraction = format_args!("{:.3}", self.waiting / total.max(1e-9)),
            compute_fraction = format_args!("{:.3}", self.computing / total.max(1e-9)),
            metrics = %self.paths.metrics.display(),
            "done training"
        );
        Ok(None)
    }
}

/// The metrics line of step `step`, trained on the batch `meta` after waiting `wait`
/// seconds for it.
fn step_record(step: u64, meta: &BatchMeta, outcome: &StepOutcome, wait: f64) -> StepRecord {
    StepRecord {
        step,
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
    }
}

fn log_step(record: &StepRecord, outcome: &StepOutcome) {
    tracing::info!(
        step = record.step,
        epoch = record.epoch,
        batch = record.batch,
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
