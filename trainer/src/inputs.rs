//! A received batch → the tensors of one training step, on the chosen device: one
//! transfer per section (plus the host-side index plan of the losses). Sections are read
//! by [`Section`], the table of `superflow_schemas::batch::sections` (`BATCH_FORMAT.md`).

use crate::loss::{LossInputs, LossPlan, PlanError};
use crate::model::PixelSampler;
use crate::unet::{LevelMaps, UNetConfig, index_tensor};
use burn::tensor::{Device, Int, Tensor, TensorData};
use superflow_schemas::batch::{BatchError, BatchView, Section};

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
    /// A kernel map (`l{l}_nbr`, `l{l}_down`) that does not fit its rows.
    #[error("batch {epoch}/{step}: {section}: {source}")]
    Map {
        /// Epoch of the batch.
        epoch: u64,
        /// Step of the batch.
        step: u64,
        /// The map's section.
        section: String,
        /// What is wrong.
        source: MapError,
    },
}

/// What is wrong with a kernel map.
#[derive(Debug, Clone, PartialEq, Eq, thiserror::Error)]
pub enum MapError {
    /// The starts are not one per offset plus one.
    #[error("{starts} starts for {offsets} offsets")]
    Starts {
        /// Entries of the starts section.
        starts: usize,
        /// Kernel offsets of the map.
        offsets: usize,
    },
    /// The starts decrease or do not end at the pair count.
    #[error("starts do not partition the pairs")]
    Partition,
    /// A pair points past the rows of its level.
    #[error("pair ({input}, {output}) out of range")]
    OutOfRange {
        /// Input row.
        input: u32,
        /// Output row.
        output: u32,
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
        let at = At {
            epoch: view.meta().epoch,
            step: view.meta().step,
        };
        if view.is_lost() {
            return Err(at.invalid(
                "the batch is lost (BATCH_LOST): every sample failed in the pipeline, there is nothing to train on"
                    .to_string(),
            ));
        }
        let (geometry, images) = Geometry::read(view, at)?;
        let (plan, pairing_point) = loss_plan(view, &geometry, pixel_stride, device)?;
        let Geometry { n_images, h, w, .. } = geometry;
        let sampler = PixelSampler::new(&plan.pixels, [h, w], [h / PATCH, w / PATCH], device);

        let voxel = view.section::<f32>(Section::VoxelFeatures)?;
        let [voxels, channels] = <[usize; 2]>::try_from(voxel.shape())
            .map_err(|_| at.invalid(format!("`{}` is not V×C", Section::VoxelFeatures.name())))?;
        let point_to_voxel = view.section::<u32>(Section::PointToVoxel)?.data;
        let pairing_voxel = pairing_voxels(pairing_point, point_to_voxel, voxels, at)?;
        let levels = host_levels(view, at)?;
        let maps = level_maps(&levels, voxels, at, device)?;

        let images_f32: Vec<f32> = images.iter().map(|&v| f32::from(v)).collect();
        let sample_ids = view
            .section::<u64>(Section::SampleIds)?
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
            counts: [point_to_voxel.len(), pairing_point.len(), voxels],
        })
    }
}

/// Where a batch sits in the stream, for its errors.
#[derive(Debug, Clone, Copy)]
struct At {
    epoch: u64,
    step: u64,
}

impl At {
    fn invalid(self, reason: String) -> InputError {
        InputError::Invalid {
            epoch: self.epoch,
            step: self.step,
            reason,
        }
    }

    fn map(self, section: Section, source: MapError) -> InputError {
        InputError::Map {
            epoch: self.epoch,
            step: self.step,
            section: section.name().into_owned(),
            source,
        }
    }
}

/// How the images of a batch are numbered: `B` samples × `F` frames × their own `K_b`
/// cameras (`sample_cameras`) of `H × W` pixels, and which frame is the keyframe.
#[derive(Debug, Clone, Copy)]
struct Geometry<'a> {
    n_images: usize,
    h: usize,
    w: usize,
    batch: usize,
    frames: usize,
    sample_cameras: &'a [u32],
    key_frame: usize,
}

impl<'a> Geometry<'a> {
    /// The geometry of `view`'s images, checked against each other, and the images.
    fn read(view: &BatchView<'a>, at: At) -> Result<(Self, &'a [u8]), InputError> {
        let images = view.section::<u8>(Section::Images)?;
        let [n_images, h, w, _] = <[usize; 4]>::try_from(images.shape())
            .map_err(|_| at.invalid(format!("`{}` is not I×H×W×3", Section::Images.name())))?;
        if h % PATCH != 0 || w % PATCH != 0 {
            return Err(at.invalid(format!(
                "images are {h}×{w}, not multiples of the ViT patch {PATCH}"
            )));
        }
        let batch = view.section::<u64>(Section::SampleIds)?.shape()[0];
        let sample_cameras = view.section::<u32>(Section::SampleCameras)?.data;
        let slots = view.section::<u32>(Section::CameraIds)?.data.len();
        if sample_cameras.len() != batch + 1
            || sample_cameras[0] != 0
            || sample_cameras.windows(2).any(|w| w[0] > w[1])
            || sample_cameras[batch] as usize != slots
        {
            return Err(at.invalid(format!(
                "`{}` does not cut the {slots} camera slots into {batch} samples",
                Section::SampleCameras.name()
            )));
        }
        let offsets = view.section::<i32>(Section::FrameOffsets)?;
        let frames = offsets.data.len();
        let key_frame = offsets
            .data
            .iter()
            .position(|&o| o == 0)
            .ok_or_else(|| at.invalid("no frame at offset 0".into()))?;
        if frames * slots != n_images {
            return Err(at.invalid(format!(
                "{n_images} images for {frames} frames × {slots} camera slots"
            )));
        }
        let geometry = Self {
            n_images,
            h,
            w,
            batch,
            frames,
            sample_cameras,
            key_frame,
        };
        Ok((geometry, images.data))
    }
}

/// The losses' plan from the superpixel and pairing sections, and `pairing_point`.
fn loss_plan<'a>(
    view: &BatchView<'a>,
    g: &Geometry<'a>,
    pixel_stride: usize,
    device: &Device,
) -> Result<(LossPlan, &'a [u32]), InputError> {
    let num_superpixels = view.section::<u32>(Section::NumSuperpixels)?;
    let superpixels = view.section::<u16>(Section::Superpixels)?;
    let pairing_point = view.section::<u32>(Section::PairingPoint)?;
    let pairing_superpixel = view.section::<u32>(Section::PairingSuperpixel)?;
    let pairing_clouds = view.section::<u32>(Section::PairingClouds)?;
    let plan = LossPlan::new(
        &LossInputs {
            batch: g.batch,
            frames: g.frames,
            sample_cameras: g.sample_cameras,
            key_frame: g.key_frame,
            height: g.h,
            width: g.w,
            num_superpixels: num_superpixels.data,
            superpixels: superpixels.data,
            pairing_point: pairing_point.data,
            pairing_superpixel: pairing_superpixel.data,
            pairing_clouds: pairing_clouds.data,
        },
        pixel_stride,
        device,
    )?;
    Ok((plan, pairing_point.data))
}

/// The level-0 voxel row of every pairing's point.
fn pairing_voxels(
    pairing_point: &[u32],
    point_to_voxel: &[u32],
    voxels: usize,
    at: At,
) -> Result<Vec<i64>, InputError> {
    let points = point_to_voxel.len();
    let mut pairing_voxel = Vec::with_capacity(pairing_point.len());
    for &p in pairing_point {
        let v = *point_to_voxel
            .get(p as usize)
            .ok_or_else(|| at.invalid(format!("pairing point {p} beyond {points} points")))?;
        if v as usize >= voxels {
            return Err(at.invalid(format!("point {p} in voxel {v} beyond {voxels} voxels")));
        }
        pairing_voxel.push(i64::from(v));
    }
    Ok(pairing_voxel)
}

/// The kernel maps of one level as the batch holds them.
#[derive(Debug, Clone, Copy)]
struct HostLevel<'a> {
    rows: usize,
    nbr: &'a [u32],
    starts: &'a [u32],
    down: Option<(&'a [u32], &'a [u32])>,
}

/// Every level the batch holds (`l{l}_coords` present), its neighbour map checked.
fn host_levels<'a>(view: &BatchView<'a>, at: At) -> Result<Vec<HostLevel<'a>>, InputError> {
    let mut levels = Vec::new();
    while view.has(Section::LevelCoords(levels.len())) {
        let l = levels.len();
        let rows = view.section::<i32>(Section::LevelCoords(l))?.shape()[0];
        if !view.has(Section::LevelNbr(l)) {
            return Err(at.invalid(format!(
                "no kernel maps: the batch carries level {l}'s voxels only (the pipeline's \
                 recipe has kernel_maps = \"none\", for networks that build their own \
                 maps); this trainer's UNet runs on the batch's maps: set kernel_maps = \
                 \"unet\" in the pipeline's [sample]"
            )));
        }
        let nbr = view.section::<u32>(Section::LevelNbr(l))?;
        let starts = view.section::<u32>(Section::LevelNbrStarts(l))?;
        check_map(nbr.data, starts.data, 27, rows, rows)
            .map_err(|e| at.map(Section::LevelNbr(l), e))?;
        let down = match (
            view.section::<u32>(Section::LevelDown(l)),
            view.section::<u32>(Section::LevelDownStarts(l)),
        ) {
            (Ok(d), Ok(s)) => Some((d.data, s.data)),
            _ => None,
        };
        levels.push(HostLevel {
            rows,
            nbr: nbr.data,
            starts: starts.data,
            down,
        });
    }
    if levels.len() < UNetConfig::LEVELS {
        return Err(at.invalid(format!(
            "kernel maps of {} levels, the UNet needs {}",
            levels.len(),
            UNetConfig::LEVELS
        )));
    }
    Ok(levels)
}

/// The device maps of `levels`, after checking level 0 against the `voxels` of
/// `voxel_features` and each down map against the rows of the next level.
fn level_maps(
    levels: &[HostLevel<'_>],
    voxels: usize,
    at: At,
    device: &Device,
) -> Result<Vec<LevelMaps>, InputError> {
    if levels[0].rows != voxels {
        return Err(at.invalid(format!(
            "l0 has {} voxels, {} {voxels}",
            levels[0].rows,
            Section::VoxelFeatures.name()
        )));
    }
    let mut maps = Vec::with_capacity(levels.len());
    for (l, level) in levels.iter().enumerate() {
        let down = if l + 1 < UNetConfig::LEVELS {
            let (pairs, down_starts) = level
                .down
                .ok_or_else(|| at.invalid(format!("level {l} has no down map")))?;
            check_map(pairs, down_starts, 8, level.rows, levels[l + 1].rows)
                .map_err(|e| at.map(Section::LevelDown(l), e))?;
            Some((pairs, down_starts))
        } else {
            None
        };
        maps.push(LevelMaps::from_host(
            level.rows,
            level.nbr,
            level.starts,
            down,
            device,
        ));
    }
    Ok(maps)
}

/// Checks a kernel map: `starts` has `offsets + 1` non-decreasing entries ending at the
/// pair count, inputs are below `in_rows` and outputs below `out_rows`.
fn check_map(
    pairs: &[u32],
    starts: &[u32],
    offsets: usize,
    in_rows: usize,
    out_rows: usize,
) -> Result<(), MapError> {
    if starts.len() != offsets + 1 {
        return Err(MapError::Starts {
            starts: starts.len(),
            offsets,
        });
    }
    if starts.windows(2).any(|w| w[0] > w[1]) || starts[offsets] as usize * 2 != pairs.len() {
        return Err(MapError::Partition);
    }
    for p in pairs.chunks_exact(2) {
        if p[0] as usize >= in_rows || p[1] as usize >= out_rows {
            return Err(MapError::OutOfRange {
                input: p[0],
                output: p[1],
            });
        }
    }
    Ok(())
}

#[cfg(test)]
mod tests {
    #![allow(clippy::unwrap_used)] // tests fail loudly on purpose

    use super::*;
    use superflow_pipeline::batch::{BatchPlan, BatchShape};
    use superflow_pipeline::drive::{Dataset, IngestConfig};
    use superflow_pipeline::sample::{KernelMaps, SampleBuilder, SampleConfig};
    use superflow_schemas::batch::{BatchHeader, BatchMeta};

    /// Two samples of the ROS 2 street drive (default recipe) as one batch, epoch 3 step 7.
    fn street_batch() -> (BatchHeader, Vec<u64>) {
        street_batch_of(SampleConfig::default())
    }

    /// [`street_batch`] built with `config`.
    fn street_batch_of(config: SampleConfig) -> (BatchHeader, Vec<u64>) {
        let drive = superflow_recordings::sample_drive_path("street_ros2");
        let dataset =
            Dataset::open(std::slice::from_ref(&drive), &IngestConfig::default()).unwrap();
        let builder = SampleBuilder::new(&dataset, config.clone()).unwrap();
        let samples: Vec<_> = (0..2).map(|i| builder.build(0, i).unwrap()).collect();
        let plan = BatchPlan::new(&samples, BatchShape::of(&config)).unwrap();
        let mut storage = vec![0u64; plan.layout().payload_len().div_ceil(8)];
        plan.write(&samples, bytemuck::cast_slice_mut(&mut storage))
            .unwrap();
        let meta = BatchMeta {
            run: "inputs".into(),
            epoch: 3,
            step: 7,
            sample_count: 2,
            ..Default::default()
        };
        (plan.layout().header(&meta).unwrap(), storage)
    }

    #[test]
    fn a_pipeline_batch_becomes_step_inputs_and_a_bad_map_a_typed_error() {
        let (header, mut storage) = street_batch();
        let device = Device::flex();
        {
            let view = BatchView::new(&header, bytemuck::cast_slice(&storage)).unwrap();
            let inputs = StepInputs::from_view(&view, &device, &device, 4).unwrap();
            let len = |s: Section| view.section::<u32>(s).unwrap().data.len();
            let voxels = view.section::<f32>(Section::VoxelFeatures).unwrap().shape()[0];
            assert_eq!(
                inputs.counts,
                [
                    len(Section::PointToVoxel),
                    len(Section::PairingPoint),
                    voxels
                ]
            );
            assert_eq!(inputs.levels.len(), UNetConfig::LEVELS);
            assert_eq!(inputs.sample_ids.len(), 2);
            assert_eq!(inputs.images.dims(), [2 * 3 * 3, 224, 448, 3]);
        }
        // The first pair of `l2_nbr` pointing past every row.
        let nbr = header
            .sections
            .iter()
            .find(|s| s.name.starts_with(b"l2_nbr\0"))
            .unwrap();
        let first = nbr.offset as usize / 4;
        bytemuck::cast_slice_mut::<u64, u32>(&mut storage)[first] = u32::MAX;
        let view = BatchView::new(&header, bytemuck::cast_slice(&storage)).unwrap();
        let err = StepInputs::from_view(&view, &device, &device, 4).unwrap_err();
        assert!(matches!(err, InputError::Map { .. }), "{err:?}");
        assert!(
            err.to_string()
                .starts_with("batch 3/7: l2_nbr: pair (4294967295, "),
            "{err}"
        );
    }

    /// A batch of a recipe without kernel maps is refused with the setting to change, not
    /// as a missing section.
    #[test]
    fn a_batch_without_kernel_maps_names_the_setting() {
        let config = SampleConfig {
            kernel_maps: KernelMaps::None,
            ..SampleConfig::default()
        };
        let (header, storage) = street_batch_of(config);
        let view = BatchView::new(&header, bytemuck::cast_slice(&storage)).unwrap();
        let device = Device::flex();
        let err = StepInputs::from_view(&view, &device, &device, 4).unwrap_err();
        assert!(matches!(err, InputError::Invalid { .. }), "{err:?}");
        let text = err.to_string();
        assert!(text.starts_with("batch 3/7: no kernel maps"), "{text}");
        assert!(text.contains("kernel_maps = \"unet\""), "{text}");
    }

    /// A lost batch is refused by name, not as a missing section.
    #[test]
    fn a_lost_batch_is_not_trained_on() {
        let meta = BatchMeta {
            run: "inputs".into(),
            epoch: 1,
            step: 4,
            ..Default::default()
        };
        let header = BatchHeader::lost(&meta).unwrap();
        let view = BatchView::new(&header, &[]).unwrap();
        let device = Device::flex();
        let err = StepInputs::from_view(&view, &device, &device, 4).unwrap_err();
        assert!(matches!(err, InputError::Invalid { .. }), "{err:?}");
        assert!(
            err.to_string()
                .starts_with("batch 1/4: the batch is lost (BATCH_LOST)"),
            "{err}"
        );
    }

    #[test]
    fn map_errors_read_as_before() {
        let pairs = [0u32, 0, 1, 1];
        assert_eq!(
            check_map(&pairs, &[0, 2], 2, 2, 2).unwrap_err().to_string(),
            "2 starts for 2 offsets"
        );
        assert_eq!(
            check_map(&pairs, &[0, 1], 1, 2, 2).unwrap_err().to_string(),
            "starts do not partition the pairs"
        );
        assert_eq!(
            check_map(&pairs, &[0, 2], 1, 2, 1).unwrap_err().to_string(),
            "pair (1, 1) out of range"
        );
        assert!(check_map(&pairs, &[0, 1, 2], 2, 2, 2).is_ok());
    }
}
