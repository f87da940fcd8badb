//! The trainer library's errors: [`TrainerError`] for a run's files, configuration, batches
//! and checkpoints; a setting out of range is an [`InvalidSetting`] (shared with the
//! pipeline, from `superflow-common`).
//!
//! Every message names the file (and line) or the setting at fault; a typed cause is the
//! error's [`source`](std::error::Error::source), not part of its message: a printer of
//! the whole chain (`superflow_common::exit::describe`, as the binary prints) shows it
//! after a `: `.

use crate::inputs::InputError;
use crate::probe_error::ProbeError;
use crate::vit::WeightsError;
use burn::store::RecordError;
use std::path::PathBuf;
use superflow_schemas::batch::BatchError;

pub use superflow_common::InvalidSetting;

/// A failure of the trainer library.
#[derive(Debug, thiserror::Error)]
pub enum TrainerError {
    /// Reading, writing, creating, renaming or syncing a file or directory failed.
    #[error("{action} {}", path.display())]
    Io {
        /// What was done, such as `reading` or `checkpoint: renaming into`.
        action: &'static str,
        /// The file or directory.
        path: PathBuf,
        /// The I/O error.
        #[source]
        error: std::io::Error,
    },
    /// A JSON file does not parse (or could not be written).
    #[error("{}", path.display())]
    Json {
        /// The file.
        path: PathBuf,
        /// The parse error.
        #[source]
        error: serde_json::Error,
    },
    /// A line of a JSON-lines file does not parse.
    #[error("{}:{line}", path.display())]
    JsonLine {
        /// The file.
        path: PathBuf,
        /// The line, 1-based.
        line: usize,
        /// The parse error.
        #[source]
        error: serde_json::Error,
    },
    /// trainer.toml does not parse (or names an unknown field).
    #[error("{}", path.display())]
    Toml {
        /// The file.
        path: PathBuf,
        /// The parse error.
        #[source]
        error: toml::de::Error,
    },
    /// A setting out of range.
    #[error(transparent)]
    Config(#[from] InvalidSetting),
    /// A setting out of range in a configuration file.
    #[error("{}", path.display())]
    ConfigFile {
        /// The file.
        path: PathBuf,
        /// The setting.
        #[source]
        error: InvalidSetting,
    },
    /// A checkpoint's `state.json` has another format tag.
    #[error("{}: format {found:?}, expected {expected:?}", path.display())]
    CheckpointFormat {
        /// The `state.json`.
        path: PathBuf,
        /// Its format tag.
        found: String,
        /// [`checkpoint::FORMAT`](crate::checkpoint::FORMAT).
        expected: &'static str,
    },
    /// A checkpoint's model or optimizer record cannot be loaded.
    #[error("{}", path.display())]
    Record {
        /// The record file.
        path: PathBuf,
        /// burn's error.
        #[source]
        error: RecordError,
    },
    /// The model or the optimizer cannot be encoded for a checkpoint.
    #[error("checkpoint: encoding the {what}")]
    Encode {
        /// `model` or `optimizer`.
        what: &'static str,
        /// burn's error.
        #[source]
        error: RecordError,
    },
    /// The 2D network's weights cannot be loaded.
    #[error(transparent)]
    Weights(#[from] WeightsError),
    /// A batch cannot be trained on.
    #[error(transparent)]
    Batch(#[from] InputError),
    /// A step's loss is NaN or infinite.
    #[error("loss is {loss} at step {step} (epoch {epoch}, batch {batch})")]
    NonFiniteLoss {
        /// The loss.
        loss: f64,
        /// The step (1-based).
        step: u64,
        /// Epoch of the batch.
        epoch: u64,
        /// Batch in the epoch.
        batch: u64,
    },
    /// A batch file (`superflow-pipeline batch`) too short for a batch header.
    #[error("batch file {}: {bytes} bytes: shorter than a batch header", path.display())]
    BatchFileTooShort {
        /// The file.
        path: PathBuf,
        /// Its size.
        bytes: usize,
    },
    /// A batch file (`superflow-pipeline batch`) whose batch cannot be read.
    #[error("batch file {}", path.display())]
    BatchFile {
        /// The file.
        path: PathBuf,
        /// What is wrong.
        #[source]
        error: BatchError,
    },
    /// The downstream probe (`superflow-trainer probe`).
    #[error("probe")]
    Probe(#[source] Box<ProbeError>),
    /// `--ddp` in a process whose MPI was initialized already.
    #[error("MPI: MPI was initialized already")]
    MpiInitialized,
    /// A data-parallel step without a batch on this rank was run without the other
    /// ranks' gradients to apply.
    #[error(
        "data-parallel ranks disagree: a step without a batch needs the other ranks' gradients"
    )]
    StepWithoutBatch,
    /// A plot of a run without steps.
    #[error("no steps to plot")]
    NothingToPlot,
}

/// Boxed: a probe's error would make every `TrainerError` larger.
impl From<ProbeError> for TrainerError {
    fn from(error: ProbeError) -> Self {
        Self::Probe(Box::new(error))
    }
}

impl TrainerError {
    /// An I/O error of `action` on `path`.
    pub fn io(action: &'static str, path: impl Into<PathBuf>, error: std::io::Error) -> Self {
        Self::Io {
            action,
            path: path.into(),
            error,
        }
    }
}
