//! `[sample]` of `pipeline.toml`: the sample recipe. Every default is the paper's (or its
//! official code's where the two differ; see `pipeline/docs/RECIPE.md`).

use super::image_ops::resize_bilinear_mirrored;
use super::slic::SlicParams;
use super::voxel::VoxelGrid;
use crate::decode::image::Scale;
use serde::{Deserialize, Serialize};
use superflow_common::InvalidSetting;
use superflow_schemas::sensor::Image;

/// What to do with a keyframe whose t−Δt or t+Δt frame falls outside the drive.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Default, Serialize, Deserialize)]
#[serde(rename_all = "snake_case")]
pub enum EdgePolicy {
    /// Use the keyframe itself in place of the missing frame (the official code).
    #[default]
    Reuse,
    /// Leave the keyframe out of the plan.
    Skip,
}

/// Which sweep of each keyframe interval becomes the keyframe.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Default, Serialize, Deserialize)]
#[serde(rename_all = "snake_case")]
pub enum KeyframeChoice {
    /// The sweep whose worst camera is nearest its scan moment (see
    /// [`CameraSync`]), one per interval: moving objects then pair with their own pixels.
    #[default]
    LeastCameraOffset,
    /// The first usable sweep, the next one at least an interval later.
    First,
}

/// Which camera image goes with a sweep.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Default, Serialize, Deserialize)]
#[serde(rename_all = "snake_case")]
pub enum CameraSync {
    /// The image nearest the moment the LiDAR scanned the camera's direction (measured
    /// once per drive from a sweep's point times or firing order).
    #[default]
    Scan,
    /// The image nearest the sweep's stamp.
    Stamp,
}

/// Where superpixels come from.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Default, Serialize, Deserialize)]
#[serde(rename_all = "snake_case")]
pub enum SuperpixelSource {
    /// The recording's class-map channels when every camera has one, else SLIC.
    #[default]
    Auto,
    /// The recording's class-map channels (an error if a camera has none).
    Channel,
    /// SLIC on each resized image: read from the drive's `.slic.mcap` sidecar when one
    /// was written with this recipe (`superflow-pipeline superpixels`), else computed.
    Slic,
}

/// Which sparse-convolution maps a batch carries.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Default, Serialize, Deserialize)]
#[serde(rename_all = "snake_case")]
pub enum KernelMaps {
    /// Every UNet level's coordinates, 3×3×3 neighbour map and stride-2 map: what the
    /// burn trainer and a network run on the batch's own maps read.
    #[default]
    Unet,
    /// Level-0 voxels only (`l0_coords`, `l0_clouds`), no map: for a 3D network that
    /// builds its own on the GPU (spconv, torchsparse, MinkowskiEngine). Building the maps
    /// is the largest share of a sample's work after decoding, and they are a large share
    /// of a batch's bytes.
    None,
}

/// 3D augmentation, applied to each cloud after its points are paired with pixels.
#[derive(Debug, Clone, Copy, PartialEq, Serialize, Deserialize)]
#[serde(default, deny_unknown_fields)]
pub struct AugmentConfig {
    /// Off: points stay in their LiDAR frame.
    pub enabled: bool,
    /// Probability of mirroring x (x → −x).
    pub flip_x_probability: f64,
    /// Probability of mirroring y.
    pub flip_y_probability: f64,
    /// Rotation about z, uniform in `[0, rotation_max_rad]`.
    pub rotation_max_rad: f64,
    /// Scale, uniform in `[scale_min, scale_max]`.
    pub scale_min: f64,
    /// Upper end of the scale range.
    pub scale_max: f64,
    /// One draw shared by every cloud of a sample (frames and dense cloud) instead of
    /// one per cloud.
    pub shared: bool,
}

impl Default for AugmentConfig {
    fn default() -> Self {
        Self {
            enabled: true,
            flip_x_probability: 0.5,
            flip_y_probability: 0.5,
            rotation_max_rad: std::f64::consts::PI,
            scale_min: 0.95,
            scale_max: 1.05,
            shared: false,
        }
    }
}

/// The sample recipe.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(default, deny_unknown_fields)]
pub struct SampleConfig {
    /// One keyframe per interval of this many seconds (0.5).
    pub keyframe_interval_secs: f64,
    /// Which sweep of an interval is its keyframe.
    pub keyframe_choice: KeyframeChoice,
    /// Which camera image goes with a sweep.
    pub camera_sync: CameraSync,
    /// Δt between the keyframe and its temporal context, seconds (0.5; 0.5–2.0).
    pub delta_t_secs: f64,
    /// 3: (t−Δt, t, t+Δt); 2: (t−Δt, t).
    pub temporal_frames: u32,
    /// A context frame outside the drive.
    pub edge: EdgePolicy,
    /// Earlier sweeps added to the keyframe for the dense cloud (2; 1, 2, 5, 7 in the paper).
    pub dense_sweeps: u32,
    /// De-skew raw sweeps that carry per-point time (motion-compensated clouds are left
    /// as they are).
    pub deskew: bool,
    /// Cameras per sample, the same for every frame of it (3).
    pub cameras: u32,
    /// Height of the resized images (224).
    pub image_height: u32,
    /// Width of the resized images (448).
    pub image_width: u32,
    /// Probability of flipping each image horizontally (0.5).
    pub image_flip_probability: f64,
    /// Decode JPEG camera images at 1/2 or 1/4 scale in the DCT domain when that is
    /// still at least the resized size (a 1600×900 image for 448×224 decodes at
    /// 800×450, then resizes). Costs a fraction of a full decode; the pixels differ from
    /// a full decode + resize by the DCT scaling's own averaging (see
    /// `pipeline/docs/RECIPE.md`). Pairings are unchanged: they use the full size.
    pub image_reduced_decode: bool,
    /// Superpixel source.
    pub superpixels: SuperpixelSource,
    /// Number of classes of a class-map channel; a larger id is an error (17, nuScenes
    /// lidarseg).
    pub num_classes: u32,
    /// SLIC parameters.
    pub slic: SlicParams,
    /// 3D augmentation.
    pub augment: AugmentConfig,
    /// Voxel grid (cylindrical 0.1 m, 1°, 0.1 m).
    pub voxel: VoxelGrid,
    /// Resolutions of the 3D UNet (5: strides 1 to 16).
    pub unet_levels: u32,
    /// Which maps are built and sent (`"unet"`: every level's; `"none"`: level-0 voxels
    /// only, for networks that build their own maps).
    pub kernel_maps: KernelMaps,
    /// Seed of every random choice: with (epoch, index) it fixes a sample.
    pub seed: u64,
}

impl Default for SampleConfig {
    fn default() -> Self {
        Self {
            keyframe_interval_secs: superflow_schemas::time::KEYFRAME_INTERVAL_SECS,
            keyframe_choice: KeyframeChoice::LeastCameraOffset,
            camera_sync: CameraSync::Scan,
            delta_t_secs: 0.5,
            temporal_frames: 3,
            edge: EdgePolicy::Reuse,
            dense_sweeps: 2,
            deskew: true,
            cameras: 3,
            image_height: 224,
            image_width: 448,
            image_flip_probability: 0.5,
            image_reduced_decode: true,
            superpixels: SuperpixelSource::Auto,
            num_classes: 17,
            slic: SlicParams::default(),
            augment: AugmentConfig::default(),
            voxel: VoxelGrid::default(),
            unet_levels: 5,
            kernel_maps: KernelMaps::Unet,
            seed: 0,
        }
    }
}

impl SampleConfig {
    /// A decoded `Rgb8` camera image resized (bilinear) to the recipe's size, mirrored
    /// left to right when `flipped`: what samples show and segment.
    pub fn resized_rgb(&self, image: &Image, flipped: bool) -> Vec<u8> {
        resize_bilinear_mirrored(
            &image.data,
            [image.width as usize, image.height as usize, 3],
            [self.image_width as usize, self.image_height as usize],
            flipped,
        )
    }

    /// How small a camera image may decode: at least the recipe's size when
    /// `image_reduced_decode` is on, else full size.
    pub fn decode_scale(&self) -> Scale {
        if self.image_reduced_decode {
            Scale::AtLeast {
                width: self.image_width,
                height: self.image_height,
            }
        } else {
            Scale::Full
        }
    }

    /// Checks ranges; the error names the setting (`sample.…`).
    pub fn validate(&self) -> Result<(), InvalidSetting> {
        let positive = |name: &str, v: f64| {
            if v.is_finite() && v > 0.0 {
                Ok(())
            } else {
                Err(InvalidSetting::new(
                    format!("sample.{name}"),
                    v,
                    "must be finite and positive",
                ))
            }
        };
        let probability = |name: &str, v: f64| {
            if (0.0..=1.0).contains(&v) {
                Ok(())
            } else {
                Err(InvalidSetting::new(
                    format!("sample.{name}"),
                    v,
                    "is not a probability",
                ))
            }
        };
        let within = |name: &str, v: u32, range: std::ops::RangeInclusive<u32>| {
            if range.contains(&v) {
                Ok(())
            } else {
                let rule = format!("must be {}..={}", range.start(), range.end());
                Err(InvalidSetting::new(format!("sample.{name}"), v, rule))
            }
        };
        positive("keyframe_interval_secs", self.keyframe_interval_secs)?;
        positive("delta_t_secs", self.delta_t_secs)?;
        if !(2..=3).contains(&self.temporal_frames) {
            return Err(InvalidSetting::new(
                "sample.temporal_frames",
                self.temporal_frames,
                "must be 2 or 3",
            ));
        }
        if self.dense_sweeps > 32 {
            return Err(InvalidSetting::new(
                "sample.dense_sweeps",
                self.dense_sweeps,
                "is more than 32",
            ));
        }
        within("cameras", self.cameras, 1..=255)?;
        within("image_height", self.image_height, 1..=8192)?;
        within("image_width", self.image_width, 1..=8192)?;
        probability("image_flip_probability", self.image_flip_probability)?;
        within("num_classes", self.num_classes, 1..=65_536)?;
        self.slic.validate().map_err(in_sample)?;
        // SLIC ids are offset per image of a frame, and a batch stores 16-bit ids.
        let frame_segments = u64::from(self.slic.n_segments) * u64::from(self.cameras);
        if frame_segments > u64::from(crate::sample::slic::MAX_SEGMENTS) {
            return Err(InvalidSetting::new(
                "sample.slic.n_segments",
                self.slic.n_segments,
                format!(
                    "times sample.cameras ({}) must be at most {} (16-bit ids per frame)",
                    self.cameras,
                    crate::sample::slic::MAX_SEGMENTS
                ),
            ));
        }
        let a = &self.augment;
        probability("augment.flip_x_probability", a.flip_x_probability)?;
        probability("augment.flip_y_probability", a.flip_y_probability)?;
        if !(a.rotation_max_rad.is_finite() && a.rotation_max_rad >= 0.0) {
            return Err(InvalidSetting::new(
                "sample.augment.rotation_max_rad",
                a.rotation_max_rad,
                "must be finite and >= 0",
            ));
        }
        positive("augment.scale_min", a.scale_min)?;
        positive("augment.scale_max", a.scale_max)?;
        if a.scale_min > a.scale_max {
            return Err(InvalidSetting::new(
                "sample.augment.scale_min",
                a.scale_min,
                format!("exceeds scale_max = {}", a.scale_max),
            ));
        }
        self.voxel.validate().map_err(in_sample)?;
        within("unet_levels", self.unet_levels, 1..=8)
    }

    /// Offsets of the temporal frames in units of Δt, in time order.
    pub fn frame_offsets(&self) -> &'static [i32] {
        if self.temporal_frames == 2 {
            &[-1, 0]
        } else {
            &[-1, 0, 1]
        }
    }
}

/// A sub-table's error (`slic.…`, `voxel.…`) named from the top (`sample.slic.…`).
fn in_sample(e: InvalidSetting) -> InvalidSetting {
    InvalidSetting {
        setting: format!("sample.{}", e.setting),
        ..e
    }
}
