//! Samples → one batch, written in place into a payload buffer (in the service, the
//! loaned iceoryx2 slice): no intermediate serialization, each byte written once.
//!
//! The sections of a batch — names, dtypes, shapes, meanings, how the clouds of the `B`
//! samples are concatenated and the images numbered — are the table of
//! [`superflow_schemas::batch::sections`], shown in `schemas/BATCH_FORMAT.md` ("SuperFlow
//! sections"). [`BatchPlan::new`] plans them in the table's order with the sizes of the
//! samples ([`Dims`]); [`BatchPlan::write`] fills each [`Section`], the table checking the
//! element type of every write.

use crate::sample::kernel_maps::KernelMap;
use crate::sample::{Cloud, Sample};
use crate::sample::{KernelMaps, SampleConfig};
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
    /// Which maps the samples carry; with none, the batch has level 0's voxels only.
    pub maps: KernelMaps,
}

impl BatchShape {
    /// The shape of batches of samples built with `config`.
    pub fn of(config: &SampleConfig) -> Self {
        Self {
            height: config.image_height as usize,
            width: config.image_width as usize,
            levels: config.unet_levels as usize,
            maps: config.kernel_maps,
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
    /// Plans the sections for `samples` (all built with the same recipe, from drives of
    /// any rig).
    pub fn new(samples: &[Sample], shape: BatchShape) -> Result<Self, BatchError> {
        let dims = dims(samples, shape)?;
        let mut layout = BatchLayout::new();
        let sections: Box<dyn Iterator<Item = Section>> = match shape.maps {
            KernelMaps::Unet => Box::new(Section::in_order(shape.levels)),
            KernelMaps::None => Box::new(Section::in_order_unmapped()),
        };
        for section in sections {
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
        match self.shape.maps {
            KernelMaps::Unet => {
                for l in 0..self.shape.levels {
                    let rows = write_level_cells(samples, l, &mut w)?;
                    write_level_maps(samples, l, &rows, l + 1 < self.shape.levels, &mut w)?;
                }
            }
            KernelMaps::None => {
                write_level_cells(samples, 0, &mut w)?;
            }
        }
        Ok(())
    }
}

/// The sizes behind the table's symbols for `samples`, after checking that they share
/// one recipe (the same temporal frames; the cameras may differ, one rig from another).
fn dims(samples: &[Sample], shape: BatchShape) -> Result<Dims, BatchError> {
    let first = samples
        .first()
        .ok_or_else(|| err("samples", "empty batch"))?;
    let f = first.frames.len();
    for s in samples {
        if s.frames.len() != f {
            return Err(err(
                "samples",
                "samples of different temporal frames in one batch",
            ));
        }
        if s.frames.iter().any(|fr| fr.images.len() != s.cameras.len()) {
            return Err(err(
                &Section::Images.name(),
                "a frame's images differ from its sample's cameras",
            ));
        }
        if s.frames.iter().any(|fr| fr.num_superpixels > 65_536) {
            return Err(err(
                &Section::Superpixels.name(),
                "more than 65536 superpixels in a frame",
            ));
        }
    }
    let all_clouds = || samples.iter().flat_map(clouds);
    let voxels = all_clouds().map(|c| c.voxels.coords.len()).sum();
    let levels = match shape.maps {
        KernelMaps::Unet => (0..shape.levels)
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
            .collect::<Result<Vec<_>, BatchError>>()?,
        KernelMaps::None => vec![LevelDims { voxels, pairs: 0 }],
    };
    Ok(Dims {
        samples: samples.len(),
        frames: f,
        camera_slots: samples.iter().map(|s| s.cameras.len()).sum(),
        height: shape.height,
        width: shape.width,
        points: all_clouds().map(|c| c.xyz.len()).sum(),
        pairings: all_clouds().map(|c| c.pairings.len()).sum(),
        voxels,
        levels,
    })
}

/// The first camera slot of each sample, and the total: `sample_cameras`. The images of
/// sample `b` are numbered from `F · slots[b]`, frame by frame, its cameras in slot
/// order within a frame.
fn camera_slots(samples: &[Sample]) -> Vec<usize> {
    offsets(samples.iter().map(|s| s.cameras.len()))
}

/// `sample_ids`, `frame_stamps`, `frame_offsets`, `camera_ids`, `sample_cameras`.
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
    fill(
        w.take_section::<u32>(Section::SampleCameras)?,
        camera_slots(samples).into_iter().map(|o| o as u32),
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
        // The section is u16: an id beyond it is an error, never a silent wrap.
        let mut all_bits = 0u32;
        fill(
            dst,
            img.superpixels.iter().map(|&id| {
                all_bits |= id;
                id as u16
            }),
        );
        if all_bits > u32::from(u16::MAX) {
            let worst = img.superpixels.iter().max().copied().unwrap_or_default();
            return Err(err(
                &Section::Superpixels.name(),
                format!(
                    "superpixel id {worst} of {} at {} does not fit 16 bits",
                    img.camera,
                    img.stamp.nanos()
                ),
            ));
        }
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
    let out = w.take_section::<f32>(Section::Points)?;
    concat(out, 4, all_clouds().map(|c| c.xyz.len()), |ci, dst| {
        let c = cloud_at(samples, ci);
        for ((d, p), i) in dst.chunks_exact_mut(4).zip(&c.xyz).zip(&c.intensity) {
            d.copy_from_slice(&[p[0], p[1], p[2], *i]);
        }
    });
    let point_offsets = offsets(all_clouds().map(|c| c.xyz.len()));
    fill(
        w.take_section::<u32>(Section::PointClouds)?,
        point_offsets.iter().map(|&o| o as u32),
    );
    let out = w.take_section::<u8>(Section::SourceSweep)?;
    concat(
        out,
        1,
        all_clouds().map(|c| c.source_sweep.len()),
        |ci, dst| {
            dst.copy_from_slice(&cloud_at(samples, ci).source_sweep);
        },
    );
    let voxel_offsets = offsets(all_clouds().map(|c| c.voxels.coords.len()));
    let out = w.take_section::<u32>(Section::PointToVoxel)?;
    concat(
        out,
        1,
        all_clouds().map(|c| c.voxels.point_to_voxel.len()),
        |ci, dst| {
            let first = voxel_offsets[ci] as u32;
            for (d, v) in dst
                .iter_mut()
                .zip(&cloud_at(samples, ci).voxels.point_to_voxel)
            {
                *d = v + first;
            }
        },
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
    let out = w.take_section::<f32>(Section::VoxelFeatures)?;
    concat(
        out,
        4,
        all_clouds().map(|c| c.voxel_features.len()),
        |ci, dst| {
            dst.copy_from_slice(cloud_at(samples, ci).voxel_features.as_flattened());
        },
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
    let slots = camera_slots(samples);
    let all_clouds = || samples.iter().flat_map(clouds);
    // The image number of a cloud's pairing is its frame's (the keyframe's for the
    // dense cloud): sample b's images start at F · slots[b], K_b per frame.
    let pairings = || {
        let slots = &slots;
        samples.iter().enumerate().flat_map(move |(b, s)| {
            let c_count = s.frames.len() + 1;
            let k = s.cameras.len();
            clouds(s).enumerate().map(move |(c, cloud)| {
                let frame = if c + 1 == c_count { s.key_frame } else { c };
                (b * c_count + c, f * slots[b] + frame * k, cloud)
            })
        })
    };
    // One pass over each cloud's pairings fills the six sections together.
    let mut point = w.take_section::<u32>(Section::PairingPoint)?;
    let mut image = w.take_section::<u32>(Section::PairingImage)?;
    let mut pixel = w.take_section::<u16>(Section::PairingPixel)?;
    let mut uv = w.take_section::<f32>(Section::PairingUv)?;
    let mut depth = w.take_section::<f32>(Section::PairingDepth)?;
    let mut superpixel = w.take_section::<u32>(Section::PairingSuperpixel)?;
    for (ci, first_image, cloud) in pairings() {
        let first_point = point_offsets[ci] as u32;
        let n = cloud.pairings.len();
        if [
            point.len(),
            image.len(),
            pixel.len() / 2,
            uv.len() / 2,
            depth.len(),
            superpixel.len(),
        ]
        .iter()
        .any(|&room| room < n)
        {
            return Err(err("pairings", "more pairings than planned"));
        }
        let rows = point
            .iter_mut()
            .zip(image.iter_mut())
            .zip(pixel.chunks_exact_mut(2));
        let rows = rows.zip(uv.chunks_exact_mut(2)).zip(depth.iter_mut());
        for (((((pt, im), px), uv), d), (sp, p)) in
            rows.zip(superpixel.iter_mut().zip(&cloud.pairings))
        {
            *pt = p.point + first_point;
            *im = first_image as u32 + u32::from(p.camera);
            px.copy_from_slice(&[p.row, p.col]);
            uv.copy_from_slice(&[p.u, p.v]);
            *d = p.depth;
            *sp = p.superpixel;
        }
        point = &mut point[n..];
        image = &mut image[n..];
        pixel = &mut pixel[2 * n..];
        uv = &mut uv[2 * n..];
        depth = &mut depth[n..];
        superpixel = &mut superpixel[n..];
    }
    let pairing_offsets = offsets(all_clouds().map(|c| c.pairings.len()));
    fill(
        w.take_section::<u32>(Section::PairingClouds)?,
        pairing_offsets.iter().map(|&o| o as u32),
    );
    Ok(())
}

/// The cells of level `l` of a cloud: the voxels at level 0 (built with or without
/// maps), else the level's own.
fn level_cells(cloud: &Cloud, l: usize) -> &[[i32; 3]] {
    match l {
        0 => &cloud.voxels.coords,
        _ => &cloud.levels[l].coords,
    }
}

/// The first row of each cloud at level `l`, and the total.
fn level_rows(samples: &[Sample], l: usize) -> Vec<usize> {
    offsets(
        samples
            .iter()
            .flat_map(clouds)
            .map(|c| level_cells(c, l).len()),
    )
}

/// The cell sections of level `l`: coordinates and cloud offsets; returns the offsets
/// (the first row of each cloud, and the total).
fn write_level_cells(
    samples: &[Sample],
    l: usize,
    w: &mut BatchWriter<'_>,
) -> Result<Vec<usize>, BatchError> {
    let all_clouds = || samples.iter().flat_map(clouds);
    let out = w.take_section::<i32>(Section::LevelCoords(l))?;
    concat(
        out,
        4,
        all_clouds().map(|c| level_cells(c, l).len()),
        |ci, dst| {
            for (d, x) in dst
                .chunks_exact_mut(4)
                .zip(level_cells(cloud_at(samples, ci), l))
            {
                d.copy_from_slice(&[ci as i32, x[0], x[1], x[2]]);
            }
        },
    );
    let rows = level_rows(samples, l);
    fill(
        w.take_section::<u32>(Section::LevelClouds(l))?,
        rows.iter().map(|&o| o as u32),
    );
    Ok(rows)
}

/// The map sections of level `l` (`rows`: its clouds' first rows): its neighbour map and,
/// unless it is the coarsest level (`down` false), the map down to level `l + 1`.
fn write_level_maps(
    samples: &[Sample],
    l: usize,
    rows: &[usize],
    down: bool,
    w: &mut BatchWriter<'_>,
) -> Result<(), BatchError> {
    let all_clouds = || samples.iter().flat_map(clouds);
    let maps: Vec<&KernelMap> = all_clouds().map(|c| &c.levels[l].neighbours).collect();
    let starts = merge(
        w.take_section::<u32>(Section::LevelNbr(l))?,
        &maps,
        (rows, rows),
        27,
    )?;
    w.write_section(Section::LevelNbrStarts(l), &starts)?;
    if down {
        let coarse = level_rows(samples, l + 1);
        let maps = all_clouds()
            .map(|c| {
                c.levels[l]
                    .down
                    .as_ref()
                    .ok_or_else(|| err("levels", format!("level {l} has no down map")))
            })
            .collect::<Result<Vec<_>, _>>()?;
        let starts = merge(
            w.take_section::<u32>(Section::LevelDown(l))?,
            &maps,
            (rows, &coarse),
            8,
        )?;
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

/// Cloud `ci` of the batch, counting every sample's clouds in batch order.
fn cloud_at(samples: &[Sample], ci: usize) -> &Cloud {
    let per = samples[0].frames.len() + 1;
    let s = &samples[ci / per];
    s.frames.get(ci % per).map_or(&s.dense, |f| &f.cloud)
}

/// Fills `dst` cloud after cloud: `write(ci, part)` gets cloud `ci`'s part of `width`
/// elements per item, `counts` giving the items of each cloud in order (the section was
/// sized for exactly their sum).
fn concat<T>(
    dst: &mut [T],
    width: usize,
    counts: impl Iterator<Item = usize>,
    mut write: impl FnMut(usize, &mut [T]),
) {
    let mut rest = dst;
    for (ci, n) in counts.enumerate() {
        let (part, tail) = rest.split_at_mut((n * width).min(rest.len()));
        write(ci, part);
        rest = tail;
    }
}

/// Writes per-cloud kernel maps into `dst` offset by offset, shifting input rows by
/// `rows.0[cloud]` and output rows by `rows.1[cloud]`; returns the `kernels + 1` starts.
fn merge(
    dst: &mut [u32],
    maps: &[&KernelMap],
    (in_rows, out_rows): (&[usize], &[usize]),
    kernels: usize,
) -> Result<Vec<u32>, BatchError> {
    if let Some(map) = maps.iter().find(|m| m.offsets.len() != kernels) {
        return Err(err(
            "maps",
            format!("{} kernel offsets, expected {kernels}", map.offsets.len()),
        ));
    }
    let mut starts = Vec::with_capacity(kernels + 1);
    starts.push(0);
    let mut rest = dst;
    let mut written = 0;
    for kern in 0..kernels {
        for (ci, map) in maps.iter().enumerate() {
            let (i0, o0) = (in_rows[ci] as u32, out_rows[ci] as u32);
            let pairs = map.pairs_of(kern);
            let (part, tail) = rest.split_at_mut((pairs.len() * 2).min(rest.len()));
            for (d, [i, o]) in part.chunks_exact_mut(2).zip(pairs) {
                d.copy_from_slice(&[i + i0, o + o0]);
            }
            rest = tail;
            written += pairs.len();
        }
        starts.push(written as u32);
    }
    Ok(starts)
}
