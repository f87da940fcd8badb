//! A training run as `superflow-trainer` runs it: subscribe to the run's stream, start
//! (fresh, resumed, or as rank 0 of a data-parallel job decides), step until the run's
//! length, the end of the stream or a stop signal, checkpoint, and summarize.
//!
//! * [`RunOptions`]: what the command line says about the run (not the networks: those
//!   are the [`TrainerConfig`]);
//! * [`paths`]: where the run's files go;
//! * [`start`]: fresh start, `--resume`, and the data-parallel start;
//! * [`job`]: joining the MPI job (`--ddp`);
//! * [`session`]: the step loop, the periodic and final checkpoints;
//! * [`signals`]: SIGTERM/SIGINT end the run after the step in progress.

pub mod job;
pub mod paths;
pub mod session;
pub mod signals;
pub mod start;

use crate::config::TrainerConfig;
use crate::device;
use crate::metrics::MetricsWriter;
use crate::stream::StreamTracker;
use crate::subscribe::{Subscription, Target};
use crate::train::Trainer;
use anyhow::Context as _;
use job::{Ddp, join_job};
use paths::RunPaths;
use session::{Session, progress_bar};
use signals::watch_signals;
use start::{resume, start_fresh, start_ranks};
use std::path::PathBuf;
use std::time::Instant;

/// What the command line says about a run besides its configuration.
#[derive(Debug, Clone)]
pub struct RunOptions {
    /// Run name of the pipeline to subscribe to.
    pub run: String,
    /// Data-parallel rank (shard mode) ...
    pub rank: Option<u32>,
    /// ... out of this many ranks.
    pub world_size: Option<u32>,
    /// Output directory [default: `runs/<run>` or `runs/<run>-rank<r>`].
    pub out: Option<PathBuf>,
    /// Continue from the newest checkpoint in the output directory.
    pub resume: bool,
    /// Write `losses.svg` at the end.
    pub plot: bool,
    /// Give up when no batch arrives for this long, seconds.
    pub timeout_secs: u64,
    /// Synchronous data parallelism over MPI.
    pub ddp: bool,
    /// `--ddp`: abort when a collective waits longer than this, seconds.
    pub collective_timeout_secs: u64,
    /// Isolates a deployment's iceoryx2 resources.
    pub iox_prefix: Option<String>,
    /// Compute backend: flex, wgpu, cuda.
    pub backend: String,
    /// GPU index for cuda.
    pub device_index: usize,
}

impl RunOptions {
    /// `--rank` must be below `--world-size`.
    pub fn check_rank(&self) -> anyhow::Result<()> {
        if let (Some(rank), Some(world)) = (self.rank, self.world_size)
            && rank >= world
        {
            anyhow::bail!("--rank {rank} is not below --world-size {world}");
        }
        Ok(())
    }

    /// The output directory: `--out`, or `runs/<run>` (`runs/<run>-rank<r>` for a shard).
    pub fn out_dir(&self) -> PathBuf {
        self.out.clone().unwrap_or_else(|| {
            let name = match self.rank {
                Some(r) => format!("{}-rank{r}", self.run),
                None => self.run.clone(),
            };
            PathBuf::from("runs").join(name)
        })
    }
}

/// Trains with `config`; `Some(code)` when stopped early by a signal (after a
/// checkpoint).
pub fn train(options: &RunOptions, config: TrainerConfig) -> anyhow::Result<Option<i32>> {
    options.check_rank()?;
    let ddp = join_job(options)?;
    let iox = superflow_schemas::service::iceoryx2_config(options.iox_prefix.as_deref())
        .map_err(|e| anyhow::anyhow!(e))?;
    let stop = watch_signals().context("installing the SIGTERM/SIGINT handlers")?;
    let target = match &ddp {
        Some(ddp) => Target::Rank(ddp.local_rank() as u32),
        None => options.rank.map_or(Target::Broadcast, Target::Rank),
    };
    let subscription = Subscription::open(&options.run, target, &iox, 2)
        .with_context(|| format!("subscribing to run {}", options.run))?;
    let paths = RunPaths::new(options.out_dir(), &config, ddp.as_ref().map(Ddp::rank));
    let (steps, every) = (config.optim.steps, config.checkpoint.every);
    let device = device::select(&options.backend, options.device_index)?;
    tracing::info!(backend = %options.backend, ?device, "compute device");
    let mut trainer = Trainer::new(config, &device)?;
    let resumed_at = match &ddp {
        Some(ddp) => start_ranks(options, &mut trainer, &subscription, &paths, ddp)?,
        None if options.resume => resume(options, &mut trainer, &subscription, &paths)?,
        None => {
            start_fresh(&paths, true)?;
            None
        }
    };
    let metrics = MetricsWriter::open(&paths.metrics)?;
    let bar = progress_bar(steps, trainer.step_count());
    let mut session = Session {
        options,
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
    tracing::info!(run = %options.run, ?target, steps, out = %session.paths.out.display(), "training");
    session.train()?;
    session.finish()
}

#[cfg(test)]
mod tests {
    use super::*;

    fn options(run: &str, rank: Option<u32>, world_size: Option<u32>) -> RunOptions {
        RunOptions {
            run: run.into(),
            rank,
            world_size,
            out: None,
            resume: false,
            plot: false,
            timeout_secs: 300,
            ddp: false,
            collective_timeout_secs: 900,
            iox_prefix: None,
            backend: "flex".into(),
            device_index: 0,
        }
    }

    #[test]
    fn the_output_directory_is_named_after_the_run_and_the_shard() {
        assert_eq!(options("a", None, None).out_dir(), PathBuf::from("runs/a"));
        assert_eq!(
            options("a", Some(2), Some(4)).out_dir(),
            PathBuf::from("runs/a-rank2")
        );
        let mut o = options("a", Some(2), Some(4));
        o.out = Some(PathBuf::from("/data/out"));
        assert_eq!(o.out_dir(), PathBuf::from("/data/out"));
        assert!(o.check_rank().is_ok());
        let err = options("a", Some(4), Some(4))
            .check_rank()
            .expect_err("rank 4 of 4");
        assert_eq!(err.to_string(), "--rank 4 is not below --world-size 4");
    }
}
