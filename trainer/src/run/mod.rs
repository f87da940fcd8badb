//! A training run as `superflow-trainer` runs it: subscribe to the run's stream, start
//! (fresh, resumed, or as rank 0 of a data-parallel job decides), step until the run's
//! length, the end of the stream or a stop signal, checkpoint, and summarize.
//!
//! * [`options`]: [`RunOptions`], what the command line says about the run (not the
//!   networks: those are the [`TrainerConfig`]);
//! * [`paths`]: where the run's files go;
//! * [`start`]: how the run begins ([`start::begin`]): fresh, `--resume`, or the
//!   data-parallel start;
//! * [`resume`]: asking the pipeline where the stream continues (a resumed start, a
//!   pipeline restarted under a running session);
//! * [`error`]: [`RunError`], why a run stops with an error;
//! * [`job`]: joining the MPI job (`--ddp`);
//! * [`session`]: the step loop, the periodic and final checkpoints;
//! * [`signals`]: SIGTERM/SIGINT end the run after the step in progress.

pub mod error;
pub mod job;
pub mod options;
pub mod paths;
pub mod resume;
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
use start::{Begun, begin};
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
    let resumed_at = match begin(options, &mut trainer, &subscription, &paths, ddp.as_ref())? {
        Begun::At(at) => at,
        Begun::RunComplete => return Ok(None),
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
