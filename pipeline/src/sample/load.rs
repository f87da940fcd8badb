//! Reading what one sample needs from its drive. A [`SampleContext`] holds what every
//! load of the sample shares (recipe, drive, identity, cameras); with it a sweep is
//! decoded and de-skewed ([`SampleContext::load_sweep`]), moved into the keyframe's
//! LiDAR frame for the dense cloud ([`SampleContext::load_into_key_frame`]), or loaded
//! with the frame's images ([`SampleContext::load_frame`], images in `images.rs`).
//! Reads go through a per-thread chunk cache.

use super::deskew::deskew_in_place;
use super::error::SampleError;
use super::frames::{FrameCache, FrameKey, LastUses, SweepEntry};
use super::recipe::SampleConfig;
use super::timing::CameraScan;
use super::types::{SampleId, SampleImage, StageTimes};
use crate::drive::TfError;
use crate::drive::{Drive, LidarStream};
use crate::source::ChunkCache;
use nalgebra::Point3;
use rayon::prelude::*;
use std::cell::RefCell;
use std::sync::Arc;
use std::time::Instant;
use superflow_schemas::Stamp;
use superflow_schemas::sensor::PointCloud;

thread_local! {
    static CACHE: RefCell<ChunkCache> = RefCell::new(ChunkCache::new(6));
}

/// Runs `f` with this thread's chunk cache. Decoders may run rayon jobs (JPEG), so a
/// thread can come back here while its cache is in use: it then reads through a
/// temporary cache (the result is the same, only slower).
pub(super) fn with_cache<T>(f: impl FnOnce(&mut ChunkCache) -> T) -> T {
    CACHE.with(|c| match c.try_borrow_mut() {
        Ok(mut cache) => f(&mut cache),
        Err(_) => f(&mut ChunkCache::new(2)),
    })
}

/// Nanoseconds since `t`.
pub(super) fn elapsed(t: Instant) -> u64 {
    t.elapsed().as_nanos() as u64
}

/// What every load of one sample shares.
#[derive(Debug, Clone, Copy)]
pub(super) struct SampleContext<'a> {
    /// The recipe.
    pub config: &'a SampleConfig,
    /// The keyframe's drive.
    pub drive: &'a Drive,
    /// Which keyframe and draws (keys the image flips).
    pub id: SampleId,
    /// Superpixels come from the drive's class maps (else SLIC).
    pub class_superpixels: bool,
    /// SLIC superpixels come from the drive's `.slic.mcap` sidecar (else computed).
    pub slic_sidecar: bool,
    /// The chosen cameras' indices in the drive, slot order.
    pub chosen: &'a [usize],
    /// When the drive's LiDAR scans each camera.
    pub scan: &'a CameraScan,
    /// Frames shared with the neighbouring samples (the `blocks` order), if kept.
    pub frames: Option<&'a FrameCache>,
    /// The sample's position in the run (`epoch × samples per epoch + index`): how the
    /// frame cache tells what is still in use.
    pub position: u64,
    /// The last position of the epoch that asks for each frame (with `frames`).
    pub last_uses: Option<&'a LastUses>,
}

/// A sweep decoded, de-skewed and in its LiDAR frame at its stamp.
pub(super) struct LoadedSweep {
    /// The points (shared with the frame cache under the `blocks` order).
    pub cloud: Arc<PointCloud>,
    /// Non-finite points dropped when decoding.
    pub dropped: u64,
    /// Time spent.
    pub times: StageTimes,
}

/// What a frame needs before its clouds are finished.
pub(super) struct FrameInputs {
    /// The frame's sweep.
    pub sweep: LoadedSweep,
    /// The chosen cameras' images, slot order.
    pub images: Vec<SampleImage>,
    /// Superpixel ids of the frame are `0..num_superpixels`.
    pub num_superpixels: u32,
    /// Time spent on the images.
    pub times: StageTimes,
}

impl SampleContext<'_> {
    /// A missing transform, naming the drive's files.
    pub(super) fn transform_error(
        &self,
        what: String,
        stamp: Stamp,
        source: TfError,
    ) -> SampleError {
        SampleError::Transform {
            files: self.drive.file_list(),
            what,
            stamp,
            source: Box::new(source),
        }
    }

    /// The drive's LiDAR.
    fn lidar(&self) -> Result<&LidarStream, SampleError> {
        self.drive
            .lidar
            .as_ref()
            .ok_or_else(|| SampleError::NoLidar {
                files: self.drive.file_list(),
            })
    }

    /// This sample's use of frame `key`: its position, and whether it is the last one.
    pub(super) fn use_of(&self, key: FrameKey) -> (u64, bool) {
        let last = self
            .last_uses
            .is_some_and(|uses| uses.get(&key) == Some(&self.position));
        (self.position, last)
    }

    /// Sweep `sweep`, decoded and de-skewed ([`Self::decode_sweep`]) or from the frame
    /// cache.
    pub(super) fn load_sweep(&self, sweep: u32) -> Result<LoadedSweep, SampleError> {
        let Some(cache) = self.frames else {
            let (entry, times) = self.decode_sweep(sweep)?;
            return Ok(LoadedSweep {
                cloud: entry.cloud,
                dropped: entry.dropped,
                times,
            });
        };
        let key = (self.id.drive, sweep);
        let used = self.use_of(FrameKey::Sweep {
            drive: key.0,
            sweep,
        });
        let (entry, times) = cache.sweep(key, used, || self.decode_sweep(sweep))?;
        // Shared, not copied: only the dense cloud's earlier sweeps are changed, and
        // `load_into_key_frame` copies one only while a later sample still holds it.
        Ok(LoadedSweep {
            cloud: Arc::clone(&entry.cloud),
            dropped: entry.dropped,
            times,
        })
    }

    /// Decodes sweep `sweep` and de-skews it when configured and it has per-point time.
    fn decode_sweep(&self, sweep: u32) -> Result<(SweepEntry, StageTimes), SampleError> {
        let drive = self.drive;
        let mut times = StageTimes::default();
        let lidar = self.lidar()?;
        let frame = &lidar.sweeps[sweep as usize];
        let t = Instant::now();
        let decoded = with_cache(|cache| drive.read_sweep(frame, cache))?;
        times.decode += elapsed(t);
        if decoded.cloud.is_empty() {
            // Nothing to pair, voxelize or contrast: refuse rather than train on it.
            return Err(drive
                .decode_error(
                    frame,
                    &lidar.topic,
                    format!(
                        "the sweep has no finite point ({} non-finite dropped)",
                        decoded.dropped_non_finite
                    ),
                )
                .into());
        }
        let mut cloud = decoded.cloud;
        if self.config.deskew && cloud.time_offset_secs.is_some() {
            let t = Instant::now();
            let map = drive.map_frame.as_deref().unwrap_or_default();
            deskew_in_place(&mut cloud, &drive.tf, map).map_err(|e| {
                self.transform_error(format!("de-skew of {}", lidar.topic), frame.stamp, e)
            })?;
            times.sweeps += elapsed(t);
        }
        let entry = SweepEntry {
            cloud: Arc::new(cloud),
            dropped: decoded.dropped_non_finite as u64,
        };
        Ok((entry, times))
    }

    /// Sweep `sweep` moved into the LiDAR frame of sweep `key`:
    /// `key_lidar_from_map(t_key) · map_from_lidar(t_s)`.
    pub(super) fn load_into_key_frame(
        &self,
        sweep: u32,
        key: u32,
    ) -> Result<LoadedSweep, SampleError> {
        let mut loaded = self.load_sweep(sweep)?;
        let t = Instant::now();
        let lidar = self.lidar()?;
        let map = self.drive.map_frame.as_deref().unwrap_or_default();
        let key_stamp = lidar.sweeps[key as usize].stamp;
        let lookup = |stamp: Stamp| {
            self.drive
                .tf
                .lookup(map, &lidar.frame_id, stamp)
                .map_err(|e| self.transform_error(format!("pose of {}", lidar.topic), stamp, e))
        };
        let key_from_sweep = lookup(key_stamp)?.inverse() * lookup(loaded.cloud.stamp)?;
        for p in &mut Arc::make_mut(&mut loaded.cloud).xyz {
            let q = key_from_sweep * Point3::new(f64::from(p[0]), f64::from(p[1]), f64::from(p[2]));
            *p = [q.x as f32, q.y as f32, q.z as f32];
        }
        loaded.times.sweeps += elapsed(t);
        Ok(loaded)
    }

    /// Temporal frame `frame_pos`: sweep `sweep` and the chosen cameras' images, loaded
    /// in parallel, with the superpixel ids of the images made distinct within the frame.
    pub(super) fn load_frame(
        &self,
        frame_pos: u32,
        sweep: u32,
    ) -> Result<FrameInputs, SampleError> {
        let (sweep_result, images) = rayon::join(
            || self.load_sweep(sweep),
            || {
                self.chosen
                    .par_iter()
                    .enumerate()
                    .map(|(slot, &c)| self.load_image(c, sweep, frame_pos, slot))
                    .collect::<Result<Vec<_>, _>>()
            },
        );
        let sweep = sweep_result?;
        let mut times = StageTimes::default();
        let mut images = images?;
        // Superpixel ids: class ids as they are (view-consistent), SLIC labels offset per
        // image.
        let mut num_superpixels = if self.class_superpixels {
            self.config.num_classes
        } else {
            0
        };
        for (image, count, t) in &mut images {
            times.add(t);
            if !self.class_superpixels {
                for id in &mut image.superpixels {
                    *id += num_superpixels;
                }
                num_superpixels += *count;
            }
        }
        Ok(FrameInputs {
            sweep,
            images: images.into_iter().map(|(i, _, _)| i).collect(),
            num_superpixels,
            times,
        })
    }
}
