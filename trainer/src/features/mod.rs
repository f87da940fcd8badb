//! What a backbone learned, to look at: per-point features coloured by their principal
//! components, and their similarity to one point (`superflow-trainer features`).
//!
//! * [`pca`]: the top three principal components of features, as colours; cosine
//!   similarity;
//! * [`drive_view`] (the `probe` feature: it reads drives with the pipeline): a drive's
//!   keyframe sweeps through a backbone, written as Foxglove point clouds;
//! * [`images`] (the `probe` feature): the keyframes' camera images through the frozen
//!   ViT, its patch features as colours.

#[cfg(feature = "probe")]
pub mod drive_view;
#[cfg(feature = "probe")]
pub mod images;
pub mod pca;

#[cfg(feature = "probe")]
pub use drive_view::{
    FeatureReport, FeatureSettings, FeaturesError, ImageSettings, write_features,
};
pub use pca::{Pca, PcaError, cosine_similarity};
