//! One LiDAR sweep as the 3D backbone takes it outside training: voxelized with the
//! recipe's grid, its levels of kernel maps built, no augmentation — what `probe` scores
//! and `features` looks at.

use crate::rows::RowOps;
use crate::unet::{LevelMaps, SparseUNet};
use burn::tensor::{Device, Tensor, TensorData};
use superflow_pipeline::sample::SampleConfig;
use superflow_pipeline::sample::kernel_maps::{Level, build_levels};
use superflow_pipeline::sample::voxel::voxelize;

/// A sweep ready for the backbone.
#[derive(Debug, Clone)]
pub struct SweepInput {
    /// `[x, y, z, intensity]` of each voxel's representative point (the pretraining input).
    pub voxel_features: Vec<[f32; 4]>,
    /// Kernel maps of the UNet's levels, finest first.
    pub levels: Vec<Level>,
    /// The voxel of each point.
    pub point_to_voxel: Vec<u32>,
}

impl SweepInput {
    /// Voxels and maps of the points `xyz` (intensities `intensity`) by `recipe`.
    pub fn prepare(xyz: &[[f32; 3]], intensity: &[f32], recipe: &SampleConfig) -> Self {
        let voxels = voxelize(xyz, &recipe.voxel);
        let voxel_features = voxels
            .representative
            .iter()
            .map(|&i| {
                let [x, y, z] = xyz[i as usize];
                [x, y, z, intensity[i as usize]]
            })
            .collect();
        let levels = build_levels(&voxels.coords, recipe.unet_levels as usize);
        Self {
            voxel_features,
            levels,
            point_to_voxel: voxels.point_to_voxel,
        }
    }

    /// The backbone's inputs on `device`: voxel features and level maps.
    pub fn inputs(&self, device: &Device) -> (Tensor<2>, Vec<LevelMaps>) {
        let v = self.voxel_features.len();
        let features = Tensor::from_data(
            TensorData::new(self.voxel_features.concat(), [v, 4]),
            device,
        );
        let levels = self
            .levels
            .iter()
            .map(|level| {
                LevelMaps::from_host(
                    level.coords.len(),
                    bytemuck::cast_slice(&level.neighbours.pairs),
                    &level.neighbours.starts,
                    level
                        .down
                        .as_ref()
                        .map(|d| (bytemuck::cast_slice(&d.pairs), &d.starts[..])),
                    device,
                )
            })
            .collect();
        (features, levels)
    }

    /// `unet`'s backbone features of every point (its voxel's), on `device`.
    pub fn point_features(&self, unet: &SparseUNet, device: &Device) -> Tensor<2> {
        let (features, levels) = self.inputs(device);
        let index: Vec<i64> = self.point_to_voxel.iter().map(|&i| i64::from(i)).collect();
        let n = index.len();
        let index = Tensor::from_data(TensorData::new(index, [n]), device);
        RowOps::of(device).gather(unet.backbone(features, &levels), &index)
    }
}
