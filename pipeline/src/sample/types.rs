//! What a sample is made of: its [`SampleId`], the point↔pixel [`Pair`]s, each
//! [`Cloud`] ready for the 3D network, the resized [`SampleImage`]s of a temporal
//! [`Frame`], the [`Sample`] itself and the [`StageTimes`] spent building it.

use super::augment::Augmentation;
use super::kernel_maps::Level;
use super::voxel::Voxelized;
use nalgebra::Isometry3;
use serde::Serialize;
use superflow_schemas::Stamp;
use superflow_schemas::sensor::CameraCalibration;

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
    /// Sparse-convolution maps per UNet level (level 0 = `voxels.coords`); empty when the
    /// recipe builds none (`kernel_maps = "none"`).
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
    /// Image stamp minus the moment the LiDAR scanned this camera's direction in the
    /// frame's sweep, nanoseconds (see `sample.camera_sync`).
    pub scan_offset_nanos: i64,
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
