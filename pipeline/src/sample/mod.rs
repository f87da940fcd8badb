//! Building SuperFlow samples (`../shared/DESIGN.md` §3): a [`builder::Plan`] of
//! keyframes with their temporal context, and [`builder::SampleBuilder`] that turns
//! `(epoch, index)` into a [`builder::Sample`].
//!
//! * [`recipe`]: the `[sample]` config with the paper's defaults;
//! * [`project`]: LiDAR → camera through the ego poses at both stamps (paper Eq. 1) with
//!   the lens distortion and strict bounds, and per-point de-skew of raw sweeps;
//! * [`image_ops`]: bilinear / nearest resize, flips, raw → resized pixel;
//! * [`slic`]: SLIC superpixels when the recording has no class maps;
//! * [`voxel`]: cylindrical (ρ 0.1 m, φ 1°, z 0.1 m) or cartesian voxelization — unique
//!   cells, a representative point per cell, the point→voxel map;
//! * [`sparse`]: the sparse-convolution maps of every UNet level — 3×3×3 neighbour maps,
//!   stride-2 down-sampling maps and their transposes for up-sampling;
//! * [`rng`]: the keyed random streams that make a sample a function of
//!   `(seed, epoch, index)`;
//! * [`export`]: a sample as `.npy` arrays, `sample.json` and overlay PNGs.

pub mod builder;
pub mod export;
pub mod image_ops;
pub mod project;
pub mod recipe;
pub mod rng;
pub mod slic;
pub mod sparse;
pub mod voxel;

pub use builder::{Plan, Sample, SampleBuilder, SampleError};
pub use recipe::SampleConfig;
