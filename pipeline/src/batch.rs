//! Samples → one batch, written in place into a payload buffer (in the service, the
//! loaned iceoryx2 slice): no intermediate serialization, each byte written once.
//!
//! The sections of a batch — names, dtypes, shapes, meanings, how the clouds of the `B`
//! samples are concatenated and the images numbered — are the table of
//! [`superflow_schemas::batch::sections`], shown in `schemas/BATCH_FORMAT.md` ("SuperFlow
//! sections"). [`BatchPlan::new`] plans them in the table's order with the sizes of the
//! samples ([`Dims`]); [`BatchPlan::write`] fills each [`Section`], the table checking the
//! element type of every write.

use crate::sample::SampleConfig;
use crate::sample::sparse::KernelMap;
use crate::sample::{Cloud, Sample};
use superflow_schemas::batch::{
    BatchError, BatchLayout, BatchMeta, BatchWriter, Dims, LevelDims, Section,
};

/// What goes into a batch besides the samples.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub struct BatchShape {
    /// Image height.
    pub height: usize,
    /// Image width.
    pub width: usize,
    /// UNet levels.
    pub levels: usize,
}

impl BatchShape {
    /// The shape of batches of samples built with `config`.
    pub fn of(config: &SampleConfig) -> Self {
        Self {
            height: config.image_height as usize,
            width: config.image_width as usize,
            levels: config.unet_levels as usize,
        }
    }
}

/// `samples` as one batch exactly as it goes on the wire — the `BatchHeader` bytes, then
/// the payload (`schemas/BATCH_FORMAT.md`): what `superflow-pipeline batch` writes to a
/// file and benchmarks read back.
pub fn batch_bytes(
    samples: &[Sample],
    shape: BatchShape,
    meta: &BatchMeta,
) -> Result<Vec<u8>, BatchError> {
    let plan = BatchPlan::new(samples, shape)?;
    let header = plan.layout().header(meta)?;
    let mut bytes = header.as_bytes().to_vec();
    let start = bytes.len();
    bytes.resize(start + plan.layout().payload_len(), 0);
    plan.write_zeroed(samples, &mut bytes[start..])?;
    Ok(bytes)
}

/// The clouds of a sample in batch order: frames, then the dense cloud.
fn clouds(sample: &Sample) -> impl Iterator<Item = &Cloud> {
    sample
        .frames
        .iter()
        .map(|f| &f.cloud)
        .chain(std::iter::once(&sample.dense))
}

fn err(name: &str, reason: impl Into<String>) -> BatchError {
    BatchError::BadSection {
        name: name.to_string(),
        reason: reason.into(),
    }
}

/// The planned sections of a batch of `samples`.
#[derive(Debug, Clone)]
pub struct BatchPlan {
    layout: BatchLayout,
    shape: BatchShape,
}

impl BatchPlan {
    /// Plans the sections for `samples` (all built with the same recipe).
    pub fn new(samples: &[Sample], shape: BatchShape) -> Result<Self, BatchError> {
        let dims = dims(samples, shape)?;
        let mut layout = BatchLayout::new();
        for section in Section::in_order(shape.levels) {
            layout.add_section(section, &dims.shape(section)?)?;
        }
        Ok(Self { layout, shape })
    }

    /// The layout (payload length, header).
    pub fn layout(&self) -> &BatchLayout {
        &self.layout
    }

    /// Writes `samples` (the ones planned) into `payload`, every section in place.
    pub fn write(&self, samples: &[Sample], payload: &mut [u8]) -> Result<(), BatchError> {
        self.write_with(samples, BatchWriter::new(&self.layout, payload)?)
    }

    /// [`BatchPlan::write`] into a payload that is already all zeros (a freshly zeroed
    /// loan): one pass over the memory fewer.
    pub fn write_zeroed(&self, samples: &[Sample], payload: &mut [u8]) -> Result<(), BatchError> {
        self.write_with(samples, BatchWriter::over_zeroed(&self.layout, payload)?)
    }

    fn write_with(&self, samples: &[Sample], mut w: BatchWriter<'_>) -> Result<(), BatchError> {
        write_sample_sections(samples, &mut w)?;
        write_images(samples, self.shape, &mut w)?;
        let point_offsets = write_points(samples, &mut w)?;
        write_pairings(samples, &point_offsets, &mut w)?;
        for l in 0..self.shape.levels {
            write_level(samples, l, l + 1 < self.shape.levels, &mut w)?;
        }
        Ok(())
    }
}

/// The sizes behind the table's symbols for `samples`, after checking that they share
/// one recipe.
fn dims(samples: &[Sample], shape: BatchShape) -> Result<Dims, BatchError> {
    let first = samples
        .first()
        .ok_or_else(|| err("samples", "empty batch"))?;
    let f = first.frames.len();
    let k = first.cameras.len();
    for s in samples {
        if s.frames.len() != f || s.cameras.len() != k {
            return Err(err("samples", "samples of different recipes in one batch"));
        }
        if s.frames.iter().any(|fr| fr.num_superpixels > 65_536) {
            return Err(err(
                &Section::Superpixels.name(),
                "more than 65536 superpixels in a frame",
            ));
        }
    }
    let all_clouds = || samples.iter().flat_map(clouds);
    let levels = (0..shape.levels)
        .map(|l| {
            let mut level_dims = LevelDims::default();
            for cloud in all_clouds() {
                let level = cloud
                    .levels
                    .get(l)
                    .ok_or_else(|| err("levels", format!("a cloud has no level {l}")))?;
                level_dims.voxels += level.coords.len();
                level_dims.pairs += level.neighbours.pairs.len();
            }
            Ok(level_dims)
        })
        .collect::<Result<Vec<_>, BatchError>>()?;
    Ok(Dims {
        samples: samples.len(),
        frames: f,
        cameras: k,
        height: shape.height,
        width: shape.width,
        points: all_clouds().map(|c| c.xyz.len()).sum(),
        pairings: all_clouds().map(|c| c.pairings.len()).sum(),
        voxels: all_clouds().map(|c| c.voxels.coords.len()).sum(),
        levels,
    })
}

/// `sample_ids`, `frame_stamps`, `frame_offsets`, `camera_ids`.
fn write_sample_sections(samples: &[Sample], w: &mut BatchWriter<'_>) -> Result<(), BatchError> {
    fill(
        w.take_section::<u64>(Section::SampleIds)?,
        samples.iter().flat_map(|s| {
            [
                s.id.epoch,
                s.id.index,
                u64::from(s.id.keyframe),
                u64::from(s.id.drive),
                u64::from(s.id.sweep),
            ]
        }),
    );
    fill(
        w.take_section::<i64>(Section::FrameStamps)?,
        samples
            .iter()
            .flat_map(|s| s.frames.iter().map(|fr| fr.lidar_stamp.nanos())),
    );
    fill(
        w.take_section::<i32>(Section::FrameOffsets)?,
        samples[0].frames.iter().map(|fr| fr.offset),
    );
    fill(
        w.take_section::<u32>(Section::CameraIds)?,
        samples
            .iter()
            .flat_map(|s| s.camera_indices.iter().copied()),
    );
    Ok(())
}

/// `image_stamps`, `image_flipped`, `images`, `superpixels`, `num_superpixels`.
fn write_images(
    samples: &[Sample],
    shape: BatchShape,
    w: &mut BatchWriter<'_>,
) -> Result<(), BatchError> {
    let (h, wd) = (shape.height, shape.width);
    let images = || {
        samples
            .iter()
            .flat_map(|s| s.frames.iter().flat_map(|fr| fr.images.iter()))
    };
    fill(
        w.take_section::<i64>(Section::ImageStamps)?,
        images().map(|i| i.stamp.nanos()),
    );
    fill(
        w.take_section::<u8>(Section::ImageFlipped)?,
        images().map(|i| u8::from(i.flipped)),
    );
    let out = w.take_section::<u8>(Section::Images)?;
    for (dst, img) in out.chunks_exact_mut(h * wd * 3).zip(images()) {
        if img.rgb.len() != dst.len() {
            return Err(err(
                &Section::Images.name(),
                "image size differs from the recipe",
            ));
        }
        dst.copy_from_slice(&img.rgb);
    }
    let out = w.take_section::<u16>(Section::Superpixels)?;
    for (dst, img) in out.chunks_exact_mut(h * wd).zip(images()) {
        fill(dst, img.superpixels.iter().map(|&id| id as u16));
    }
    fill(
        w.take_section::<u32>(Section::NumSuperpixels)?,
        samples
            .iter()
            .flat_map(|s| s.frames.iter().map(|fr| fr.num_superpixels)),
    );
    Ok(())
}

/// `points`, `point_clouds`, `source_sweep`, `point_to_voxel`, `augmentation`,
/// `voxel_features`; returns the first point row of every cloud (and the total).
fn write_points(samples: &[Sample], w: &mut BatchWriter<'_>) -> Result<Vec<usize>, BatchError> {
    let all_clouds = || samples.iter().flat_map(clouds);
    fill(
        w.take_section::<f32>(Section::Points)?,
        all_clouds().flat_map(|c| {
            c.xyz
                .iter()
                .zip(&c.intensity)
                .flat_map(|(p, i)| [p[0], p[1], p[2], *i])
        }),
    );
    let point_offsets = offsets(all_clouds().map(|c| c.xyz.len()));
    fill(
        w.take_section::<u32>(Section::PointClouds)?,
        point_offsets.iter().map(|&o| o as u32),
    );
    fill(
        w.take_section::<u8>(Section::SourceSweep)?,
        all_clouds().flat_map(|c| c.source_sweep.iter().copied()),
    );
    let voxel_offsets = offsets(all_clouds().map(|c| c.voxels.coords.len()));
    fill(
        w.take_section::<u32>(Section::PointToVoxel)?,
        all_clouds()
            .zip(&voxel_offsets)
            .flat_map(|(c, &o)| c.voxels.point_to_voxel.iter().map(move |&v| v + o as u32)),
    );
    fill(
        w.take_section::<f32>(Section::Augmentation)?,
        all_clouds().flat_map(|c| {
            let a = c.augmentation;
            [
                f32::from(u8::from(a.flip_x)),
                f32::from(u8::from(a.flip_y)),
                a.yaw_rad as f32,
                a.scale as f32,
            ]
        }),
    );
    fill(
        w.take_section::<f32>(Section::VoxelFeatures)?,
        all_clouds().flat_map(|c| c.voxel_features.iter().flatten().copied()),
    );
    Ok(point_offsets)
}

/// The `pairing_*` sections; `point_offsets` is the first point row of every cloud.
fn write_pairings(
    samples: &[Sample],
    point_offsets: &[usize],
    w: &mut BatchWriter<'_>,
) -> Result<(), BatchError> {
    let f = samples[0].frames.len();
    let k = samples[0].cameras.len();
    let all_clouds = || samples.iter().flat_map(clouds);
    // The image number of a cloud's pairing is its frame's (the keyframe's for the
    // dense cloud).
    let pairings = || {
        samples.iter().enumerate().flat_map(move |(b, s)| {
            let c_count = s.frames.len() + 1;
            clouds(s).enumerate().map(move |(c, cloud)| {
                let frame = if c + 1 == c_count { s.key_frame } else { c };
                (b * c_count + c, (b * f + frame) * k, cloud)
            })
        })
    };
    fill(
        w.take_section::<u32>(Section::PairingPoint)?,
        pairings().flat_map(|(ci, _, cloud)| {
            let o = point_offsets[ci] as u32;
            cloud.pairings.iter().map(move |p| p.point + o)
        }),
    );
    fill(
        w.take_section::<u32>(Section::PairingImage)?,
        pairings().flat_map(|(_, first_image, cloud)| {
            cloud
                .pairings
                .iter()
                .map(move |p| (first_image + usize::from(p.camera)) as u32)
        }),
    );
    fill(
        w.take_section::<u16>(Section::PairingPixel)?,
        all_clouds().flat_map(|c| c.pairings.iter().flat_map(|p| [p.row, p.col])),
    );
    fill(
        w.take_section::<f32>(Section::PairingUv)?,
        all_clouds().flat_map(|c| c.pairings.iter().flat_map(|p| [p.u, p.v])),
    );
    fill(
        w.take_section::<f32>(Section::PairingDepth)?,
        all_clouds().flat_map(|c| c.pairings.iter().map(|p| p.depth)),
    );
    fill(
        w.take_section::<u32>(Section::PairingSuperpixel)?,
        all_clouds().flat_map(|c| c.pairings.iter().map(|p| p.superpixel)),
    );
    let pairing_offsets = offsets(all_clouds().map(|c| c.pairings.len()));
    fill(
        w.take_section::<u32>(Section::PairingClouds)?,
        pairing_offsets.iter().map(|&o| o as u32),
    );
    Ok(())
}

/// The sections of level `l`: coordinates, cloud offsets, neighbour map and, unless it
/// is the coarsest level (`down` false), the map down to level `l + 1`.
fn write_level(
    samples: &[Sample],
    l: usize,
    down: bool,
    w: &mut BatchWriter<'_>,
) -> Result<(), BatchError> {
    let all_clouds = || samples.iter().flat_map(clouds);
    let rows = offsets(all_clouds().map(|c| c.levels[l].coords.len()));
    fill(
        w.take_section::<i32>(Section::LevelCoords(l))?,
        all_clouds().enumerate().flat_map(|(ci, c)| {
            c.levels[l]
                .coords
                .iter()
                .flat_map(move |x| [ci as i32, x[0], x[1], x[2]])
        }),
    );
    fill(
        w.take_section::<u32>(Section::LevelClouds(l))?,
        rows.iter().map(|&o| o as u32),
    );
    let maps: Vec<&KernelMap> = all_clouds().map(|c| &c.levels[l].neighbours).collect();
    let (pairs, starts) = merge(&maps, &rows, &rows, 27)?;
    w.write_section(Section::LevelNbr(l), &pairs)?;
    w.write_section(Section::LevelNbrStarts(l), &starts)?;
    if down {
        let coarse = offsets(all_clouds().map(|c| c.levels[l + 1].coords.len()));
        let maps = all_clouds()
            .map(|c| {
                c.levels[l]
                    .down
                    .as_ref()
                    .ok_or_else(|| err("levels", format!("level {l} has no down map")))
            })
            .collect::<Result<Vec<_>, _>>()?;
        let (pairs, starts) = merge(&maps, &rows, &coarse, 8)?;
        w.write_section(Section::LevelDown(l), &pairs)?;
        w.write_section(Section::LevelDownStarts(l), &starts)?;
    }
    Ok(())
}

/// Writes `items` into `dst` in order (`dst` was sized for exactly these items).
fn fill<T>(dst: &mut [T], items: impl IntoIterator<Item = T>) {
    for (d, x) in dst.iter_mut().zip(items) {
        *d = x;
    }
}

/// Exclusive prefix sums with the total last.
fn offsets(counts: impl Iterator<Item = usize>) -> Vec<usize> {
    let mut out = vec![0];
    for c in counts {
        out.push(out[out.len() - 1] + c);
    }
    out
}

/// Concatenates per-cloud kernel maps offset by offset, shifting input rows by
/// `in_rows[cloud]` and output rows by `out_rows[cloud]`; returns flattened pairs and the
/// `kernels + 1` starts.
fn merge(
    maps: &[&KernelMap],
    in_rows: &[usize],
    out_rows: &[usize],
    kernels: usize,
) -> Result<(Vec<u32>, Vec<u32>), BatchError> {
    let total: usize = maps.iter().map(|m| m.pairs.len()).sum();
    let mut pairs = Vec::with_capacity(total * 2);
    let mut starts = Vec::with_capacity(kernels + 1);
    starts.push(0);
    for kern in 0..kernels {
        for (ci, map) in maps.iter().enumerate() {
            if map.offsets.len() != kernels {
                return Err(err(
                    "maps",
                    format!("{} kernel offsets, expected {kernels}", map.offsets.len()),
                ));
            }
            let (i0, o0) = (in_rows[ci] as u32, out_rows[ci] as u32);
            for [i, o] in map.pairs_of(kern) {
                pairs.push(i + i0);
                pairs.push(o + o0);
            }
        }
        starts.push((pairs.len() / 2) as u32);
    }
    Ok((pairs, starts))
}
