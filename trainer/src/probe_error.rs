//! [`ProbeError`]: why a probe cannot run or score. It stands beside the [`probe`](crate::probe)
//! folder, not in it: [`TrainerError`](crate::error::TrainerError) carries it, and the probe's
//! files return that.

/// Why a probe cannot run or score.
#[derive(Debug, thiserror::Error)]
pub enum ProbeError {
    /// A confusion matrix was given unequal numbers of labels and predictions.
    #[error("{labels} labels and {predictions} predictions")]
    Lengths {
        /// Labels given.
        labels: usize,
        /// Predictions given.
        predictions: usize,
    },
    /// A label or prediction names a class past the classes probed.
    #[error("class {class} outside the {classes} classes")]
    Class {
        /// The class found.
        class: usize,
        /// Classes probed.
        classes: usize,
    },
    /// A training label names a class past the classes probed.
    #[error("label {label} outside the {classes} classes")]
    Label {
        /// The label found.
        label: u16,
        /// Classes probed.
        classes: usize,
    },
    /// Every training point carries the ignore index.
    #[error("no labelled training point")]
    NoTrainingPoint,
    /// The feature matrix does not match the points.
    #[error("{values} feature values for {points} points of {dim} features")]
    Features {
        /// Values given.
        values: usize,
        /// Points given.
        points: usize,
        /// Features per point.
        dim: usize,
    },
    /// The split leaves nothing to train on or to score.
    #[error(
        "{clouds} labelled clouds give {train} training and {val} validation clouds: record more, or change the split"
    )]
    EmptySplit {
        /// Labelled clouds.
        clouds: usize,
        /// Training clouds.
        train: usize,
        /// Validation clouds.
        val: usize,
    },
    /// `--checkpoint` names no checkpoint.
    #[error(
        "{checkpoint}: no checkpoint (neither a step-N directory nor a run's checkpoints/ with `latest`); `random` probes an untrained network"
    )]
    NoCheckpoint {
        /// What `--checkpoint` said.
        checkpoint: String,
    },
    /// A drive's labels cannot be opened or read.
    #[cfg(feature = "probe")]
    #[error("labels of {drive}: {error}")]
    Labels {
        /// The drive's files.
        drive: String,
        /// The pipeline's error.
        error: superflow_pipeline::drive::labels::LabelError,
    },
    /// A labelled sweep cannot be de-skewed.
    #[cfg(feature = "probe")]
    #[error("{drive}: de-skew of {topic} at {stamp}: {error}")]
    Deskew {
        /// The drive's files.
        drive: String,
        /// The LiDAR topic.
        topic: String,
        /// The sweep's stamp.
        stamp: superflow_schemas::Stamp,
        /// The transform lookup's error.
        error: superflow_pipeline::drive::tf::TfError,
    },
}
