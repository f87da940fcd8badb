//! From loaded sweeps to the clouds of a sample: the dense cloud (the keyframe's points,
//! then earlier sweeps in its LiDAR frame) and, for every cloud, pairing with the frame's
//! images, augmentation, voxelization and the UNet's sparse-convolution maps.

use super::augment::Augmentation;
use super::error::SampleError;
use super::image_ops;
use super::kernel_maps::build_levels_keyed;
use super::load::{LoadedSweep, SampleContext, elapsed};
use super::project::{CameraView, pair_points};
use super::recipe::KernelMaps;
use super::rng::{Purpose, SampleRng};
use super::types::{Cloud, Pair, SampleImage, StageTimes};
use super::voxel::voxelize_keyed;
use std::time::Instant;
use superflow_schemas::Stamp;
use superflow_schemas::sensor::PointCloud;

/// The dense cloud before it is finished.
pub(super) struct DenseCloud {
    /// The keyframe's points, then each earlier sweep's, in the keyframe's LiDAR frame.
    pub cloud: PointCloud,
    /// Source sweep per point: 0 = the keyframe, k = the k-th earlier sweep.
    pub source_sweep: Vec<u8>,
    /// Stamps of the sweeps in it, keyframe first.
    pub stamps: Vec<Stamp>,
    /// Earlier sweeps that could not be loaded.
    pub missing: u32,
    /// Non-finite points dropped from the earlier sweeps.
    pub dropped_non_finite: u64,
    /// Time spent on the earlier sweeps.
    pub times: StageTimes,
}

impl DenseCloud {
    /// The keyframe's sweep `key` followed by the `earlier` ones that loaded (already in
    /// its LiDAR frame); `missing` earlier sweeps were out of the drive, and every one
    /// that failed to load is counted with them (`keyframe` names it in the log).
    pub(super) fn assemble(
        key: &LoadedSweep,
        earlier: Vec<Result<LoadedSweep, SampleError>>,
        missing: u32,
        keyframe: usize,
    ) -> Self {
        // Sized for every point at once (a clone of the keyframe's cloud, extended sweep by
        // sweep, was copied again each time it grew). Ring, time and labels stay with the
        // sweeps: the dense cloud carries positions and intensities only.
        let total = key.cloud.len()
            + earlier
                .iter()
                .filter_map(|part| part.as_ref().ok())
                .map(|sweep| sweep.cloud.len())
                .sum::<usize>();
        fn with_key<T: Copy>(first: &[T], total: usize) -> Vec<T> {
            let mut column = Vec::with_capacity(total);
            column.extend_from_slice(first);
            column
        }
        let mut source_sweep = Vec::with_capacity(total);
        source_sweep.resize(key.cloud.len(), 0u8);
        let mut dense = DenseCloud {
            cloud: PointCloud {
                stamp: key.cloud.stamp,
                frame_id: key.cloud.frame_id.clone(),
                xyz: with_key(&key.cloud.xyz, total),
                intensity: with_key(&key.cloud.intensity, total),
                ring: None,
                time_offset_secs: None,
                label: None,
            },
            source_sweep,
            stamps: vec![key.cloud.stamp],
            missing,
            dropped_non_finite: 0,
            times: StageTimes::default(),
        };
        for (j, part) in earlier.into_iter().enumerate() {
            match part {
                Ok(sweep) => {
                    dense.times.add(&sweep.times);
                    dense.dropped_non_finite += sweep.dropped;
                    dense.stamps.push(sweep.cloud.stamp);
                    let source = std::iter::repeat_n((j + 1) as u8, sweep.cloud.len());
                    dense.source_sweep.extend(source);
                    dense.cloud.xyz.extend_from_slice(&sweep.cloud.xyz);
                    dense
                        .cloud
                        .intensity
                        .extend_from_slice(&sweep.cloud.intensity);
                }
                Err(e) => {
                    tracing::debug!("dense cloud of keyframe {keyframe}: {e}");
                    dense.missing += 1;
                }
            }
        }
        dense
    }
}

impl SampleContext<'_> {
    /// Pairs `cloud` with `images` (the cloud must be in the LiDAR frame at the sweep
    /// stamp the images' `camera_from_lidar` was computed for), then augments it with the
    /// draw of cloud `number` (frames in order, then the dense cloud; all share draw 0
    /// when the recipe says so), voxelizes it and builds the maps. `known`: the pairings
    /// of the first points of `cloud` and how many points they cover (a cloud that
    /// `cloud` begins with, paired with the same `images`), reused.
    pub(super) fn finish_cloud(
        &self,
        number: u32,
        cloud: &PointCloud,
        source_sweep: Vec<u8>,
        images: &[SampleImage],
        known: Option<(&[Pair], usize)>,
    ) -> (Cloud, StageTimes) {
        let cfg = self.config;
        let stream = if cfg.augment.shared { 0 } else { number };
        let mut rng = SampleRng::new(
            cfg.seed,
            self.id.epoch,
            self.id.index,
            Purpose::Augment { cloud: stream },
        );
        let augmentation = Augmentation::draw(cfg, &mut rng);
        let mut times = StageTimes::default();
        let t = Instant::now();
        let pairings = self.pair(cloud, images, known);
        times.projection += elapsed(t);

        let t = Instant::now();
        let xyz = augmentation.applied(&cloud.xyz);
        let (voxels, voxel_keys) = voxelize_keyed(&xyz, &cfg.voxel);
        let voxel_features = voxels
            .representative
            .iter()
            .map(|&i| {
                let [x, y, z] = xyz[i as usize];
                [x, y, z, cloud.intensity[i as usize]]
            })
            .collect();
        let levels = match cfg.kernel_maps {
            KernelMaps::Unet => {
                build_levels_keyed(&voxels.coords, voxel_keys, cfg.unet_levels as usize)
            }
            // The batch's level-0 voxels are then `voxels.coords` themselves.
            KernelMaps::None => Vec::new(),
        };
        times.voxels += elapsed(t);
        let cloud = Cloud {
            xyz,
            intensity: cloud.intensity.clone(),
            source_sweep,
            pairings,
            augmentation,
            voxels,
            voxel_features,
            levels,
        };
        (cloud, times)
    }

    /// The points of `cloud` seen by each of `images`, camera slot by slot (in point
    /// order within a slot). `known` holds the pairings of the cloud's first points (a
    /// keyframe cloud the dense cloud begins with, paired with the same images): they are
    /// taken as they are and only the points after them are projected.
    fn pair(
        &self,
        cloud: &PointCloud,
        images: &[SampleImage],
        known: Option<(&[Pair], usize)>,
    ) -> Vec<Pair> {
        let cfg = self.config;
        let out_size = (cfg.image_width, cfg.image_height);
        let (known, skip) = known.unwrap_or((&[], 0));
        let skip = skip.min(cloud.xyz.len());
        // Every slot's points first, so that the pairings are allocated once.
        let seen: Vec<_> = images
            .iter()
            .map(|image| {
                let view = CameraView::new(&image.calibration, image.camera_from_lidar);
                pair_points(&cloud.xyz[skip..], &view)
            })
            .collect();
        let mut pairings =
            Vec::with_capacity(known.len() + seen.iter().map(Vec::len).sum::<usize>());
        let mut known = known;
        for (slot, (image, seen)) in images.iter().zip(seen).enumerate() {
            // Known pairings are in slot order: this slot's come first.
            let (this_slot, later) =
                known.split_at(known.partition_point(|p| usize::from(p.camera) <= slot));
            pairings.extend_from_slice(this_slot);
            known = later;
            let first = pairings.len();
            pairings.extend(seen.into_iter().map(|p| {
                let (row, col) =
                    image_ops::resized_pixel(p.u, p.v, image.native_size, out_size, image.flipped);
                Pair {
                    point: p.point + skip as u32,
                    camera: slot as u8,
                    u: p.u,
                    v: p.v,
                    depth: p.depth,
                    row,
                    col,
                    superpixel: 0,
                }
            }));
            // The superpixel ids in a loop of their own: its loads (scattered over a map
            // that is mostly out of cache by now) do not wait on each other.
            for pair in &mut pairings[first..] {
                let pixel = pair.row as usize * cfg.image_width as usize + pair.col as usize;
                pair.superpixel = image.superpixels[pixel];
            }
        }
        pairings
    }
}
