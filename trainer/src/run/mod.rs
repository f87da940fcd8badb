//! A training run as `superflow-trainer` runs it: subscribe to the run's stream, start
//! (fresh, resumed, or as rank 0 of a data-parallel job decides), step until the run's
//! length, the end of the stream or a stop signal, checkpoint, and summarize.
//!
//! * [`options`]: [`RunOptions`], what the command line says about the run (not the
//!   networks: those are the [`TrainerConfig`]);
//! * [`paths`]: where the run's files go;
//! * [`start`]: fresh start, `--resume`, and the data-parallel start;
//! * [`error`]: [`RunError`], why a run stops with an error;
//! * [`job`]: joining the MPI job (`--ddp`);
//! * [`session`]: the step loop, the periodic and final checkpoints;
//! * [`signals`]: SIGTERM/SIGINT end the run after the step in progress.

pub mod error;
pub mod job;
pub mod options;
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
use job::{Ddp, join_job};
use paths::RunPaths;
use session::{Session, progress_bar};
use signals::watch_signals;
use start::{resume, run_complete, start_fresh, start_ranks};
use std::time::Instant;

pub use error::{ResumeRefused, RunError};
pub use options::RunOptions;

/// Trains with `config`; `Some(code)` when stopped early by a signal (after a
/// checkpoint). Resuming a run whose pipeline has served all its epochs (a requeued job
/// of a finished run) is not a failure: it says so and returns `Ok(None)` at once.
pub fn train(options: &RunOptions, config: TrainerConfig) -> Result<Option<i32>, RunError> {
    options.check_rank()?;
    let ddp = join_job(options)?;
    let iox = superflow_schemas::service::iceoryx2_config(options.iox_prefix.as_deref())?;
    let stop = watch_signals().map_err(RunError::Signals)?;
    let target = match &ddp {
        Some(ddp) => Target::Rank(ddp.local_rank() as u32),
        None => options.rank.map_or(Target::Broadcast, Target::Rank),
    };
    let subscription = Subscription::open(&options.run, target, &iox, 2).map_err(|source| {
        RunError::Subscribe {
            run: options.run.clone(),
            source,
        }
    })?;
    let paths = RunPaths::new(options.out_dir(), &config, ddp.as_ref().map(Ddp::rank));
    let (steps, every) = (config.optim.steps, config.checkpoint.every);
    let device = device::select(options.backend, options.device_index)?;
    tracing::info!(backend = %options.backend, ?device, "compute device");
    let mut trainer = Trainer::new(config, &device)?;
    let started = match &ddp {
        Some(ddp) => start_ranks(options, &mut trainer, &subscription, &paths, ddp),
        None if options.resume => resume(options, &mut trainer, &subscription, &paths),
        None => start_fresh(&paths, true).map(|()| None),
    };
    let resumed_at = match started {
        Ok(at) => at,
        Err(e) if run_complete(&e).is_some() => {
            tracing::info!(run = %options.run, step = trainer.step_count(), "{e}");
            return Ok(None);
        }
        Err(e) => return Err(e),
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
        schedule: None,
        unscheduled: Vec::new(),
        ended: false,
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
    let outcome = session.train().and_then(|()| session.finish());
    device::settle(&device);
    outcome
}
