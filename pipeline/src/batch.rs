//! Samples → one batch, written in place into a payload buffer (in the service, the
//! loaned iceoryx2 slice): no intermediate serialization, each byte written once.
//!
//! A batch holds `B` samples of `F` temporal frames, `K` cameras each, and `C = F + 1`
//! clouds per sample (the frames in time order, then the dense cloud). Clouds are
//! concatenated row-wise, cloud `b·C + c` after cloud `b·C + c − 1`, with offset tables
//! (`*_clouds`, `B·C + 1` entries) so the trainer runs the 3D network on all clouds at
//! once. Indices in the maps and pairings are global rows of the batch. Images are
//! numbered `(b·F + f)·K + k`; the dense cloud of sample `b` pairs with the images of its
//! keyframe. The sections (see `schemas/BATCH_FORMAT.md` for the container):
//!
//! | section | dtype | shape | meaning |
//! |---|---|---|---|
//! | `sample_ids` | u64 | B×5 | epoch, index in epoch, keyframe, drive, sweep |
//! | `frame_stamps` | i64 | B×F | LiDAR stamp of each frame, ns |
//! | `frame_offsets` | i32 | F | frame offsets in units of Δt (−1, 0, 1) |
//! | `camera_ids` | u32 | B×K | camera index in the drive per slot |
//! | `image_stamps` | i64 | B·F·K | image stamps, ns |
//! | `image_flipped` | u8 | B·F·K | 1 if the image was mirrored |
//! | `images` | u8 | B·F·K×H×W×3 | RGB, resized |
//! | `superpixels` | u16 | B·F·K×H×W | superpixel id per pixel (ids per frame) |
//! | `num_superpixels` | u32 | B×F | ids of frame (b, f) are `0..n` |
//! | `points` | f32 | N×4 | x, y, z (augmented), intensity |
//! | `point_clouds` | u32 | B·C+1 | first point row of each cloud |
//! | `source_sweep` | u8 | N | 0 = keyframe sweep, k = k-th earlier (dense cloud) |
//! | `point_to_voxel` | u32 | N | level-0 voxel row of each point |
//! | `augmentation` | f32 | B·C×4 | flip_x, flip_y, yaw (rad), scale |
//! | `pairing_point` | u32 | P | point row |
//! | `pairing_image` | u32 | P | image number |
//! | `pairing_pixel` | u16 | P×2 | (row, col) in the resized image |
//! | `pairing_uv` | f32 | P×2 | (u, v) in the raw image |
//! | `pairing_depth` | f32 | P | depth, m |
//! | `pairing_superpixel` | u32 | P | superpixel id (of the frame) of the pixel |
//! | `pairing_clouds` | u32 | B·C+1 | first pairing of each cloud |
//! | `voxel_features` | f32 | V₀×4 | representative point's x, y, z, intensity |
//! | `l{l}_coords` | i32 | V_l×4 | cloud, then the cell at level l (stride 2^l) |
//! | `l{l}_clouds` | u32 | B·C+1 | first voxel row of each cloud at level l |
//! | `l{l}_nbr` | u32 | E×2 | 3×3×3 map (input row, output row), offset by offset |
//! | `l{l}_nbr_starts` | u32 | 28 | pairs of offset k are `nbr[starts[k]..starts[k+1]]` |
//! | `l{l}_down` | u32 | V_l×2 | stride-2 map (row at l, row at l+1); transpose = up |
//! | `l{l}_down_starts` | u32 | 9 | pairs of child position k |
//!
//! Offsets of the kernels: `l{l}_nbr` offset k is `(k/9 − 1, (k/3)%3 − 1, k%3 − 1)`;
//! `l{l}_down` offset k is the child's position `(k>>2 & 1, k>>1 & 1, k & 1)` in its
//! parent cell.

use crate::sample::SampleConfig;
use crate::sample::builder::{Cloud, Sample};
use crate::sample::sparse::KernelMap;
use superflow_schemas::batch::{BatchError, BatchLayout, BatchMeta, BatchWriter, SectionId};

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
    ids: Vec<SectionId>,
}

impl BatchPlan {
    /// Plans the sections for `samples` (all built with the same recipe).
    pub fn new(samples: &[Sample], shape: BatchShape) -> Result<Self, BatchError> {
        let first = samples
            .first()
            .ok_or_else(|| err("samples", "empty batch"))?;
        let b = samples.len();
        let f = first.frames.len();
        let k = first.cameras.len();
        for s in samples {
            if s.frames.len() != f || s.cameras.len() != k {
                return Err(err("samples", "samples of different recipes in one batch"));
            }
            if s.frames.iter().any(|fr| fr.num_superpixels > 65_536) {
                return Err(err("superpixels", "more than 65536 superpixels in a frame"));
            }
        }
        let c = f + 1;
        let n: usize = samples.iter().flat_map(clouds).map(|c| c.xyz.len()).sum();
        let p: usize = samples
            .iter()
            .flat_map(clouds)
            .map(|c| c.pairings.len())
            .sum();
        let images = b * f * k;
        let (h, w) = (shape.height, shape.width);
        let mut layout = BatchLayout::new();
        let mut ids = vec![
            layout.add::<u64>("sample_ids", &[b, 5])?,
            layout.add::<i64>("frame_stamps", &[b, f])?,
            layout.add::<i32>("frame_offsets", &[f])?,
            layout.add::<u32>("camera_ids", &[b, k])?,
            layout.add::<i64>("image_stamps", &[images])?,
            layout.add::<u8>("image_flipped", &[images])?,
            layout.add::<u8>("images", &[images, h, w, 3])?,
            layout.add::<u16>("superpixels", &[images, h, w])?,
            layout.add::<u32>("num_superpixels", &[b, f])?,
            layout.add::<f32>("points", &[n, 4])?,
            layout.add::<u32>("point_clouds", &[b * c + 1])?,
            layout.add::<u8>("source_sweep", &[n])?,
            layout.add::<u32>("point_to_voxel", &[n])?,
            layout.add::<f32>("augmentation", &[b * c, 4])?,
            layout.add::<u32>("pairing_point", &[p])?,
            layout.add::<u32>("pairing_image", &[p])?,
            layout.add::<u16>("pairing_pixel", &[p, 2])?,
            layout.add::<f32>("pairing_uv", &[p, 2])?,
            layout.add::<f32>("pairing_depth", &[p])?,
            layout.add::<u32>("pairing_superpixel", &[p])?,
            layout.add::<u32>("pairing_clouds", &[b * c + 1])?,
        ];
        let v0: usize = samples
            .iter()
            .flat_map(clouds)
            .map(|c| c.voxels.coords.len())
            .sum();
        ids.push(layout.add::<f32>("voxel_features", &[v0, 4])?);
        for l in 0..shape.levels {
            let mut v = 0;
            let mut e = 0;
            for cloud in samples.iter().flat_map(clouds) {
                let level = cloud
                    .levels
                    .get(l)
                    .ok_or_else(|| err("levels", format!("a cloud has no level {l}")))?;
                v += level.coords.len();
                e += level.neighbours.pairs.len();
            }
            ids.push(layout.add::<i32>(&format!("l{l}_coords"), &[v, 4])?);
            ids.push(layout.add::<u32>(&format!("l{l}_clouds"), &[b * c + 1])?);
            ids.push(layout.add::<u32>(&format!("l{l}_nbr"), &[e, 2])?);
            ids.push(layout.add::<u32>(&format!("l{l}_nbr_starts"), &[28])?);
            if l + 1 < shape.levels {
                ids.push(layout.add::<u32>(&format!("l{l}_down"), &[v, 2])?);
                ids.push(layout.add::<u32>(&format!("l{l}_down_starts"), &[9])?);
            }
        }
        Ok(Self { layout, shape, ids })
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
        let mut ids = self.ids.iter().copied();
        let mut next = || {
            ids.next()
                .ok_or_else(|| err("layout", "fewer sections than planned"))
        };
        let f = samples[0].frames.len();
        let k = samples[0].cameras.len();
        let (h, wd) = (self.shape.height, self.shape.width);

        fill(
            w.take::<u64>(next()?)?,
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
            w.take::<i64>(next()?)?,
            samples
                .iter()
                .flat_map(|s| s.frames.iter().map(|fr| fr.lidar_stamp.nanos())),
        );
        fill(
            w.take::<i32>(next()?)?,
            samples[0].frames.iter().map(|fr| fr.offset),
        );
        fill(
            w.take::<u32>(next()?)?,
            samples
                .iter()
                .flat_map(|s| s.camera_indices.iter().copied()),
        );
        let images = || {
            samples
                .iter()
                .flat_map(|s| s.frames.iter().flat_map(|fr| fr.images.iter()))
        };
        fill(w.take::<i64>(next()?)?, images().map(|i| i.stamp.nanos()));
        fill(
            w.take::<u8>(next()?)?,
            images().map(|i| u8::from(i.flipped)),
        );
        let out = w.take::<u8>(next()?)?;
        for (dst, img) in out.chunks_exact_mut(h * wd * 3).zip(images()) {
            if img.rgb.len() != dst.len() {
                return Err(err("images", "image size differs from the recipe"));
            }
            dst.copy_from_slice(&img.rgb);
        }
        let out = w.take::<u16>(next()?)?;
        for (dst, img) in out.chunks_exact_mut(h * wd).zip(images()) {
            fill(dst, img.superpixels.iter().map(|&id| id as u16));
        }
        fill(
            w.take::<u32>(next()?)?,
            samples
                .iter()
                .flat_map(|s| s.frames.iter().map(|fr| fr.num_superpixels)),
        );

        let all_clouds = || samples.iter().flat_map(clouds);
        fill(
            w.take::<f32>(next()?)?,
            all_clouds().flat_map(|c| {
                c.xyz
                    .iter()
                    .zip(&c.intensity)
                    .flat_map(|(p, i)| [p[0], p[1], p[2], *i])
            }),
        );
        let point_offsets = offsets(all_clouds().map(|c| c.xyz.len()));
        fill(
            w.take::<u32>(next()?)?,
            point_offsets.iter().map(|&o| o as u32),
        );
        fill(
            w.take::<u8>(next()?)?,
            all_clouds().flat_map(|c| c.source_sweep.iter().copied()),
        );
        let voxel_offsets = offsets(all_clouds().map(|c| c.voxels.coords.len()));
        fill(
            w.take::<u32>(next()?)?,
            all_clouds()
                .zip(&voxel_offsets)
                .flat_map(|(c, &o)| c.voxels.point_to_voxel.iter().map(move |&v| v + o as u32)),
        );
        fill(
            w.take::<f32>(next()?)?,
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
        // Pairings: the image number of a cloud's pairing is its frame's (the
        // keyframe's for the dense cloud).
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
            w.take::<u32>(next()?)?,
            pairings().flat_map(|(ci, _, cloud)| {
                let o = point_offsets[ci] as u32;
                cloud.pairings.iter().map(move |p| p.point + o)
            }),
        );
        fill(
            w.take::<u32>(next()?)?,
            pairings().flat_map(|(_, first_image, cloud)| {
                cloud
                    .pairings
                    .iter()
                    .map(move |p| (first_image + usize::from(p.camera)) as u32)
            }),
        );
        fill(
            w.take::<u16>(next()?)?,
            all_clouds().flat_map(|c| c.pairings.iter().flat_map(|p| [p.row, p.col])),
        );
        fill(
            w.take::<f32>(next()?)?,
            all_clouds().flat_map(|c| c.pairings.iter().flat_map(|p| [p.u, p.v])),
        );
        fill(
            w.take::<f32>(next()?)?,
            all_clouds().flat_map(|c| c.pairings.iter().map(|p| p.depth)),
        );
        fill(
            w.take::<u32>(next()?)?,
            all_clouds().flat_map(|c| c.pairings.iter().map(|p| p.superpixel)),
        );
        let pairing_offsets = offsets(all_clouds().map(|c| c.pairings.len()));
        fill(
            w.take::<u32>(next()?)?,
            pairing_offsets.iter().map(|&o| o as u32),
        );
        fill(
            w.take::<f32>(next()?)?,
            all_clouds().flat_map(|c| c.voxel_features.iter().flatten().copied()),
        );

        for l in 0..self.shape.levels {
            let rows = offsets(all_clouds().map(|c| c.levels[l].coords.len()));
            fill(
                w.take::<i32>(next()?)?,
                all_clouds().enumerate().flat_map(|(ci, c)| {
                    c.levels[l]
                        .coords
                        .iter()
                        .flat_map(move |x| [ci as i32, x[0], x[1], x[2]])
                }),
            );
            fill(w.take::<u32>(next()?)?, rows.iter().map(|&o| o as u32));
            let maps: Vec<&KernelMap> = all_clouds().map(|c| &c.levels[l].neighbours).collect();
            let (pairs, starts) = merge(&maps, &rows, &rows, 27)?;
            w.write(next()?, &pairs)?;
            w.write(next()?, &starts)?;
            if l + 1 < self.shape.levels {
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
                w.write(next()?, &pairs)?;
                w.write(next()?, &starts)?;
            }
        }
        Ok(())
    }
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
