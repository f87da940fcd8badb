//! Building SuperFlow samples (in progress, see the sample-builder issue). Done so far:
//!
//! * [`voxel`]: cylindrical (ρ 0.1 m, φ 1°, z 0.1 m, the paper's) or cartesian
//!   voxelization — unique cells, a representative point per cell, the point→voxel map;
//! * [`sparse`]: the sparse-convolution maps of every UNet level — 3×3×3 neighbour maps,
//!   stride-2 down-sampling maps and their transposes for up-sampling — so the trainer
//!   only gathers, multiplies and scatters;
//! * [`project`]: LiDAR → camera through the ego poses at both stamps (paper Eq. 1) with
//!   the lens distortion and strict bounds, and per-point de-skew of raw sweeps.

pub mod project;
pub mod sparse;
pub mod voxel;
