//! `superflow-trainer probe`: what a pretrained 3D backbone is worth downstream —
//! per-point semantic segmentation of labelled LiDAR sweeps, scored by mIoU (the
//! paper's linear-probing and few-label fine-tuning protocols, on the recordings a user
//! has).
//!
//! 1. **Clouds**: the labelled sweeps of every drive, thinned to one per
//!    `keyframe_interval` (nuScenes labels its 2 Hz keyframes), each decoded and
//!    de-skewed exactly as the pipeline prepares a pretraining sweep, voxelized with the
//!    recipe's grid, its 5 levels of kernel maps built, without augmentation. No camera is
//!    read.
//! 2. **Split** by time within each drive ([`linear::split_by_time`]): train, a guard gap,
//!    validation; `label_fraction` keeps that share of the training clouds.
//! 3. **Linear probe** (default): the backbone frozen (BatchNorm with its running
//!    statistics), per-point features = the last decoder stage's features of the point's
//!    voxel, a linear classifier trained on them ([`linear::LinearProbe`]).
//!    **Fine-tuning** (`finetune`): backbone and a linear classifier trained together with
//!    cross-entropy, cloud by cloud.
//! 4. **Score**: mIoU and per-class IoU over the validation clouds' labelled points.

//!
//! [`linear`] holds the pieces that do not depend on where the features come from (the
//! split, the linear classifier, the confusion matrix, the report); [`evaluate`] (the
//! `probe` cargo feature, on by default) reads the drives with the pipeline and runs the
//! protocols.

#[cfg(feature = "probe")]
pub mod evaluate;
pub mod linear;

pub use crate::probe_error::ProbeError;

#[cfg(feature = "probe")]
pub use evaluate::{
    LabelledData, ProbeCloud, ProbeSettings, labelled_clouds, load_backbone, probe,
};
pub use linear::{ConfusionMatrix, LinearProbe, ProbeReport};
