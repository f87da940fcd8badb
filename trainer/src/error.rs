//! The trainer library's errors: [`TrainerError`] for a run's files, configuration, batches
//! and checkpoints, and [`InvalidConfig`], the one error of a setting out of range.
//!
//! Every message is complete on its own — it names the file (and line) or the setting at
//! fault and includes the cause's text — so the causes are not chained again as
//! [`source`](std::error::Error::source): printed with `{:#}` (anyhow) each shows once.

use crate::inputs::InputError;
use crate::vit::WeightsError;
use burn::store::RecordError;
use std::fmt;
use std::path::PathBuf;

/// A setting out of range: which one (its path in trainer.toml, such as `optim.steps`, or
/// `vit.<field>` for a [`VitConfig`](crate::vit::VitConfig)), the value found and the rule
/// it breaks. Shown as `setting = value rule`.
#[derive(Debug, Clone, PartialEq, Eq, thiserror::Error)]
#[error("{setting} = {value} {rule}")]
pub struct InvalidConfig {
    /// The setting.
    pub setting: &'static str,
    /// The value found, as written.
    pub value: String,
    /// What it must be.
    pub rule: &'static str,
}

impl InvalidConfig {
    /// `setting = value rule`, e.g. `("loss.pixel_stride", 0, "must be at least 1")`.
    pub fn new(setting: &'static str, value: impl fmt::Display, rule: &'static str) -> Self {
        Self {
            setting,
            value: value.to_string(),
            rule,
        }
    }
}

/// A failure of the trainer library.
#[derive(Debug, thiserror::Error)]
pub enum TrainerError {
    /// Reading, writing, creating, renaming or syncing a file or directory failed.
    #[error("{action} {}: {error}", path.display())]
    Io {
        /// What was done, such as `reading` or `checkpoint: renaming into`.
        action: &'static str,
        /// The file or directory.
        path: PathBuf,
        /// The I/O error.
        error: std::io::Error,
    },
    /// A JSON file does not parse (or could not be written).
    #[error("{}: {error}", path.display())]
    Json {
        /// The file.
        path: PathBuf,
        /// The parse error.
        error: serde_json::Error,
    },
    /// A line of a JSON-lines file does not parse.
    #[error("{}:{line}: {error}", path.display())]
    JsonLine {
        /// The file.
        path: PathBuf,
        /// The line, 1-based.
        line: usize,
        /// The parse error.
        error: serde_json::Error,
    },
    /// trainer.toml does not parse (or names an unknown field).
    #[error("{}: {error}", path.display())]
    Toml {
        /// The file.
        path: PathBuf,
        /// The parse error.
        error: toml::de::Error,
    },
    /// A setting out of range.
    #[error(transparent)]
    Config(#[from] InvalidConfig),
    /// A setting out of range in a configuration file.
    #[error("{}: {error}", path.display())]
    ConfigFile {
        /// The file.
        path: PathBuf,
        /// The setting.
        error: InvalidConfig,
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
    #[error("{}: {error}", path.display())]
    Record {
        /// The record file.
        path: PathBuf,
        /// burn's error.
        error: RecordError,
    },
    /// The model or the optimizer cannot be encoded for a checkpoint.
    #[error("checkpoint: encoding the {what}: {error}")]
    Encode {
        /// `model` or `optimizer`.
        what: &'static str,
        /// burn's error.
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
    /// A batch file (`superflow-pipeline batch`) that cannot be used.
    #[error("batch file {}: {reason}", path.display())]
    BatchFile {
        /// The file.
        path: PathBuf,
        /// What is wrong.
        reason: String,
    },
    /// The downstream probe (`superflow-trainer probe`).
    #[error("probe: {0}")]
    Probe(String),
    /// The MPI job (`--ddp`).
    #[error("MPI: {0}")]
    Mpi(String),
    /// Ranks of a data-parallel job disagree.
    #[error("data-parallel ranks disagree: {0}")]
    Ranks(String),
    /// A plot of a run without steps.
    #[error("no steps to plot")]
    NothingToPlot,
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
