//! [`RunError`]: why a run stops with an error, and [`ResumeRefused`]: why the pipeline
//! did not continue a stream where a trainer asked. A leaf of the folder: the start, the
//! job and the session all return it.
//!
//! A variant that wraps a cause says what the run was doing; the cause is its
//! [`source`](std::error::Error::source), printed after it by a printer of the whole
//! chain (`superflow_common::exit::describe`, as the binary prints).

use crate::device::BackendError;
use crate::error::TrainerError;
use crate::stream::{PlanMismatch, StreamPosition};
use crate::subscribe::{ResumeAt, SubscribeError};
use std::path::PathBuf;
use superflow_schemas::batch::BatchError;
use superflow_schemas::service::{ResumeReply, ServiceSetupError};

/// Why a training run stops with an error.
#[derive(Debug, thiserror::Error)]
pub enum RunError {
    /// `--rank` is not below `--world-size`.
    #[error("--rank {rank} is not below --world-size {world_size}")]
    RankOutOfRange {
        /// `--rank`.
        rank: u32,
        /// `--world-size`.
        world_size: u32,
    },
    /// `--ddp` in a build without MPI.
    #[cfg(not(feature = "mpi"))]
    #[error(
        "--ddp needs MPI, and this superflow-trainer was built without its `mpi` feature \
         (install Open MPI and libclang: apt-get install libopenmpi-dev openmpi-bin libclang-dev, \
         then build with the default features)"
    )]
    NoMpi,
    /// The iceoryx2 configuration (`--iox-prefix`) cannot be made.
    #[error(transparent)]
    Iceoryx(#[from] ServiceSetupError),
    /// The SIGTERM/SIGINT handlers cannot be installed.
    #[error("installing the SIGTERM/SIGINT handlers")]
    Signals(#[source] std::io::Error),
    /// The run's stream cannot be subscribed to.
    #[error("subscribing to run {run}")]
    Subscribe {
        /// The run.
        run: String,
        /// What failed.
        #[source]
        source: SubscribeError,
    },
    /// Receiving a batch, or asking the pipeline for its schedule, failed.
    #[error(transparent)]
    Stream(#[from] SubscribeError),
    /// No batch arrived within `--timeout-secs`.
    #[error(
        "no batch from run {run} within {secs} s (is superflow-pipeline running with --run {run}?)"
    )]
    NoBatch {
        /// The run.
        run: String,
        /// How long the trainer waited, seconds.
        secs: u64,
    },
    /// A request to continue the stream got no answer, or could not be sent.
    #[error("asking run {run} to resume")]
    AskResume {
        /// The run.
        run: String,
        /// What failed.
        #[source]
        source: SubscribeError,
    },
    /// The pipeline answered a request to continue the stream with a refusal.
    #[error(transparent)]
    Resume(#[from] ResumeRefused),
    /// The `--backend` cannot run here.
    #[error(transparent)]
    Backend(#[from] BackendError),
    /// The trainer library failed (files, configuration, checkpoints, MPI).
    #[error(transparent)]
    Trainer(#[from] TrainerError),
    /// Reading or removing a file failed.
    #[error("{action} {}", path.display())]
    Io {
        /// What was done: `reading` or `replacing`.
        action: &'static str,
        /// The file.
        path: PathBuf,
        /// The I/O error.
        #[source]
        source: std::io::Error,
    },
    /// A fresh run in an output directory that holds checkpoints.
    #[error(
        "{} already holds checkpoints: pass --resume to continue that run, or choose another --out",
        dir.display()
    )]
    HoldsCheckpoints {
        /// The checkpoint directory.
        dir: PathBuf,
    },
    /// Rank 0's decision of how the job starts cannot be encoded.
    #[error(transparent)]
    EncodeJobStart(serde_json::Error),
    /// Rank 0's decision of how the job starts cannot be decoded.
    #[error("rank 0's job start")]
    DecodeJobStart(#[source] serde_json::Error),
    /// Rank 0 could not start the job (another process: its message, with its causes).
    #[error("rank 0 could not start the job: {0}")]
    FirstRank(String),
    /// This rank's configuration is not rank 0's.
    #[error(
        "rank {rank}'s configuration differs from rank 0's: give every rank the same trainer.toml and flags"
    )]
    ConfigDiffers {
        /// This rank.
        rank: usize,
    },
    /// A data-parallel checkpoint that counts no samples, resumed by a job of another size.
    #[error(
        "the checkpoint at step {step} was written by a job of {ranks} data-parallel ranks and does not count the samples it consumed; resume it with mpirun -np {}",
        .ranks.max(&1)
    )]
    UncountedCheckpoint {
        /// The checkpoint's step.
        step: u64,
        /// The ranks of the job that wrote it.
        ranks: usize,
    },
    /// Other ranks could not resume.
    #[error("rank(s) {ranks:?} could not resume (their logs say why): this rank stops with them")]
    RanksCannotResume {
        /// The ranks that failed.
        ranks: Vec<usize>,
    },
    /// Some ranks' pipelines found the run complete, others did not.
    #[error(
        "the pipelines of rank(s) {complete:?} found the run complete and those of rank(s) {incomplete:?} did not: every host's pipeline needs the same --epochs, drives and configuration"
    )]
    CompletionDiffers {
        /// Ranks whose pipelines found the run complete.
        complete: Vec<usize>,
        /// Ranks whose pipelines continued.
        incomplete: Vec<usize>,
    },
    /// The ranks' pipelines serve different plans.
    #[error(transparent)]
    Plans(#[from] PlanMismatch),
    /// A received batch cannot be read.
    #[error("invalid batch")]
    InvalidBatch(#[source] BatchError),
    /// A lone trainer's step without a batch.
    #[error("step {step}: no batch")]
    NoBatchForStep {
        /// The step (1-based).
        step: u64,
    },
    /// A step failed.
    #[error("step {step} ({at})")]
    Step {
        /// The step (1-based).
        step: u64,
        /// Where its batch lies in the stream.
        at: StreamPosition,
        /// What failed (boxed: the other variants are smaller).
        #[source]
        source: Box<TrainerError>,
    },
    /// A checkpoint asked for before any step.
    #[error("a checkpoint before the first step")]
    CheckpointBeforeFirstStep,
}

/// Why the pipeline did not continue a stream where a trainer asked.
#[derive(Debug, Clone, PartialEq, Eq, thiserror::Error)]
pub enum ResumeRefused {
    /// The position is at or past the end of the pipeline's epochs: a finished run (a
    /// requeued job, a `--resume` after the last step). Nothing is wrong; there is
    /// nothing to do.
    #[error("the run is complete ({epochs} epochs): nothing left to train")]
    RunComplete {
        /// The epochs the pipeline serves.
        epochs: u64,
    },
    /// Any other refusal: the position or stream does not fit this pipeline.
    #[error("the pipeline refused to resume run {run} at {position}: {why}")]
    Refused {
        /// The run.
        run: String,
        /// The position asked for, in words.
        position: String,
        /// `ResumeReply::reason`.
        reason: u32,
        /// What the reason means and what to check.
        why: String,
    },
}

impl ResumeRefused {
    /// The refusal `reply` of a request to continue `run` at `at`.
    pub fn of(run: &str, at: ResumeAt, reply: &ResumeReply) -> Self {
        if reply.reason == ResumeReply::RUN_COMPLETE {
            return Self::RunComplete {
                epochs: reply.epoch,
            };
        }
        let position = match at {
            ResumeAt::Step { epoch, step } => format!("epoch {epoch} batch {step}"),
            ResumeAt::Sample { epoch, sample, .. } => {
                format!("epoch {epoch} after {sample} samples")
            }
        };
        let why = match reply.reason {
            ResumeReply::NO_SUCH_STREAM => {
                "no such stream: another --world-size or --mode?".to_string()
            }
            ResumeReply::OUT_OF_RANGE => {
                "no such position in its epochs: is it the same recording and configuration?"
                    .to_string()
            }
            ResumeReply::OTHER_JOB_SIZE => "the position was saved by a job of another size: \
                resume by sample (start the pipeline with --start-sample, from a checkpoint \
                that counts samples)"
                .to_string(),
            other => format!("reason {other}"),
        };
        Self::Refused {
            run: run.to_string(),
            position,
            reason: reply.reason,
            why,
        }
    }
}

impl RunError {
    /// The epochs of a finished run, when this error says the pipeline found the run
    /// complete ([`ResumeRefused::RunComplete`]): not a failure, the stream has ended.
    pub fn run_complete(&self) -> Option<u64> {
        match self {
            Self::Resume(ResumeRefused::RunComplete { epochs }) => Some(*epochs),
            _ => None,
        }
    }

    /// An I/O error of `action` on `path`.
    pub fn io(action: &'static str, path: impl Into<PathBuf>, source: std::io::Error) -> Self {
        Self::Io {
            action,
            path: path.into(),
            source,
        }
    }
}
