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
use superflow_trainer::check::{self, BatchFile};
use superflow_trainer::checkpoint::CheckpointState;
use superflow_trainer::config::TrainerConfig;
#[cfg(feature = "mpi")]
use superflow_trainer::ddp::Ddp;
use superflow_trainer::evaluate;
use superflow_trainer::loss::LossValues;
use superflow_trainer::metrics::{self, DdpRecord, MetricsWriter, StepRecord};
use superflow_trainer::sparse::UNetPreset;
use superflow_trainer::stream::{self, Action, StreamPosition, StreamTracker};
use superflow_trainer::subscribe::{Received, Subscription, Target};
use superflow_trainer::train::{StepOutcome, Trainer};
use superflow_trainer::vit::VitPreset;

/// Trains a 3D network on SuperFlow batches received over shared memory.
#[derive(Debug, Parser)]
#[command(version, about)]
struct Args {
    #[command(subcommand)]
    command: Option<Sub>,
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
    #[arg(long, global = true)]
    config: Option<PathBuf>,
    /// Optimizer steps of the run (also the one-cycle schedule's length) [default: the
    /// config's `optim.steps`].
    #[arg(long, global = true)]
    steps: Option<u64>,
    /// 3D network: minkunet34, minkunet18, tiny.
    #[arg(long, global = true)]
    unet: Option<UNetPreset>,
    /// 2D network size without weights: tiny, small, base, large.
    #[arg(long, global = true)]
    vit: Option<VitPreset>,
    /// DINOv2 weights (safetensors) for the frozen 2D network.
    #[arg(long, global = true)]
    image_weights: Option<PathBuf>,
    /// Superpixel pooling at every n-th pixel (1 = all, as the official code).
    #[arg(long, global = true)]
    pixel_stride: Option<usize>,
    /// Peak learning rate.
    #[arg(long)]
    lr: Option<f64>,
    /// Seed of the initial weights.
    #[arg(long, global = true)]
    seed: Option<u64>,
    /// Compute backend: flex (CPU), wgpu (build with --features wgpu), cuda (--features cuda).
    #[arg(long, default_value = "flex", global = true)]
    backend: String,
    /// GPU index for cuda (wgpu takes the best adapter; set CUBECL_WGPU_DEFAULT_DEVICE to
    /// choose another).
    #[arg(long, default_value_t = 0, global = true)]
    device_index: usize,
    /// Output directory: checkpoints/, metrics.jsonl, losses.svg [default: runs/<run>
    /// or runs/<run>-rank<r>]; with --ddp rank r writes rank-r/metrics.jsonl there and
    /// rank 0 the checkpoints.
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
    /// Synchronous data parallelism over MPI: run every rank under `mpirun -np W` (or
    /// `srun --mpi=pmix`); rank and world size come from MPI, each rank reads the shard
    /// stream of its rank on its host, gradients are averaged over the ranks every step
    /// (all ranks hold the same model), rank 0 writes the checkpoints.
    #[arg(long, conflicts_with_all = ["rank", "world_size"])]
    ddp: bool,
    /// `--ddp`: abort the job when a collective (gradient all-reduce, checkpoint
    /// agreement) waits longer than this for the other ranks (a hung peer), seconds.
    /// Keep it above --timeout-secs: a peer may be waiting that long for its batch.
    #[arg(long, default_value_t = 900)]
    collective_timeout_secs: u64,
    /// Isolates this deployment's iceoryx2 resources (also `SUPERFLOW_IOX_PREFIX`).
    #[arg(long, env = "SUPERFLOW_IOX_PREFIX")]
    iox_prefix: Option<String>,
}

/// What else the binary does besides training on a stream.
#[derive(Debug, clap::Subcommand)]
enum Sub {
    /// Trains a few steps on one batch file on several backends from the same initial
    /// weights and compares their losses (a GPU backend against the CPU's `flex`): the
    /// check before a long run on a new machine. Network flags (--unet, --vit,
    /// --pixel-stride, --config, --seed, --steps [default 3]) apply.
    Check(CheckArgs),
    /// Scores a 3D backbone downstream: per-point semantic segmentation of the labelled
    /// sweeps of DRIVES, split by time into train and validation, a linear classifier on
    /// the frozen backbone's features (or `--finetune`: the whole network), mIoU and
    /// per-class IoU on the validation sweeps.
    Probe(ProbeArgs),
}

/// `superflow-trainer probe`.
#[derive(Debug, clap::Args)]
struct ProbeArgs {
    /// Labelled drives: MCAP files or directories of them (labels in the LiDAR clouds or
    /// in `<drive>.labels.mcap` sidecars).
    #[arg(long, num_args = 1.., required = true)]
    mcap: Vec<PathBuf>,
    /// The backbone: a run's checkpoint directory (its newest checkpoint), one `step-N`
    /// directory, or `random` (an untrained network of --unet/--config, for the
    /// baseline).
    #[arg(long)]
    checkpoint: String,
    /// The pipeline's configuration (channels, de-skew, voxel grid, `[labels]`: field,
    /// mapping, classes, ignore index) [default: the pipeline's defaults].
    #[arg(long)]
    pipeline_config: Option<PathBuf>,
    /// Train the whole network with a linear classifier instead of a linear classifier on
    /// frozen features.
    #[arg(long)]
    finetune: bool,
    /// Share of the training sweeps used (few-label protocols: 0.01, 0.1).
    #[arg(long, default_value_t = 1.0)]
    label_fraction: f64,
    /// Passes over the training data [default: 20, fine-tuning 10].
    #[arg(long)]
    epochs: Option<usize>,
    /// Learning rate [default: 1e-2 linear probe, 1e-3 fine-tuning].
    #[arg(long = "probe-lr")]
    probe_lr: Option<f64>,
    /// Share of each drive's time span, at its end, scored as validation.
    #[arg(long, default_value_t = 0.25)]
    val_fraction: f64,
    /// Validation drives of their own (e.g. nuScenes' val scenes): every labelled sweep of
    /// --mcap trains, every one of these is scored (--val-fraction and --gap-secs unused).
    #[arg(long, num_args = 1..)]
    val_mcap: Vec<PathBuf>,
    /// Seconds of sweeps left out between the training and validation parts.
    #[arg(long, default_value_t = 1.0)]
    gap_secs: f64,
    /// One labelled sweep per this many seconds (nuScenes labels its 2 Hz keyframes).
    #[arg(long, default_value_t = 0.5)]
    keyframe_interval_secs: f64,
    /// Most training points of the linear probe (evenly strided beyond).
    #[arg(long, default_value_t = 1_000_000)]
    max_train_points: usize,
    /// Print the report as JSON on stdout (`{"miou", "per_class", "points", "split", …}`).
    #[arg(long)]
    json: bool,
}

/// `superflow-trainer check`.
#[derive(Debug, clap::Args)]
struct CheckArgs {
    /// Batch file written by `superflow-pipeline batch`.
    #[arg(long)]
    batch: PathBuf,
    /// Backends to run, comma-separated; the first is the reference.
    #[arg(long, value_delimiter = ',', default_value = "flex,wgpu")]
    backends: Vec<String>,
    /// Largest relative difference of any loss term of any step from the reference.
    #[arg(long, default_value_t = 1e-3)]
    tolerance: f64,
    /// Also write the results as JSON to this file.
    #[arg(long)]
    json: Option<PathBuf>,
}

impl Args {
    fn config(&self) -> anyhow::Result<TrainerConfig> {
        let mut c = match &self.config {
            Some(path) => TrainerConfig::load(path)?,
            None => TrainerConfig::default(),
        };
        // `check --steps` counts the steps to compare, not the schedule's length.
        if let Some(v) = self.steps
            && self.command.is_none()
        {
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
    /// `metrics.jsonl` (`rank-<r>/metrics.jsonl` in a data-parallel job).
    metrics: PathBuf,
    /// `losses.svg`, beside the metrics.
    plot: PathBuf,
}

impl RunPaths {
    /// The files of this process: rank `ddp_rank` of a `--ddp` job, or a lone trainer.
    fn new(args: &Args, config: &TrainerConfig, ddp_rank: Option<usize>) -> Self {
        let out = args.out_dir();
        let checkpoints = config
            .checkpoint
            .dir
            .clone()
            .unwrap_or_else(|| out.join("checkpoints"));
        let own = match ddp_rank {
            Some(rank) => out.join(format!("rank-{rank}")),
            None => out.clone(),
        };
        Self {
            metrics: own.join("metrics.jsonl"),
            plot: own.join("losses.svg"),
            out,
            checkpoints,
        }
    }
}

/// `--ddp`: this rank's place in the MPI job.
fn join_job(args: &Args) -> anyhow::Result<Option<Ddp>> {
    if !args.ddp {
        return Ok(None);
    }
    #[cfg(feature = "mpi")]
    {
        let timeout = Duration::from_secs(args.collective_timeout_secs);
        if args.collective_timeout_secs <= args.timeout_secs {
            tracing::warn!(
                collective_timeout_secs = args.collective_timeout_secs,
                timeout_secs = args.timeout_secs,
                "the collective timeout is not above the batch timeout: a rank waiting for its batch may abort the job first"
            );
        }
        Ok(Some(Ddp::init(timeout)?))
    }
    #[cfg(not(feature = "mpi"))]
    anyhow::bail!(
        "--ddp needs MPI, and this superflow-trainer was built without its `mpi` feature \
         (install Open MPI and libclang: apt-get install libopenmpi-dev openmpi-bin libclang-dev, \
         then build with the default features)"
    )
}

/// Without the `mpi` feature there is no job to be part of: an uninhabited stand-in,
/// so the session code is the same in both builds.
#[cfg(not(feature = "mpi"))]
#[derive(Debug)]
enum Ddp {}

#[cfg(not(feature = "mpi"))]
impl Ddp {
    fn rank(&self) -> usize {
        match *self {}
    }
    fn size(&self) -> usize {
        match *self {}
    }
    fn local_rank(&self) -> usize {
        match *self {}
    }
    fn all_reduce_sum(&self, _: &mut [f32], _: &str) {
        match *self {}
    }
    fn broadcast_bytes(&self, _: Vec<u8>, _: &str) -> Vec<u8> {
        match *self {}
    }
    fn all_gather(&self, _: &[u64], _: &str) -> Vec<u64> {
        match *self {}
    }
}

/// Trains; `Some(code)` when stopped early by a signal (after a checkpoint).
fn run(args: &Args) -> anyhow::Result<Option<i32>> {
    args.check_rank()?;
    let config = args.config()?;
    let ddp = join_job(args)?;
    let iox = superflow_schemas::service::iceoryx2_config(args.iox_prefix.as_deref())
        .map_err(|e| anyhow::anyhow!(e))?;
    let stop = watch_signals().context("installing the SIGTERM/SIGINT handlers")?;
    let target = match &ddp {
        Some(ddp) => Target::Rank(ddp.local_rank() as u32),
        None => args.rank.map_or(Target::Broadcast, Target::Rank),
    };
    let subscription = Subscription::open(&args.run, target, &iox, 2)
        .with_context(|| format!("subscribing to run {}", args.run))?;
    let paths = RunPaths::new(args, &config, ddp.as_ref().map(Ddp::rank));
    let (steps, every) = (config.optim.steps, config.checkpoint.every);
    let device = device(&args.backend, args.device_index)?;
    tracing::info!(backend = %args.backend, ?device, "compute device");
    let mut trainer = Trainer::new(config, &device)?;
    let resumed_at = match &ddp {
        Some(ddp) => start_ranks(args, &mut trainer, &subscription, &paths, ddp)?,
        None if args.resume => resume(args, &mut trainer, &subscription, &paths)?,
        None => {
            start_fresh(&paths, true)?;
            None
        }
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
        held: None,
        ddp,
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

/// Asks the pipeline to continue this trainer's stream at `at`.
fn ask_resume(
    subscription: &Subscription,
    run: &str,
    at: StreamPosition,
    timeout: Duration,
) -> anyhow::Result<u128> {
    let reply = subscription
        .resume(at.epoch, at.batch, timeout)
        .with_context(|| format!("asking run {run} to resume"))?;
    if reply.accepted != 1 {
        anyhow::bail!(
            "the pipeline refused to resume run {run} at epoch {} batch {} (reason {}): \
             is it the same recording and configuration?",
            at.epoch,
            at.batch,
            reply.reason
        );
    }
    Ok(reply.publisher())
}

/// How rank 0 starts a data-parallel job; every rank receives it.
#[derive(Debug, Default, serde::Serialize, serde::Deserialize)]
struct JobStart {
    /// Rank 0's configuration (TOML): every rank must run the same.
    config: String,
    /// The checkpoint the job continues from (`--resume` and one exists).
    resume: Option<CheckpointState>,
    /// Why rank 0 cannot start the job.
    error: Option<String>,
}

/// `--ddp`: rank 0 decides how the job starts (fresh, or from the newest checkpoint)
/// and every rank receives the same parameters and optimizer state from it; each rank
/// then asks its shard stream to continue at its own position. Returns that position
/// when resuming.
fn start_ranks(
    args: &Args,
    trainer: &mut Trainer,
    subscription: &Subscription,
    paths: &RunPaths,
    ddp: &Ddp,
) -> anyhow::Result<Option<StreamPosition>> {
    let rank = ddp.rank();
    let (start, model, optim) = if rank == 0 {
        match first_rank_start(args, trainer, paths) {
            Ok(start) => start,
            Err(e) => (
                JobStart {
                    error: Some(format!("{e:#}")),
                    ..JobStart::default()
                },
                Vec::new(),
                Vec::new(),
            ),
        }
    } else {
        Default::default()
    };
    let start = ddp.broadcast_bytes(serde_json::to_vec(&start)?, "job start (rank 0's decision)");
    let start: JobStart = serde_json::from_slice(&start).context("rank 0's job start")?;
    if let Some(error) = start.error {
        anyhow::bail!(if rank == 0 {
            error
        } else {
            format!("rank 0 could not start the job: {error}")
        });
    }
    if start.config != trainer.config_toml() {
        anyhow::bail!(
            "rank {rank}'s configuration differs from rank 0's: give every rank the same trainer.toml and flags"
        );
    }
    let model = ddp.broadcast_bytes(model, "rank 0's parameters");
    let optim = ddp.broadcast_bytes(optim, "rank 0's optimizer state");
    let step = start.resume.as_ref().map_or(0, |s| s.step);
    trainer.restore_bytes(model, optim, step, &paths.checkpoints)?;
    let Some(state) = start.resume else {
        start_fresh(paths, false)?;
        tracing::info!(
            rank,
            world_size = ddp.size(),
            "every rank starts from rank 0's parameters"
        );
        return Ok(None);
    };
    if state.ranks.len() != ddp.size() {
        anyhow::bail!(
            "the checkpoint at step {} was written by a job of {} data-parallel ranks; resume it with mpirun -np {}",
            state.step,
            state.ranks.len(),
            state.ranks.len().max(1)
        );
    }
    let [epoch, batch] = state.ranks[rank];
    let at = StreamPosition::new(epoch, batch);
    ask_resume(
        subscription,
        &args.run,
        at,
        Duration::from_secs(args.timeout_secs),
    )?;
    tracing::info!(
        rank,
        step,
        epoch,
        batch,
        "resuming: this rank's shard continues at its checkpointed position"
    );
    drop_redone_metrics(paths, step)?;
    Ok(Some(at))
}

/// Rank 0's part of [`start_ranks`]: the decision and the records to send.
fn first_rank_start(
    args: &Args,
    trainer: &Trainer,
    paths: &RunPaths,
) -> anyhow::Result<(JobStart, Vec<u8>, Vec<u8>)> {
    let config = trainer.config_toml();
    let latest = superflow_trainer::checkpoint::latest(&paths.checkpoints)?;
    match latest {
        Some(ckpt) if args.resume => {
            let read =
                |p: PathBuf| std::fs::read(&p).with_context(|| format!("reading {}", p.display()));
            let (model, optim) = (read(ckpt.model_path())?, read(ckpt.optim_path())?);
            tracing::info!(checkpoint = %ckpt.dir.display(), step = ckpt.state.step, "the job continues from this checkpoint");
            let start = JobStart {
                config,
                resume: Some(ckpt.state),
                error: None,
            };
            Ok((start, model, optim))
        }
        Some(_) => Err(holds_checkpoints(paths)),
        None => {
            if args.resume {
                tracing::warn!(dir = %paths.checkpoints.display(), "--resume: no checkpoint yet, starting fresh");
            }
            let start = JobStart {
                config,
                ..JobStart::default()
            };
            Ok((start, trainer.model_bytes()?, Vec::new()))
        }
    }
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
    ask_resume(
        subscription,
        &args.run,
        state.next(),
        Duration::from_secs(args.timeout_secs),
    )?;
    tracing::info!(
        step = state.step,
        epoch = state.next_epoch,
        batch = state.next_batch,
        "resuming: the pipeline continues at the checkpoint's next batch"
    );
    drop_redone_metrics(paths, state.step)?;
    Ok(Some(state.next()))
}

/// A resumed run redoes the steps after its checkpoint's `step`: their metrics lines go.
fn drop_redone_metrics(paths: &RunPaths, step: u64) -> anyhow::Result<()> {
    let redone = metrics::truncate_after(&paths.metrics, step)?;
    if redone > 0 {
        tracing::warn!(
            steps = redone,
            after = step,
            "steps trained after the checkpoint are lost and will be redone on the same batches; their metrics lines are dropped"
        );
    }
    Ok(())
}

/// Why a fresh run does not start in `paths`: it holds checkpoints.
fn holds_checkpoints(paths: &RunPaths) -> anyhow::Error {
    anyhow::anyhow!(
        "{} already holds checkpoints: pass --resume to continue that run, or choose another --out",
        paths.checkpoints.display()
    )
}

/// A fresh run: refuses an output directory holding checkpoints (`check_checkpoints`:
/// the process that writes them), drops old metrics.
fn start_fresh(paths: &RunPaths, check_checkpoints: bool) -> anyhow::Result<()> {
    if check_checkpoints && superflow_trainer::checkpoint::latest(&paths.checkpoints)?.is_some() {
        return Err(holds_checkpoints(paths));
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
    /// `--ddp`: a batch received but kept for a later step (this rank's shard began its
    /// next epoch while others finish theirs).
    held: Option<Received>,
    ddp: Option<Ddp>,
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

/// Where a batch lies in its stream.
fn position_of(batch: &Received) -> StreamPosition {
    StreamPosition::new(batch.header().epoch, batch.header().step)
}

impl Session<'_> {
    fn timeout(&self) -> Duration {
        Duration::from_secs(self.args.timeout_secs)
    }

    /// Steps until the run's length, the end of the stream or a stop signal.
    fn train(&mut self) -> anyhow::Result<()> {
        while self.trainer.step_count() < self.steps {
            let t = Instant::now();
            let batch = match self.held.take() {
                Some(batch) => Some(batch),
                None => self.next_trainable()?,
            };
            let wait = t.elapsed().as_secs_f64();
            let Some(ddp) = &self.ddp else {
                let Some(batch) = batch else { break };
                let at = position_of(&batch);
                if self.step(Some(batch), at, wait)? {
                    break;
                }
                continue;
            };
            // Data-parallel: every rank says where its batch lies and whether it stops;
            // the step trains the earliest position (a rank whose shard already began
            // the next epoch keeps its batch for later and adds no gradient).
            let mine = batch.as_ref().map(position_of);
            let stop = self.stop.load(Ordering::SeqCst) != 0 || batch.is_none();
            let what = format!("agreement before step {}", self.trainer.step_count() + 1);
            let ranks = ddp.all_gather(
                &[
                    mine.map_or(u64::MAX, |p| p.epoch),
                    mine.map_or(u64::MAX, |p| p.batch),
                    u64::from(stop),
                ],
                &what,
            );
            let states: Vec<_> = ranks
                .chunks(3)
                .map(|r| {
                    (
                        (r[0] != u64::MAX).then(|| StreamPosition::new(r[0], r[1])),
                        r[2] != 0,
                    )
                })
                .collect();
            let Some(at) = stream::agree(&states) else {
                self.held = batch;
                tracing::warn!("a rank is stopping: every rank stops after the same step");
                break;
            };
            let batch = match batch {
                Some(b) if position_of(&b) == at => Some(b),
                other => {
                    self.held = other;
                    None
                }
            };
            self.step(batch, at, wait)?;
        }
        Ok(())
    }

    /// The next batch to train on, past batches trained already and streams asked to
    /// continue elsewhere; `None` once a stop signal was caught.
    fn next_trainable(&mut self) -> anyhow::Result<Option<Received>> {
        loop {
            let Some(batch) = next_batch(
                &self.subscription,
                &self.args.run,
                self.timeout(),
                &self.stop,
            )?
            else {
                return Ok(None);
            };
            let position = position_of(&batch);
            match self.stream.classify(batch.origin(), position) {
                Action::Train => return Ok(Some(batch)),
                Action::Skip { skipped } => {
                    tracing::warn!(
                        epoch = position.epoch,
                        batch = position.batch,
                        skipped,
                        "already trained on this batch: skipped"
                    );
                }
                Action::Resume { at, restarted } => {
                    drop(batch);
                    self.continue_at(position, at, restarted)?;
                }
            }
        }
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
        let publisher = ask_resume(&self.subscription, &self.args.run, at, self.timeout())?;
        self.stream.resumed(publisher);
        Ok(())
    }

    /// One step at stream position `at` on `batch` (waited for `wait` seconds; `None`: a
    /// data-parallel rank without a batch at this step): metrics, log, progress and the
    /// periodic checkpoint. `true` when a stop signal was caught: a lone trainer ends
    /// here (data-parallel ranks agree on stopping before the next step).
    fn step(
        &mut self,
        batch: Option<Received>,
        at: StreamPosition,
        wait: f64,
    ) -> anyhow::Result<bool> {
        let view = batch
            .as_ref()
            .map(Received::view)
            .transpose()
            .context("invalid batch")?;
        let meta = view.as_ref().map(|v| v.meta().clone());
        let number = self.trainer.step_count() + 1;
        let outcome = match (&self.ddp, &view) {
            (Some(ddp), view) => {
                let what = format!("gradient all-reduce of step {number}");
                let mut reduce = |values: &mut [f32]| ddp.all_reduce_sum(values, &what);
                self.trainer.step_synced(view.as_ref(), Some(&mut reduce))
            }
            (None, Some(view)) => self.trainer.step(view),
            (None, None) => anyhow::bail!("step {number}: no batch"),
        }
        .with_context(|| format!("step {number} ({at})"))?;
        drop(view);
        drop(batch);
        self.waiting += wait;
        self.computing += outcome.seconds;
        if meta.is_some() {
            self.stream.trained(at);
        }
        let mut record = step_record(number, at, meta.as_ref(), &outcome, wait);
        record.params_hash = self.trainer.params_hash();
        if let (Some(ddp), Some(global)) = (&self.ddp, &outcome.global) {
            record.ddp = Some(DdpRecord {
                rank: ddp.rank() as u32,
                world_size: ddp.size() as u32,
                loss: global.losses.total,
                samples: global.samples,
                reduce_ms: outcome.phases.reduce * 1e3,
                reduce_bytes: global.bytes,
            });
        }
        self.metrics.write(&record)?;
        log_step(&record, &outcome);
        self.bar.set_position(record.step);
        let shown = record.ddp.as_ref().map_or(record.loss, |d| d.loss);
        self.bar.set_message(format!("loss {shown:.4}"));
        let losses = outcome.global.map_or(outcome.losses, |g| g.losses);
        let stopping = self.stop.load(Ordering::SeqCst) != 0;
        let periodic = self.every > 0 && record.step.is_multiple_of(self.every);
        // Data-parallel ranks checkpoint together whatever their signals say (the stop
        // is agreed before the next step).
        if periodic
            && record.step < self.steps
            && (!stopping || self.ddp.is_some())
            && let Some(dir) = self.save_checkpoint(&losses)?
        {
            tracing::info!(checkpoint = %dir.display(), "checkpoint saved");
        }
        self.last = Some(losses);
        Ok(stopping)
    }

    /// The position this trainer continues at: the batch it holds, or the one after its
    /// last trained batch.
    fn next_position(&self) -> Option<StreamPosition> {
        self.held.as_ref().map(position_of).or(self.stream.next())
    }

    /// Saves a checkpoint (a data-parallel job: every rank calls this, rank 0 writes it
    /// with every rank's next position); the directory written, if this process wrote.
    /// `losses` are the last step's (over all ranks in a data-parallel job).
    fn save_checkpoint(&self, losses: &LossValues) -> anyhow::Result<Option<PathBuf>> {
        let run = &self.args.run;
        let Some(ddp) = &self.ddp else {
            let next = self
                .next_position()
                .context("a checkpoint before the first step")?;
            let state = self.trainer.checkpoint_state(run, next, losses);
            return Ok(Some(
                self.trainer
                    .save_checkpoint(&self.paths.checkpoints, &state)?,
            ));
        };
        let next = self.next_position().unwrap_or_default();
        let what = format!("checkpoint positions at step {}", self.trainer.step_count());
        let all = ddp.all_gather(&[next.epoch, next.batch], &what);
        if ddp.rank() != 0 {
            return Ok(None);
        }
        let mut state = self.trainer.checkpoint_state(run, next, losses);
        state.ranks = all.chunks(2).map(|p| [p[0], p[1]]).collect();
        Ok(Some(
            self.trainer
                .save_checkpoint(&self.paths.checkpoints, &state)?,
        ))
    }

    /// The final checkpoint, the plot and the summary; `Some(128 + signal)` when stopped
    /// by a signal.
    fn finish(self) -> anyhow::Result<Option<i32>> {
        self.bar.finish_and_clear();
        let signal = self.stop.load(Ordering::SeqCst);
        let checkpoint = match &self.ddp {
            // Every rank takes part (the same steps on all ranks).
            Some(_) => self.last.filter(|_| self.trainer.step_count() > 0),
            None => self.last.filter(|_| self.stream.next().is_some()),
        };
        if let Some(losses) = checkpoint
            && let Some(dir) = self.save_checkpoint(&losses)?
        {
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
        // Stopped early: by this process's signal, or (data-parallel) another rank's.
        let stopped_early =
            signal != 0 || (self.ddp.is_some() && self.trainer.step_count() < self.steps);
        if stopped_early {
            return Ok(Some(128 + if signal != 0 { signal } else { 15 }));
        }
        if self.args.plot {
            metrics::plot_svg(&metrics::read(&self.paths.metrics)?, &self.paths.plot)?;
            tracing::info!(plot = %self.paths.plot.display(), "loss curves written");
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

/// The metrics line of step `step` at stream position `at`, trained on the batch `meta`
/// (none: a data-parallel rank without a batch at this step) after waiting `wait`
/// seconds for it.
fn step_record(
    step: u64,
    at: StreamPosition,
    meta: Option<&BatchMeta>,
    outcome: &StepOutcome,
    wait: f64,
) -> StepRecord {
    let samples = meta.map_or(0, |m| m.sample_count as usize);
    StepRecord {
        step,
        epoch: at.epoch,
        batch: at.batch,
        loss: outcome.losses.total,
        l_sc: outcome.losses.sc,
        l_tc: outcome.losses.tc,
        l_d2s: outcome.losses.d2s,
        lr: outcome.lr,
        wait_ms: wait * 1e3,
        step_ms: outcome.seconds * 1e3,
        samples_per_s: samples as f64 / (wait + outcome.seconds).max(1e-9),
        samples,
        points: outcome.counts[0],
        pairings: outcome.counts[1],
        voxels: outcome.counts[2],
        sample_ids: outcome.sample_ids.clone(),
        params_hash: 0,
        ddp: None,
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

/// `superflow-trainer check`: the same steps on every backend, compared with the first.
fn check(args: &Args, c: &CheckArgs) -> anyhow::Result<Option<i32>> {
    let steps = args.steps.unwrap_or(3).max(1) as usize;
    let config = args.config()?;
    let batch = BatchFile::read(&c.batch)?;
    let view = batch.view()?;
    tracing::info!(
        batch = %c.batch.display(),
        bytes = batch.bytes(),
        samples = view.meta().sample_count,
        unet = ?config.model.unet,
        vit = ?config.model.vit,
        steps,
        "checking backends on one batch"
    );
    drop(view);
    let mut runs = Vec::new();
    for backend in &c.backends {
        let device = device(backend, args.device_index)?;
        tracing::info!(backend, ?device, "running");
        let run = check::run_backend(backend, &config, &device, &batch, steps)
            .with_context(|| format!("backend {backend}"))?;
        runs.push(run);
    }
    let reference = &runs[0];
    println!(
        "| backend | init s | first step ms | ms / step (after the first) | steps/s | worst relative loss difference vs {} |",
        reference.backend
    );
    println!("|---|---:|---:|---:|---:|---:|");
    let mut worst = 0.0f64;
    let mut json = Vec::new();
    for run in &runs {
        let difference = run.worst_difference(reference);
        worst = worst.max(difference);
        let steady = run.steady_ms();
        println!(
            "| {} | {:.2} | {:.1} | {steady:.1} | {:.2} | {difference:.2e} |",
            run.backend,
            run.init_s,
            run.step_ms[0],
            1e3 / steady
        );
        json.push(serde_json::json!({
            "backend": run.backend,
            "init_s": run.init_s,
            "step_ms": run.step_ms,
            "losses": run.losses,
            "worst_relative_difference": difference,
        }));
    }
    if let Some(path) = &c.json {
        std::fs::write(path, serde_json::to_vec_pretty(&json)?)
            .with_context(|| format!("writing {}", path.display()))?;
    }
    if worst > c.tolerance {
        anyhow::bail!(
            "the backends disagree: a loss differs by {worst:.2e} (relative) from {}'s, more than --tolerance {:.0e}",
            reference.backend,
            c.tolerance
        );
    }
    tracing::info!(
        worst = format_args!("{worst:.2e}"),
        tolerance = c.tolerance,
        "the backends agree"
    );
    Ok(None)
}

/// `superflow-trainer probe`.
fn probe(args: &Args, p: &ProbeArgs) -> anyhow::Result<Option<i32>> {
    let pipeline = match &p.pipeline_config {
        Some(path) => superflow_pipeline::config::PipelineConfig::load(path)?,
        None => superflow_pipeline::config::PipelineConfig::default(),
    };
    let device = device(&args.backend, args.device_index)?;
    let (unet, what) = evaluate::load_backbone(&p.checkpoint, &args.config()?, &device)?;
    tracing::info!(backbone = %what, "probing");
    let dataset = superflow_pipeline::drive::Dataset::open(&p.mcap, &pipeline.ingest)
        .context("opening the drives")?;
    let interval = (p.keyframe_interval_secs * 1e9) as i64;
    let mut data = evaluate::labelled_clouds(&dataset, &pipeline, interval)?;
    let val_from = if p.val_mcap.is_empty() {
        None
    } else {
        let val = superflow_pipeline::drive::Dataset::open(&p.val_mcap, &pipeline.ingest)
            .context("opening the validation drives")?;
        let val = evaluate::labelled_clouds(&val, &pipeline, interval)?;
        let first = data.clouds.len();
        let drives = dataset.drives.len();
        data.clouds.extend(val.clouds.into_iter().map(|mut c| {
            c.time.drive += drives;
            c
        }));
        data.classes = data.classes.max(val.classes);
        Some(first)
    };
    tracing::info!(
        clouds = data.clouds.len(),
        classes = data.classes,
        unlabelled_drives = data.unlabelled_drives,
        "labelled sweeps"
    );
    let settings = evaluate::ProbeSettings {
        classes: data.classes,
        ignore: data.ignore,
        names: data.names,
        val_fraction: p.val_fraction,
        val_from,
        gap_ns: (p.gap_secs * 1e9) as i64,
        label_fraction: p.label_fraction,
        finetune: p.finetune,
        epochs: p.epochs.unwrap_or(if p.finetune { 10 } else { 20 }),
        lr: p.probe_lr.unwrap_or(if p.finetune { 1e-3 } else { 1e-2 }),
        max_train_points: p.max_train_points,
        seed: args.seed.unwrap_or(0),
    };
    let report = evaluate::probe(unet, &data.clouds, &settings, &device)?;
    if p.json {
        let mut value = serde_json::to_value(&report)?;
        value["backbone"] = serde_json::Value::String(what);
        value["protocol"] =
            serde_json::Value::String(if p.finetune { "finetune" } else { "linear" }.into());
        value["label_fraction"] = serde_json::json!(p.label_fraction);
        println!("{}", serde_json::to_string(&value)?);
    } else {
        println!("backbone: {what}");
        println!(
            "mIoU {:.2} % (accuracy {:.2} %) on {} validation points of {} sweeps; trained on {} points of {} sweeps",
            report.miou * 100.0,
            report.accuracy * 100.0,
            report.points.val,
            report.split.val,
            report.points.train,
            report.split.train
        );
        for (name, iou) in &report.per_class {
            println!("  {name:<24} {:6.2} %", iou * 100.0);
        }
    }
    Ok(None)
}

/// mimalloc, keeping the pages it frees (as the pipeline does,
/// `superflow_pipeline::memory`): a step allocates and frees the same hundreds of
/// megabytes of tensors every time.
#[global_allocator]
static ALLOCATOR: superflow_pipeline::memory::Allocator = superflow_pipeline::memory::Allocator;

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
    let args = Args::parse();
    let outcome = match &args.command {
        Some(Sub::Check(c)) => check(&args, c),
        Some(Sub::Probe(p)) => probe(&args, p),
        None => run(&args),
    };
    match outcome {
        Ok(None) => std::process::ExitCode::SUCCESS,
        // Stopped by a signal after checkpointing: not done, so not success.
        Ok(Some(code)) => std::process::ExitCode::from(code as u8),
        Err(err) => {
            eprintln!("superflow-trainer: {err:#}");
            std::process::ExitCode::from(1)
        }
    }
}
