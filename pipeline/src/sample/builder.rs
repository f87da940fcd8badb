//! From a dataset to samples: the [`Plan`] lists every usable keyframe with its temporal
//! context; [`SampleBuilder::build`] turns `(epoch, index)` into a [`Sample`] — decoded
//! and de-skewed sweeps, the dense cloud, chosen cameras with resized (and maybe
//! flipped) images and superpixels, point↔pixel pairings, augmented clouds, voxels and
//! the UNet's sparse-convolution maps. Work inside a sample runs on rayon; every random
//! choice comes from a [`SampleRng`] stream keyed by `(seed, epoch, index)`.

use super::image_ops;
use super::project::{CameraView, camera_from_lidar, deskew, pair_points};
use super::recipe::{EdgePolicy, SampleConfig, SuperpixelSource};
use super::rng::{Purpose, SampleRng};
use super::slic::slic;
use super::sparse::{Level, build_levels};
use super::voxel::{Voxelized, voxelize};
use crate::decode::image::Target;
use crate::drive::TfError;
use crate::drive::dataset::{CameraStream, Dataset, Drive, FrameRef, ReadError, nearest};
use crate::source::ChunkCache;
use nalgebra::{Isometry3, Point3, Rotation3, Vector3};
use rayon::prelude::*;
use serde::Serialize;
use std::cell::RefCell;
use std::time::Instant;
use superflow_schemas::Stamp;
use superflow_schemas::sensor::{CameraCalibration, PixelFormat, PointCloud};

/// Class maps are matched to images by stamp within this tolerance.
pub const CLASS_MAP_TOLERANCE_NANOS: i64 = 1_000_000;

/// Why a sample (or a plan) cannot be built. Each names the file, channel and time.
#[derive(Debug, thiserror::Error)]
pub enum SampleError {
    /// A message could not be read or decoded.
    #[error(transparent)]
    Read(#[from] ReadError),
    /// A transform is missing at the instant a sensor needs it.
    #[error("{files}: {what} at {stamp}: {source}")]
    Transform {
        /// The drive's files.
        files: String,
        /// Which sensor needed it.
        what: String,
        /// The instant.
        stamp: Stamp,
        /// The lookup error.
        source: Box<TfError>,
    },
    /// A class map that cannot serve as superpixels.
    #[error("{files}: {topic} at {stamp}: {reason}")]
    Superpixels {
        /// The drive's files.
        files: String,
        /// The class-map topic.
        topic: String,
        /// The image stamp.
        stamp: Stamp,
        /// What is wrong.
        reason: String,
    },
    /// An image that does not match its calibration.
    #[error("{files}: {topic} at {stamp}: {reason}")]
    Image {
        /// The drive's files.
        files: String,
        /// The image topic.
        topic: String,
        /// The image stamp.
        stamp: Stamp,
        /// What is wrong.
        reason: String,
    },
    /// The recipe cannot be used with this dataset.
    #[error("{0}")]
    Config(String),
    /// An index past the plan.
    #[error("keyframe {index} requested, the plan has {len}")]
    OutOfRange {
        /// The index asked for.
        index: usize,
        /// Keyframes in the plan.
        len: usize,
    },
}

/// One keyframe of the plan and the sweeps of its temporal frames.
#[derive(Debug, Clone, PartialEq, Eq, Serialize)]
pub struct KeyframeRef {
    /// Drive index in the dataset.
    pub drive: u32,
    /// LiDAR sweep index of the keyframe.
    pub sweep: u32,
    /// Sweep index of each temporal frame, in time order (see
    /// [`SampleConfig::frame_offsets`]); the keyframe's own index where the edge policy
    /// reused it.
    pub frame_sweeps: Vec<u32>,
    /// Context frames that fell outside the drive and were replaced by the keyframe.
    pub reused: u32,
}

/// Every usable keyframe of a dataset, in drive and time order.
#[derive(Debug, Clone, Default, Serialize)]
pub struct Plan {
    /// The keyframes.
    pub keyframes: Vec<KeyframeRef>,
    /// Keyframes left out because a context frame was missing (edge policy `skip`).
    pub skipped_at_edges: u64,
}

/// Whether sweep `i` can be a frame of a sample: the ego pose is known at the sweep and
/// every camera has a calibration and an image within half its period whose pose is
/// known.
fn usable(drive: &Drive, i: usize) -> bool {
    let (Some(lidar), Some(map), Some(ego)) = (&drive.lidar, &drive.map_frame, &drive.ego_frame)
    else {
        return false;
    };
    let Some(sweep) = lidar.sweeps.get(i) else {
        return false;
    };
    let pose_ok = |s: Stamp| drive.tf.lookup(map, ego, s).is_ok();
    pose_ok(sweep.stamp)
        && !drive.cameras.is_empty()
        && drive.cameras.iter().all(|camera| {
            camera_frame_for(camera, sweep.stamp).is_some_and(|f| pose_ok(f.stamp))
                && !camera.calibrations.is_empty()
        })
}

/// The image of `camera` for a sweep at `stamp`: the nearest one, if within half the
/// camera's period.
fn camera_frame_for(camera: &CameraStream, stamp: Stamp) -> Option<&FrameRef> {
    let half = camera.period_nanos().unwrap_or(0) / 2;
    nearest(&camera.frames, stamp).filter(|f| f.stamp.nanos_since(stamp).abs() <= half)
}

fn median_sweep_period(drive: &Drive) -> i64 {
    let Some(lidar) = &drive.lidar else { return 0 };
    let mut gaps: Vec<i64> = lidar
        .sweeps
        .windows(2)
        .map(|w| w[1].stamp.nanos_since(w[0].stamp))
        .collect();
    gaps.sort_unstable();
    gaps.get(gaps.len() / 2).copied().unwrap_or(0)
}

impl Plan {
    /// Keyframes of every drive (see `Drive::keyframes`) with their context frames: the
    /// sweep nearest to `t + k·Δt` if within half a LiDAR period and usable, else the
    /// edge policy decides.
    pub fn new(dataset: &Dataset, config: &SampleConfig) -> Plan {
        let mut plan = Plan::default();
        let interval = (config.keyframe_interval_secs * 1e9).round() as i64;
        let delta = (config.delta_t_secs * 1e9).round() as i64;
        for (d, drive) in dataset.drives.iter().enumerate() {
            let Some(lidar) = &drive.lidar else { continue };
            let half_period = median_sweep_period(drive) / 2;
            for key in drive.keyframes(interval) {
                let t = lidar.sweeps[key].stamp;
                let mut frame_sweeps = Vec::new();
                let mut reused = 0;
                let mut skip = false;
                for &offset in config.frame_offsets() {
                    if offset == 0 {
                        frame_sweeps.push(key as u32);
                        continue;
                    }
                    let target = t.add_nanos(i64::from(offset) * delta);
                    let found = nearest(&lidar.sweeps, target)
                        .filter(|f| f.stamp.nanos_since(target).abs() <= half_period)
                        .map(|f| lidar.sweeps.partition_point(|s| s.stamp < f.stamp))
                        .filter(|&i| usable(drive, i));
                    match (found, config.edge) {
                        (Some(i), _) => frame_sweeps.push(i as u32),
                        (None, EdgePolicy::Reuse) => {
                            frame_sweeps.push(key as u32);
                            reused += 1;
                        }
                        (None, EdgePolicy::Skip) => skip = true,
                    }
                }
                if skip {
                    plan.skipped_at_edges += 1;
                } else {
                    plan.keyframes.push(KeyframeRef {
                        drive: d as u32,
                        sweep: key as u32,
                        frame_sweeps,
                        reused,
                    });
                }
            }
        }
        plan
    }

    /// The keyframe order of `epoch`: a shuffle seeded by `(seed, epoch)`.
    pub fn epoch_order(&self, seed: u64, epoch: u64) -> Vec<u32> {
        let mut order: Vec<u32> = (0..self.keyframes.len() as u32).collect();
        SampleRng::new(seed, epoch, 0, Purpose::Shuffle).shuffle(&mut order);
        order
    }
}

/// Identity of a sample: which keyframe and which draws.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Serialize)]
pub struct SampleId {
    /// Epoch of the draws.
    pub epoch: u64,
    /// Position in the epoch (keys every random draw).
    pub index: u64,
    /// Keyframe number in the plan.
    pub keyframe: u32,
    /// Drive of the keyframe.
    pub drive: u32,
    /// Sweep of the keyframe.
    pub sweep: u32,
}

/// The 3D augmentation drawn for one cloud: `p' = scale · Rz(yaw) · flip · p`.
#[derive(Debug, Clone, Copy, PartialEq, Serialize)]
pub struct Augmentation {
    /// x → −x.
    pub flip_x: bool,
    /// y → −y.
    pub flip_y: bool,
    /// Rotation about z, radians.
    pub yaw_rad: f64,
    /// Scale factor.
    pub scale: f64,
}

impl Augmentation {
    /// No change.
    pub const IDENTITY: Augmentation = Augmentation {
        flip_x: false,
        flip_y: false,
        yaw_rad: 0.0,
        scale: 1.0,
    };

    fn draw(config: &SampleConfig, rng: &mut SampleRng) -> Self {
        let a = &config.augment;
        if !a.enabled {
            return Self::IDENTITY;
        }
        Augmentation {
            flip_x: rng.bernoulli(a.flip_x_probability),
            flip_y: rng.bernoulli(a.flip_y_probability),
            yaw_rad: rng.uniform(0.0, a.rotation_max_rad),
            scale: rng.uniform(a.scale_min, a.scale_max),
        }
    }

    /// Applies the augmentation to points in place.
    pub fn apply(&self, xyz: &mut [[f32; 3]]) {
        if *self == Self::IDENTITY {
            return;
        }
        let r =
            Rotation3::from_axis_angle(&Vector3::z_axis(), self.yaw_rad).into_inner() * self.scale;
        let (sx, sy) = (
            if self.flip_x { -1.0 } else { 1.0 },
            if self.flip_y { -1.0 } else { 1.0 },
        );
        for p in xyz {
            let v = r * Vector3::new(sx * f64::from(p[0]), sy * f64::from(p[1]), f64::from(p[2]));
            *p = [v.x as f32, v.y as f32, v.z as f32];
        }
    }
}

/// A point seen by one of the sample's cameras.
#[derive(Debug, Clone, Copy, PartialEq, Serialize)]
pub struct Pair {
    /// Point index in its cloud.
    pub point: u32,
    /// Camera slot in the sample (0..k).
    pub camera: u8,
    /// Column in the raw image (float, OpenCV convention).
    pub u: f32,
    /// Row in the raw image.
    pub v: f32,
    /// Depth along the optical axis, metres.
    pub depth: f32,
    /// Row in the resized image.
    pub row: u16,
    /// Column in the resized (and possibly flipped) image.
    pub col: u16,
    /// Superpixel (superpoint) id: the id of the pixel it lands on.
    pub superpixel: u32,
}

/// One cloud of a sample, ready for the 3D network.
#[derive(Debug, Clone, PartialEq)]
pub struct Cloud {
    /// Points after augmentation (in the LiDAR frame without it).
    pub xyz: Vec<[f32; 3]>,
    /// Intensity per point.
    pub intensity: Vec<f32>,
    /// Source sweep per point: 0 = the keyframe, k = the k-th sweep before it (dense
    /// cloud); all 0 in a frame's own cloud.
    pub source_sweep: Vec<u8>,
    /// Point↔pixel pairings, camera slot by slot, in point order within a slot.
    pub pairings: Vec<Pair>,
    /// The augmentation applied after pairing.
    pub augmentation: Augmentation,
    /// Voxels of the augmented points.
    pub voxels: Voxelized,
    /// Features of each voxel's representative point: x, y, z, intensity.
    pub voxel_features: Vec<[f32; 4]>,
    /// Sparse-convolution maps per UNet level (level 0 = `voxels.coords`).
    pub levels: Vec<Level>,
}

/// One resized camera image of a frame.
#[derive(Debug, Clone, PartialEq)]
pub struct SampleImage {
    /// Camera name.
    pub camera: String,
    /// Image topic.
    pub topic: String,
    /// Image stamp.
    pub stamp: Stamp,
    /// Raw size (width, height).
    pub native_size: (u32, u32),
    /// Mirrored left to right.
    pub flipped: bool,
    /// RGB8, `image_height × image_width × 3`.
    pub rgb: Vec<u8>,
    /// Superpixel id per pixel, `image_height × image_width`.
    pub superpixels: Vec<u32>,
    /// `camera_from_lidar` used for the pairings of this frame's cloud.
    pub camera_from_lidar: Isometry3<f64>,
    /// The calibration in force.
    pub calibration: CameraCalibration,
}

/// One temporal frame.
#[derive(Debug, Clone, PartialEq)]
pub struct Frame {
    /// Offset in units of Δt (−1, 0, +1).
    pub offset: i32,
    /// LiDAR sweep index.
    pub sweep: u32,
    /// LiDAR stamp.
    pub lidar_stamp: Stamp,
    /// The chosen cameras' images, slot order.
    pub images: Vec<SampleImage>,
    /// Superpixel ids of this frame are `0..num_superpixels`.
    pub num_superpixels: u32,
    /// The sweep's cloud with its pairings.
    pub cloud: Cloud,
    /// Non-finite points dropped when decoding the sweep.
    pub dropped_non_finite: u64,
}

/// CPU time per stage, summed over threads, nanoseconds.
#[derive(Debug, Clone, Copy, Default, PartialEq, Eq, Serialize)]
pub struct StageTimes {
    /// Reading and decoding sweeps and images.
    pub decode: u64,
    /// De-skew and moving earlier sweeps into the keyframe frame.
    pub sweeps: u64,
    /// Resizing and flipping images.
    pub images: u64,
    /// Projection and pairing.
    pub projection: u64,
    /// Superpixels (class-map resize or SLIC).
    pub superpixels: u64,
    /// Augmentation, voxelization and sparse-convolution maps.
    pub voxels: u64,
}

impl StageTimes {
    /// Adds `o` stage by stage.
    pub fn add(&mut self, o: &StageTimes) {
        self.decode += o.decode;
        self.sweeps += o.sweeps;
        self.images += o.images;
        self.projection += o.projection;
        self.superpixels += o.superpixels;
        self.voxels += o.voxels;
    }
}

/// A SuperFlow training sample.
#[derive(Debug, Clone, PartialEq)]
pub struct Sample {
    /// Which keyframe and draws.
    pub id: SampleId,
    /// The seed of the draws.
    pub seed: u64,
    /// Names of the chosen cameras, slot order.
    pub cameras: Vec<String>,
    /// Indices of the chosen cameras in the drive's camera list, slot order.
    pub camera_indices: Vec<u32>,
    /// Temporal frames in time order.
    pub frames: Vec<Frame>,
    /// Position of the keyframe (t) in `frames`.
    pub key_frame: usize,
    /// The dense cloud: the keyframe's points first (source 0, same order as its frame
    /// cloud before augmentation), then each earlier sweep's, in the keyframe's LiDAR frame;
    /// paired with the keyframe's images.
    pub dense: Cloud,
    /// Stamps of the dense cloud's sweeps (keyframe first).
    pub dense_stamps: Vec<Stamp>,
    /// Earlier sweeps the recipe asked for that the drive could not give (drive start,
    /// missing pose).
    pub dense_missing: u32,
    /// Non-finite points dropped when decoding the dense cloud's earlier sweeps (the
    /// keyframe's own are in its [`Frame::dropped_non_finite`]).
    pub dense_dropped_non_finite: u64,
    /// Superpixels came from the recording's class maps (else SLIC).
    pub class_superpixels: bool,
    /// Time per stage.
    pub times: StageTimes,
}

thread_local! {
    static CACHE: RefCell<ChunkCache> = RefCell::new(ChunkCache::new(6));
}

/// Runs `f` with this thread's chunk cache. Decoders may run rayon jobs (JPEG), so a
/// thread can come back here while its cache is in use: it then reads through a
/// temporary cache (the result is the same, only slower).
fn with_cache<T>(f: impl FnOnce(&mut ChunkCache) -> T) -> T {
    CACHE.with(|c| match c.try_borrow_mut() {
        Ok(mut cache) => f(&mut cache),
        Err(_) => f(&mut ChunkCache::new(2)),
    })
}

fn elapsed(t: Instant) -> u64 {
    t.elapsed().as_nanos() as u64
}

/// Builds samples of a dataset.
#[derive(Debug)]
pub struct SampleBuilder<'d> {
    dataset: &'d Dataset,
    config: SampleConfig,
    plan: Plan,
    class_superpixels: Vec<bool>,
}

/// A sweep decoded, de-skewed and in its LiDAR frame at its stamp.
struct LoadedSweep {
    cloud: PointCloud,
    dropped: u64,
    times: StageTimes,
}

impl<'d> SampleBuilder<'d> {
    /// Checks the recipe against the dataset and plans its keyframes.
    pub fn new(dataset: &'d Dataset, config: SampleConfig) -> Result<Self, SampleError> {
        config.validate().map_err(SampleError::Config)?;
        dataset
            .check_sensors()
            .map_err(|e| SampleError::Config(e.to_string()))?;
        let mut class_superpixels = Vec::new();
        for drive in &dataset.drives {
            let all_have = drive.cameras.iter().all(|c| !c.superpixels.is_empty());
            class_superpixels.push(match config.superpixels {
                SuperpixelSource::Auto => all_have,
                SuperpixelSource::Slic => false,
                SuperpixelSource::Channel if all_have => true,
                SuperpixelSource::Channel => {
                    let missing: Vec<&str> = drive
                        .cameras
                        .iter()
                        .filter(|c| c.superpixels.is_empty())
                        .map(|c| c.name.as_str())
                        .collect();
                    return Err(SampleError::Config(format!(
                        "{}: superpixels = \"channel\" but cameras {} have no class-map channel",
                        drive.file_list(),
                        missing.join(", ")
                    )));
                }
            });
        }
        let plan = Plan::new(dataset, &config);
        Ok(Self {
            dataset,
            config,
            plan,
            class_superpixels,
        })
    }

    /// The plan.
    pub fn plan(&self) -> &Plan {
        &self.plan
    }

    /// The recipe.
    pub fn config(&self) -> &SampleConfig {
        &self.config
    }

    /// Sample `index` of `epoch` (the epoch's shuffled keyframe order).
    pub fn build(&self, epoch: u64, index: u64) -> Result<Sample, SampleError> {
        let len = self.plan.keyframes.len();
        if index as usize >= len {
            return Err(SampleError::OutOfRange {
                index: index as usize,
                len,
            });
        }
        let order = self.plan.epoch_order(self.config.seed, epoch);
        self.build_keyframe(order[index as usize] as usize, epoch, index)
    }

    /// The sample of plan keyframe `keyframe` with the draws of `(epoch, index)`.
    pub fn build_keyframe(
        &self,
        keyframe: usize,
        epoch: u64,
        index: u64,
    ) -> Result<Sample, SampleError> {
        let key = self
            .plan
            .keyframes
            .get(keyframe)
            .ok_or(SampleError::OutOfRange {
                index: keyframe,
                len: self.plan.keyframes.len(),
            })?;
        let drive = &self.dataset.drives[key.drive as usize];
        let class_superpixels = self.class_superpixels[key.drive as usize];
        let cfg = &self.config;
        let seed = cfg.seed;
        let id = SampleId {
            epoch,
            index,
            keyframe: keyframe as u32,
            drive: key.drive,
            sweep: key.sweep,
        };
        let m = drive.cameras.len();
        let k = (cfg.cameras as usize).min(m);
        let chosen = SampleRng::new(seed, epoch, index, Purpose::Cameras).choose(m, k);
        let offsets = cfg.frame_offsets();
        let key_frame = offsets.iter().position(|o| *o == 0).unwrap_or(0);

        // Frames (sweep + images) and earlier sweeps load in parallel.
        let earlier: Vec<u32> = (1..=cfg.dense_sweeps)
            .filter_map(|j| key.sweep.checked_sub(j))
            .collect();
        let (frames, dense_parts) = rayon::join(
            || {
                key.frame_sweeps
                    .par_iter()
                    .enumerate()
                    .map(|(f, &sweep)| {
                        self.load_frame(drive, f as u32, sweep, &chosen, id, class_superpixels)
                    })
                    .collect::<Result<Vec<_>, _>>()
            },
            || {
                earlier
                    .par_iter()
                    .map(|&s| self.load_into_key_frame(drive, s, key.sweep))
                    .collect::<Vec<_>>()
            },
        );
        let frames = frames?;
        let mut times = StageTimes::default();
        let mut dense_stamps = Vec::new();
        let mut dense_missing = cfg.dense_sweeps - earlier.len() as u32;
        let mut dense_dropped_non_finite = 0;
        let key_inputs = &frames[key_frame];
        // The dense cloud: keyframe points (source 0), then earlier sweeps.
        let mut dense_cloud = key_inputs.sweep.cloud.clone();
        dense_stamps.push(dense_cloud.stamp);
        let mut source_sweep = vec![0u8; dense_cloud.len()];
        for (j, part) in dense_parts.into_iter().enumerate() {
            match part {
                Ok(sweep) => {
                    times.add(&sweep.times);
                    dense_dropped_non_finite += sweep.dropped;
                    dense_stamps.push(sweep.cloud.stamp);
                    source_sweep.extend(std::iter::repeat_n((j + 1) as u8, sweep.cloud.len()));
                    dense_cloud.xyz.extend_from_slice(&sweep.cloud.xyz);
                    dense_cloud
                        .intensity
                        .extend_from_slice(&sweep.cloud.intensity);
                }
                Err(e) => {
                    tracing::debug!("dense cloud of keyframe {keyframe}: {e}");
                    dense_missing += 1;
                }
            }
        }

        // Pairing, augmentation, voxels and maps of every cloud.
        let n_frames = frames.len() as u32;
        let mut jobs: Vec<(u32, &PointCloud, Vec<u8>, &FrameInputs)> = frames
            .iter()
            .enumerate()
            .map(|(f, fr)| {
                (
                    f as u32,
                    &fr.sweep.cloud,
                    vec![0u8; fr.sweep.cloud.len()],
                    fr,
                )
            })
            .collect();
        jobs.push((n_frames, &dense_cloud, source_sweep, key_inputs));
        let shared = cfg.augment.shared;
        let clouds: Vec<(Cloud, StageTimes)> = jobs
            .into_par_iter()
            .map(|(c, cloud, source, inputs)| {
                let stream = if shared { 0 } else { c };
                let mut rng =
                    SampleRng::new(seed, epoch, index, Purpose::Augment { cloud: stream });
                let augmentation = Augmentation::draw(cfg, &mut rng);
                self.finish_cloud(cloud, source, inputs, augmentation)
            })
            .collect();
        let mut clouds = clouds.into_iter();
        let mut out_frames = Vec::with_capacity(frames.len());
        for (f, inputs) in frames.into_iter().enumerate() {
            let (cloud, t) = clouds
                .next()
                .ok_or_else(|| SampleError::Config("internal: cloud count mismatch".into()))?;
            times.add(&t);
            times.add(&inputs.times);
            times.add(&inputs.sweep.times);
            out_frames.push(Frame {
                offset: offsets[f],
                sweep: key.frame_sweeps[f],
                lidar_stamp: inputs.sweep.cloud.stamp,
                images: inputs.images,
                num_superpixels: inputs.num_superpixels,
                cloud,
                dropped_non_finite: inputs.sweep.dropped,
            });
        }
        let (dense, t) = clouds
            .next()
            .ok_or_else(|| SampleError::Config("internal: cloud count mismatch".into()))?;
        times.add(&t);
        Ok(Sample {
            id,
            seed,
            camera_indices: chosen.iter().map(|&c| c as u32).collect(),
            cameras: chosen
                .iter()
                .map(|&c| drive.cameras[c].name.clone())
                .collect(),
            frames: out_frames,
            key_frame,
            dense,
            dense_stamps,
            dense_missing,
            dense_dropped_non_finite,
            class_superpixels,
            times,
        })
    }

    fn transform_error(drive: &Drive, what: String, stamp: Stamp, source: TfError) -> SampleError {
        SampleError::Transform {
            files: drive.file_list(),
            what,
            stamp,
            source: Box::new(source),
        }
    }

    /// Decodes sweep `sweep` and de-skews it when configured and it has per-point time.
    fn load_sweep(&self, drive: &Drive, sweep: u32) -> Result<LoadedSweep, SampleError> {
        let mut times = StageTimes::default();
        let lidar = drive
            .lidar
            .as_ref()
            .ok_or_else(|| SampleError::Config(format!("{}: no LiDAR", drive.file_list())))?;
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
            cloud = deskew(&cloud, &drive.tf, map).map_err(|e| {
                Self::transform_error(drive, format!("de-skew of {}", lidar.topic), frame.stamp, e)
            })?;
            times.sweeps += elapsed(t);
        }
        Ok(LoadedSweep {
            cloud,
            dropped: decoded.dropped_non_finite as u64,
            times,
        })
    }

    /// Sweep `sweep` moved into the LiDAR frame of sweep `key`:
    /// `key_lidar_from_map(t_key) · map_from_lidar(t_s)`.
    fn load_into_key_frame(
        &self,
        drive: &Drive,
        sweep: u32,
        key: u32,
    ) -> Result<LoadedSweep, SampleError> {
        let mut loaded = self.load_sweep(drive, sweep)?;
        let t = Instant::now();
        let lidar = drive
            .lidar
            .as_ref()
            .ok_or_else(|| SampleError::Config(format!("{}: no LiDAR", drive.file_list())))?;
        let map = drive.map_frame.as_deref().unwrap_or_default();
        let key_stamp = lidar.sweeps[key as usize].stamp;
        let lookup = |stamp: Stamp| {
            drive.tf.lookup(map, &lidar.frame_id, stamp).map_err(|e| {
                Self::transform_error(drive, format!("pose of {}", lidar.topic), stamp, e)
            })
        };
        let key_from_sweep = lookup(key_stamp)?.inverse() * lookup(loaded.cloud.stamp)?;
        for p in &mut loaded.cloud.xyz {
            let q = key_from_sweep * Point3::new(f64::from(p[0]), f64::from(p[1]), f64::from(p[2]));
            *p = [q.x as f32, q.y as f32, q.z as f32];
        }
        loaded.times.sweeps += elapsed(t);
        Ok(loaded)
    }

    fn load_frame(
        &self,
        drive: &Drive,
        frame_pos: u32,
        sweep: u32,
        chosen: &[usize],
        id: SampleId,
        class_superpixels: bool,
    ) -> Result<FrameInputs, SampleError> {
        let (sweep_result, images) = rayon::join(
            || self.load_sweep(drive, sweep),
            || {
                let lidar_stamp = drive
                    .lidar
                    .as_ref()
                    .map(|l| l.sweeps[sweep as usize].stamp)
                    .unwrap_or_default();
                chosen
                    .par_iter()
                    .enumerate()
                    .map(|(slot, &c)| {
                        self.load_image(
                            drive,
                            &drive.cameras[c],
                            lidar_stamp,
                            frame_pos,
                            slot,
                            id,
                            class_superpixels,
                        )
                    })
                    .collect::<Result<Vec<_>, _>>()
            },
        );
        let sweep = sweep_result?;
        let mut times = StageTimes::default();
        let mut images = images?;
        // Superpixel ids: class ids as they are (view-consistent), SLIC labels offset per
        // image.
        let mut num_superpixels = if class_superpixels {
            self.config.num_classes
        } else {
            0
        };
        for (image, count, t) in &mut images {
            times.add(t);
            if !class_superpixels {
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

    #[allow(clippy::too_many_arguments)]
    fn load_image(
        &self,
        drive: &Drive,
        camera: &CameraStream,
        lidar_stamp: Stamp,
        frame_pos: u32,
        slot: usize,
        id: SampleId,
        class_superpixels: bool,
    ) -> Result<(SampleImage, u32, StageTimes), SampleError> {
        let cfg = &self.config;
        let mut times = StageTimes::default();
        let (out_w, out_h) = (cfg.image_width as usize, cfg.image_height as usize);
        let image_error = |stamp: Stamp, reason: String| SampleError::Image {
            files: drive.file_list(),
            topic: camera.image_topic.clone(),
            stamp,
            reason,
        };
        let frame = camera_frame_for(camera, lidar_stamp).ok_or_else(|| {
            image_error(
                lidar_stamp,
                format!(
                    "{}: no image within half a period of the sweep",
                    camera.name
                ),
            )
        })?;
        let calibration = camera
            .calibration_at(frame.stamp)
            .ok_or_else(|| image_error(frame.stamp, format!("{}: no calibration", camera.name)))?
            .clone();
        let t = Instant::now();
        let image = with_cache(|cache| drive.read_image(camera, frame, Target::Rgb, cache))?;
        times.decode += elapsed(t);
        if (image.width, image.height) != (calibration.width, calibration.height)
            || image.format != PixelFormat::Rgb8
        {
            return Err(image_error(
                frame.stamp,
                format!(
                    "{}: image is {}x{} but its calibration is for {}x{}",
                    camera.name, image.width, image.height, calibration.width, calibration.height
                ),
            ));
        }
        let map = drive.map_frame.as_deref().unwrap_or_default();
        let lidar_frame = drive
            .lidar
            .as_ref()
            .map(|l| l.frame_id.as_str())
            .unwrap_or_default();
        let camera_from_lidar = camera_from_lidar(
            &drive.tf,
            map,
            lidar_frame,
            lidar_stamp,
            &camera.frame_id,
            frame.stamp,
        )
        .map_err(|e| {
            Self::transform_error(drive, format!("{} from LiDAR", camera.name), frame.stamp, e)
        })?;
        let t = Instant::now();
        let (w, h) = (image.width as usize, image.height as usize);
        let mut rgb = image_ops::resize_bilinear(&image.data, w, h, 3, out_w, out_h);
        let flipped = SampleRng::new(
            self.config.seed,
            id.epoch,
            id.index,
            Purpose::ImageFlip {
                frame: frame_pos,
                slot: slot as u32,
            },
        )
        .bernoulli(cfg.image_flip_probability);
        if flipped {
            image_ops::flip_horizontal(&mut rgb, out_w, 3);
        }
        times.images += elapsed(t);

        let t_sp = Instant::now();
        let mut class_decode = 0;
        let (superpixels, count) = if class_superpixels {
            let topic = camera.superpixel_topic.clone().unwrap_or_default();
            let sp_error = |reason: String| SampleError::Superpixels {
                files: drive.file_list(),
                topic: topic.clone(),
                stamp: frame.stamp,
                reason,
            };
            let class_frame = nearest(&camera.superpixels, frame.stamp)
                .filter(|f| f.stamp.nanos_since(frame.stamp).abs() <= CLASS_MAP_TOLERANCE_NANOS)
                .ok_or_else(|| {
                    sp_error(format!(
                        "no class map within 1 ms of image {}",
                        camera.image_topic
                    ))
                })?;
            let t = Instant::now();
            let classes =
                with_cache(|cache| drive.read_image(camera, class_frame, Target::Mono, cache))?;
            class_decode = elapsed(t);
            times.decode += class_decode;
            if (classes.width, classes.height) != (image.width, image.height) {
                return Err(sp_error(format!(
                    "class map is {}x{}, its image {}x{}",
                    classes.width, classes.height, image.width, image.height
                )));
            }
            if let Some(bad) = classes
                .data
                .iter()
                .find(|&&c| u32::from(c) >= cfg.num_classes)
            {
                return Err(sp_error(format!(
                    "class id {bad} is outside the configured {} classes",
                    cfg.num_classes
                )));
            }
            // Resize the u8 map, then widen only the resized pixels.
            let mut small = image_ops::resize_nearest(&classes.data, w, h, out_w, out_h);
            if flipped {
                image_ops::flip_horizontal(&mut small, out_w, 1);
            }
            (small.into_iter().map(u32::from).collect(), cfg.num_classes)
        } else {
            let seg = slic(&rgb, out_w, out_h, &cfg.slic);
            (seg.labels, seg.count)
        };
        times.superpixels += elapsed(t_sp).saturating_sub(class_decode);
        Ok((
            SampleImage {
                camera: camera.name.clone(),
                topic: camera.image_topic.clone(),
                stamp: frame.stamp,
                native_size: (image.width, image.height),
                flipped,
                rgb,
                superpixels,
                camera_from_lidar,
                calibration,
            },
            count,
            times,
        ))
    }

    /// Pairs `cloud` with the images of `inputs` (the cloud must be in the LiDAR frame at
    /// the sweep stamp the images' `camera_from_lidar` was computed for), then augments,
    /// voxelizes and builds the maps.
    fn finish_cloud(
        &self,
        cloud: &PointCloud,
        source_sweep: Vec<u8>,
        inputs: &FrameInputs,
        augmentation: Augmentation,
    ) -> (Cloud, StageTimes) {
        let cfg = &self.config;
        let mut times = StageTimes::default();
        let t = Instant::now();
        let out_size = (cfg.image_width, cfg.image_height);
        let mut pairings = Vec::new();
        for (slot, image) in inputs.images.iter().enumerate() {
            let view = CameraView::new(&image.calibration, image.camera_from_lidar);
            for p in pair_points(&cloud.xyz, &view) {
                let (row, col) =
                    image_ops::resized_pixel(p.u, p.v, image.native_size, out_size, image.flipped);
                let superpixel =
                    image.superpixels[row as usize * cfg.image_width as usize + col as usize];
                pairings.push(Pair {
                    point: p.point,
                    camera: slot as u8,
                    u: p.u,
                    v: p.v,
                    depth: p.depth,
                    row,
                    col,
                    superpixel,
                });
            }
        }
        times.projection += elapsed(t);
        let t = Instant::now();
        let mut xyz = cloud.xyz.clone();
        augmentation.apply(&mut xyz);
        let voxels = voxelize(&xyz, &cfg.voxel);
        let voxel_features = voxels
            .representative
            .iter()
            .map(|&i| {
                let [x, y, z] = xyz[i as usize];
                [x, y, z, cloud.intensity[i as usize]]
            })
            .collect();
        let levels = build_levels(&voxels.coords, cfg.unet_levels as usize);
        times.voxels += elapsed(t);
        (
            Cloud {
                xyz,
                intensity: cloud.intensity.clone(),
                source_sweep,
                pairings,
                augmentation,
                voxels,
                voxel_features,
                levels,
            },
            times,
        )
    }
}

/// What a frame needs before its clouds are finished.
struct FrameInputs {
    sweep: LoadedSweep,
    images: Vec<SampleImage>,
    num_superpixels: u32,
    times: StageTimes,
}
