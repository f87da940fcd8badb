//! Building SuperFlow samples (the recipe and its numbers: `pipeline/docs/RECIPE.md`).
//! In the order data flows: a [`SampleConfig`] (the recipe) and a dataset make a
//! [`Plan`] of keyframes with their temporal context; [`SampleBuilder`] turns
//! `(epoch, index)` into a [`Sample`] of temporal [`Frame`]s — each with its
//! [`SampleImage`]s and [`Cloud`] — plus the dense cloud, or a [`SampleError`].
//!
//! * [`recipe`]: the `[sample]` config with the paper's defaults;
//! * [`plan`]: the keyframes and their context sweeps, the epoch's shuffled order;
//! * [`epochs`]: [`EpochMix`], the keyframes of each epoch when dataset groups are
//!   weighted (`repeat`);
//! * [`frames`]: [`FrameCache`], the frames that neighbouring samples share, built once
//!   under the `blocks` order;
//! * [`timing`]: when the LiDAR scans each camera, which matches images to sweeps;
//! * [`builder`]: [`SampleBuilder`], a sample from its loaded parts (`load.rs`: sweeps
//!   and frames; `images.rs`: one camera image with its superpixels; `cloud.rs`: the
//!   dense cloud, pairing, augmentation, voxels and maps);
//! * [`types`]: what a sample is made of, and [`StageTimes`];
//! * [`project`]: LiDAR → camera through the ego poses at both stamps (paper Eq. 1) with
//!   the lens distortion and strict bounds;
//! * [`deskew`]: raw sweeps with per-point time moved to their stamp (exact poses at
//!   knots ≤ 0.25 ms apart, blended between);
//! * [`image_ops`]: bilinear / nearest resize, flips, raw → resized pixel;
//! * [`slic`]: SLIC superpixels when the recording has no class maps;
//! * [`sidecar`]: SLIC computed once per drive into a `<drive>.slic.mcap` sidecar
//!   (`superflow-pipeline superpixels`), read back by samples;
//! * [`augment`]: the 3D augmentation (flip, rotation about z, scale) of a cloud;
//! * [`voxel`]: cylindrical (ρ 0.1 m, φ 1°, z 0.1 m) or cartesian voxelization — unique
//!   cells, a representative point per cell, the point→voxel map (`cylinder.rs`: the
//!   cylindrical cells of a whole cloud, fast and identical to the per-point formula;
//!   `cellkey.rs`: cells packed into sortable `u64` keys);
//! * [`kernel_maps`]: the sparse-convolution maps of every UNet level — 3×3×3 neighbour maps,
//!   stride-2 down-sampling maps and their transposes for up-sampling;
//! * [`rng`]: the keyed random streams that make a sample a function of
//!   `(seed, epoch, index)`;
//! * [`export`]: a sample as `.npy` arrays, `sample.json` and overlay PNGs (and
//!   `crate::view`: as an MCAP file that Foxglove opens).

mod ahead;
pub mod augment;
pub mod builder;
mod cellkey;
mod cloud;
mod cylinder;
pub mod deskew;
pub mod epochs;
mod error;
pub mod export;
pub mod frames;
pub mod image_ops;
mod images;
pub mod kernel_maps;
mod load;
pub mod plan;
pub mod project;
pub mod recipe;
pub mod rng;
pub mod sidecar;
mod simd;
pub mod slic;
pub mod timing;
pub mod types;
pub mod voxel;

pub use augment::Augmentation;
pub use builder::SampleBuilder;
pub use epochs::{Arrangement, EpochMix, EpochOrder};
pub use error::{SampleError, SuperpixelsFault};
pub use frames::FrameCache;
pub use images::CLASS_MAP_TOLERANCE_NANOS;
pub use plan::{KeyframeRef, Plan};
pub use recipe::{KernelMaps, SampleConfig};
pub use types::{Cloud, Frame, Pair, Sample, SampleId, SampleImage, StageTimes};
