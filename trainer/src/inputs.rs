//! A received batch → the tensors of one training step, on the chosen device: one
//! transfer per section (plus the host-side index plan of the losses).

use crate::loss::{LossInputs, LossPlan, PlanError};
use crate::model::PixelSampler;
use crate::sparse::{LevelMaps, UNetConfig, index_tensor};
use burn::tensor::{Device, Int, Tensor, TensorData};
use superflow_schemas::batch::{BatchError, BatchView};

/// ViT patch size: images must be multiples of it.
pub const PATCH: usize = 14;

/// Why a batch cannot be trained on.
#[derive(Debug, thiserror::Error)]
pub enum InputError {
    /// A section is missing, of the wrong type or shape.
    #[error(transparent)]
    Batch(#[from] BatchError),
    /// The sections disagree with each other.
    #[error(transparent)]
    Plan(#[from] PlanError),
    /// Something else about the batch.
    #[error("batch {epoch}/{step}: {reason}")]
    Invalid {
        /// Epoch of the batch.
        epoch: u64,
        /// Step of the batch.
        step: u64,
        /// What is wrong.
        reason: String,
    },
}

/// The tensors and plans of one step.
#[derive(Debug)]
pub struct StepInputs {
    /// Level-0 voxel features `[V₀, 4]` (x, y, z, intensity), on the training device.
    pub voxel_features: Tensor<2>,
    /// Kernel maps of every level, finest first.
    pub levels: Vec<LevelMaps>,
    /// Level-0 voxel row of every pairing's point.
    pub pairing_voxel: Tensor<1, Int>,
    /// Images `[I, H, W, 3]` as floats in 0..255, on the ViT's device.
    pub images: Tensor<4>,
    /// The losses' plan.
    pub plan: LossPlan,
    /// Bilinear sampling of the 2D features at the plan's pixels.
    pub sampler: PixelSampler,
    /// `sample_ids` rows: epoch, index in epoch, keyframe, drive, sweep.
    pub sample_ids: Vec<[u64; 5]>,
    /// Points, pairings and level-0 voxels in the batch.
    pub counts: [usize; 3],
}

impl StepInputs {
    /// Reads `view` onto `device` (the training device) and `vit_device` (where the
    /// frozen ViT runs), with superpixel pooling at every `pixel_stride`-th pixel.
    pub fn from_view(
        view: &BatchView<'_>,
        device: &Device,
        vit_device: &Device,
        pixel_stride: usize,
    ) -> Result<Self, InputError> {
        let meta = view.meta();
        let invalid = |reason: String| InputError::Invalid {
            epoch: meta.epoch,
            step: meta.step,
            reason,
        };
        let images = view.get::<u8>("images")?;
        let [n_images, h, w, _] = <[usize; 4]>::try_from(images.shape())
            .map_err(|_| invalid("`images` is not I×H×W×3".into()))?;
        if h % PATCH != 0 || w % PATCH != 0 {
            return Err(invalid(format!(
                "images are {h}×{w}, not multiples of the ViT patch {PATCH}"
            )));
        }
        let camera_ids = view.get::<u32>("camera_ids")?;
        let [batch, cameras] = <[usize; 2]>::try_from(camera_ids.shape())
            .map_err(|_| invalid("`camera_ids` is not B×K".into()))?;
        let offsets = view.get::<i32>("frame_offsets")?;
        let frames = offsets.data.len();
        let key_frame = offsets
            .data
            .iter()
            .position(|&o| o == 0)
            .ok_or_else(|| invalid("no frame at offset 0".into()))?;
        if batch * frames * cameras != n_images {
            return Err(invalid(format!(
                "{n_images} images for {batch} samples × {frames} frames × {cameras} cameras"
            )));
        }

        let num_superpixels = view.get::<u32>("num_superpixels")?;
        let superpixels = view.get::<u16>("superpixels")?;
        let pairing_point = view.get::<u32>("pairing_point")?;
        let pairing_superpixel = view.get::<u32>("pairing_superpixel")?;
        let pairing_clouds = view.get::<u32>("pairing_clouds")?;
        let plan = LossPlan::new(
            &LossInputs {
                batch,
                frames,
                cameras,
                key_frame,
                height: h,
                width: w,
                num_superpixels: num_superpixels.data,
                superpixels: superpixels.data,
                pairing_point: pairing_point.data,
                pairing_superpixel: pairing_superpixel.data,
                pairing_clouds: pairing_clouds.data,
            },
            pixel_stride,
            device,
        )?;
        let sampler = PixelSampler::new(&plan.pixels, [h, w], [h / PATCH, w / PATCH], device);

        let voxel = view.get::<f32>("voxel_features")?;
        let [voxels, channels] = <[usize; 2]>::try_from(voxel.shape())
            .map_err(|_| invalid("`voxel_features` is not V×C".into()))?;
        let point_to_voxel = view.get::<u32>("point_to_voxel")?;
        let points = point_to_voxel.data.len();
        let mut pairing_voxel = Vec::with_capacity(pairing_point.data.len());
        for &p in pairing_point.data {
            let v = *point_to_voxel
                .data
                .get(p as usize)
                .ok_or_else(|| invalid(format!("pairing point {p} beyond {points} points")))?;
            if v as usize >= voxels {
                return Err(invalid(format!(
                    "point {p} in voxel {v} beyond {voxels} voxels"
                )));
            }
            pairing_voxel.push(i64::from(v));
        }

        let mut levels = Vec::new();
        while view.describe(&format!("l{}_coords", levels.len())).is_ok() {
            let l = levels.len();
            let rows = view.get::<i32>(&format!("l{l}_coords"))?.shape()[0];
            let nbr = view.get::<u32>(&format!("l{l}_nbr"))?;
            let starts = view.get::<u32>(&format!("l{l}_nbr_starts"))?;
            check_map(nbr.data, starts.data, 27, rows, rows)
                .map_err(|r| invalid(format!("l{l}_nbr: {r}")))?;
            let down = match (
                view.get::<u32>(&format!("l{l}_down")),
                view.get::<u32>(&format!("l{l}_down_starts")),
            ) {
                (Ok(d), Ok(s)) => Some((d.data, s.data)),
                _ => None,
            };
            levels.push((rows, nbr.data, starts.data, down));
        }
        if levels.len() < UNetConfig::LEVELS {
            return Err(invalid(format!(
                "kernel maps of {} levels, the UNet needs {}",
                levels.len(),
                UNetConfig::LEVELS
            )));
        }
        if levels[0].0 != voxels {
            return Err(invalid(format!(
                "l0 has {} voxels, voxel_features {voxels}",
                levels[0].0
            )));
        }
        let mut maps = Vec::with_capacity(levels.len());
        for (l, &(rows, nbr, starts, down)) in levels.iter().enumerate() {
            let down = if l + 1 < UNetConfig::LEVELS {
                let (pairs, down_starts) =
                    down.ok_or_else(|| invalid(format!("level {l} has no down map")))?;
                let next_rows = levels[l + 1].0;
                check_map(pairs, down_starts, 8, rows, next_rows)
                    .map_err(|r| invalid(format!("l{l}_down: {r}")))?;
                Some((pairs, down_starts))
            } else {
                None
            };
            maps.push(LevelMaps::from_host(rows, nbr, starts, down, device));
        }

        let images_f32: Vec<f32> = images.data.iter().map(|&v| f32::from(v)).collect();
        let sample_ids = view
            .get::<u64>("sample_ids")?
            .data
            .chunks_exact(5)
            .map(|c| [c[0], c[1], c[2], c[3], c[4]])
            .collect();
        Ok(Self {
            voxel_features: Tensor::from_data(
                TensorData::new(voxel.data.to_vec(), [voxels, channels]),
                device,
            ),
            levels: maps,
            pairing_voxel: index_tensor(pairing_voxel, device),
            images: Tensor::from_data(TensorData::new(images_f32, [n_images, h, w, 3]), vit_device),
            plan,
            sampler,
            sample_ids,
            counts: [points, pairing_point.data.len(), voxels],
        })
    }
}

/// Checks a kernel map: `starts` has `offsets + 1` non-decreasing entries ending at the
/// pair count, inputs are below `in_rows` and outputs below `out_rows`.
fn check_map(
    pairs: &[u32],
    starts: &[u32],
    offsets: usize,
    in_rows: usize,
    out_rows: usize,
) -> Result<(), String> {
    if starts.len() != offsets + 1 {
        return Err(format!("{} starts for {offsets} offsets", starts.len()));
    }
    if starts.windows(2).any(|w| w[0] > w[1]) || starts[offsets] as usize * 2 != pairs.len() {
        return Err("starts do not partition the pairs".into());
    }
    for p in pairs.chunks_exact(2) {
        if p[0] as usize >= in_rows || p[1] as usize >= out_rows {
            return Err(format!("pair ({}, {}) out of range", p[0], p[1]));
        }
    }
    Ok(())
}
