//! Samples as an MCAP file that Foxglove opens with no plugin: Foxglove's own protobuf
//! schemas, one sample or a whole drive's keyframes one after the other, so that the
//! timeline scrubs through each sample's frames (t − Δt, t, t + Δt).
//!
//! Per temporal frame, stamped with its LiDAR sweep's stamp:
//! * `/superflow/cloud`: the frame's cloud (`foxglove.PointCloud`) in the LiDAR frame,
//!   with the fields to colour by (see [`POINT_FIELDS`]);
//! * `/superflow/<camera>/image`: each chosen image as the model sees it (resized,
//!   flipped), PNG, and `/superflow/<camera>/calibration`: the calibration of that very
//!   image (a flipped one has a negative `fx`), so the 3D panel projects the cloud onto it;
//! * `/superflow/<camera>/superpixels`: the superpixel ids in colour;
//! * `/superflow/<camera>/pairings`: the paired points (`foxglove.ImageAnnotations`) at
//!   their pixels' centres, coloured by depth;
//! * `/tf` (`foxglove.FrameTransforms`): the LiDAR's pose in the map frame, and each
//!   camera's pose in the LiDAR frame as the pairing used it — the camera at its image's
//!   stamp, the LiDAR at the sweep's — so projecting a point through them lands on its
//!   pairing's pixel.
//!
//! And per sample, at its keyframe's stamp, `/superflow/dense`: the dense cloud in the
//! keyframe's LiDAR frame. Points are written where they were recorded: the augmentation
//! the network saw is undone (it is not rigid: a scale and flips), and listed with the
//! rest of the draws in the file's `superflow.sample.<keyframe>` metadata.

use super::cloud::Column;
use super::image::camera_topic;
use super::writer::{ViewError, ViewWriter, frame_transform};
use crate::drive::Drive;
use crate::sample::SampleConfig;
use crate::sample::export::{id_colour, ramp};
use crate::sample::{Cloud, Sample, SampleImage};
use foxglove::messages::{
    CameraCalibration, Color, FrameTransforms, ImageAnnotations, Point2, PointsAnnotation,
    Timestamp, points_annotation,
};
use std::collections::{BTreeMap, HashSet};
use std::path::Path;
use superflow_schemas::Stamp;
use superflow_schemas::sensor::Distortion;

/// Depth at the red end of the pairings' colour ramp, metres.
const DEPTH_RAMP_METRES: f32 = 50.0;

/// The fields of every cloud written beside `x`, `y`, `z`, to colour by.
pub const POINT_FIELDS: [&str; 5] = [
    "intensity",
    // 0 = the keyframe's sweep, k = the k-th sweep before it (dense cloud).
    "source_sweep",
    // 1 when a chosen camera sees the point (it has a pairing).
    "paired",
    // The superpixel of its first pairing, −1 when unpaired.
    "superpixel",
    // Its voxel (cell) of UNet level 0.
    "voxel",
];

/// What a view file holds once written.
#[derive(Debug, Clone, Copy, Default, PartialEq, Eq)]
pub struct ViewSummary {
    /// Samples written.
    pub samples: usize,
    /// Temporal frames written (a frame shared by two samples of a drive once).
    pub frames: usize,
    /// Messages written.
    pub messages: u64,
}

/// An MCAP file of samples for Foxglove: [`add`](Self::add) each, then
/// [`finish`](Self::finish).
#[derive(Debug)]
pub struct SampleMcap {
    out: ViewWriter,
    /// Frames written, by drive and LiDAR stamp: consecutive keyframes of a drive share
    /// sweeps, and a frame is written once.
    frames: HashSet<(u32, Stamp)>,
    /// The size of the sample's images (`[sample] image_width × image_height`).
    image_size: (u32, u32),
    summary: ViewSummary,
}

impl SampleMcap {
    /// Creates `path` (replacing a file there) for samples built with `config`.
    pub fn create(path: &Path, config: &SampleConfig) -> Result<Self, ViewError> {
        let library = format!("superflow-pipeline/{}", env!("CARGO_PKG_VERSION"));
        Ok(Self {
            out: ViewWriter::create(path, &library)?,
            frames: HashSet::new(),
            image_size: (config.image_width, config.image_height),
            summary: ViewSummary::default(),
        })
    }
    /// Adds `sample`, built from `drive`: its frames not written before, its dense cloud
    /// and its draws as metadata.
    pub fn add(&mut self, sample: &Sample, drive: &Drive) -> Result<(), ViewError> {
        let Some(lidar) = &drive.lidar else {
            return Ok(());
        };
        let lidar_frame = lidar.frame_id.as_str();
        let mut transforms = Vec::new();
        for frame in &sample.frames {
            if !self.frames.insert((sample.id.drive, frame.lidar_stamp)) {
                continue;
            }
            self.summary.frames += 1;
            let stamp = frame.lidar_stamp;
            let ts = self.out.timestamp(stamp)?;
            transforms.clear();
            if let Some(map) = &drive.map_frame {
                match drive.tf.lookup(map, lidar_frame, stamp) {
                    Ok(map_from_lidar) => {
                        transforms.push(frame_transform(ts, map, lidar_frame, &map_from_lidar));
                    }
                    Err(e) => {
                        tracing::warn!(%stamp, error = %e, "no pose of the LiDAR in the map frame: the frame is written without it");
                    }
                }
            }
            for image in &frame.images {
                transforms.push(frame_transform(
                    ts,
                    lidar_frame,
                    &image.calibration.frame_id,
                    &image.camera_from_lidar.inverse(),
                ));
            }
            self.out.write(
                "/tf",
                stamp,
                &FrameTransforms {
                    transforms: transforms.clone(),
                },
            )?;
            self.write_cloud("/superflow/cloud", stamp, lidar_frame, &frame.cloud)?;
            for (slot, image) in frame.images.iter().enumerate() {
                self.write_image(stamp, ts, slot, image, &frame.cloud)?;
            }
        }
        let key = &sample.frames[sample.key_frame];
        self.write_cloud(
            "/superflow/dense",
            key.lidar_stamp,
            lidar_frame,
            &sample.dense,
        )?;
        let draws = serde_json::json!({
            "drive": sample.id.drive,
            "keyframe": sample.id.keyframe,
            "sweep": sample.id.sweep,
            "epoch": sample.id.epoch,
            "index": sample.id.index,
            "seed": sample.seed,
            "cameras": sample.cameras,
            "frames": sample.frames.iter().map(|f| serde_json::json!({
                "offset": f.offset,
                "stamp_nanos": f.lidar_stamp.nanos(),
                "augmentation": f.cloud.augmentation,
                "flipped": f.images.iter().map(|i| i.flipped).collect::<Vec<_>>(),
            })).collect::<Vec<_>>(),
            "dense_augmentation": sample.dense.augmentation,
        });
        self.out.metadata(
            &format!("superflow.sample.{}", sample.id.keyframe),
            BTreeMap::from([("draws".to_string(), draws.to_string())]),
        )?;
        self.summary.samples += 1;
        Ok(())
    }

    /// One image of a frame: the picture, its calibration, its superpixels, its pairings.
    fn write_image(
        &mut self,
        stamp: Stamp,
        ts: Timestamp,
        slot: usize,
        image: &SampleImage,
        cloud: &Cloud,
    ) -> Result<(), ViewError> {
        let (width, height) = self.image_size;
        let camera = image.camera.as_str();
        let frame_id = image.calibration.frame_id.as_str();
        self.out.write_png(
            camera,
            "image",
            frame_id,
            stamp,
            self.image_size,
            &image.rgb,
        )?;
        self.out.write(
            &camera_topic(camera, "calibration"),
            stamp,
            &resized_calibration(ts, &image.calibration, image.flipped, width, height),
        )?;
        let colours: Vec<u8> = image
            .superpixels
            .iter()
            .flat_map(|id| id_colour(*id))
            .collect();
        self.out.write_png(
            camera,
            "superpixels",
            frame_id,
            stamp,
            self.image_size,
            &colours,
        )?;
        let pairs: Vec<_> = cloud
            .pairings
            .iter()
            .filter(|p| usize::from(p.camera) == slot)
            .collect();
        let annotation = PointsAnnotation {
            timestamp: Some(ts),
            r#type: points_annotation::Type::Points as i32,
            points: pairs
                .iter()
                .map(|p| Point2 {
                    x: f64::from(p.col) + 0.5,
                    y: f64::from(p.row) + 0.5,
                })
                .collect(),
            outline_color: None,
            outline_colors: pairs
                .iter()
                .map(|p| colour(ramp(p.depth / DEPTH_RAMP_METRES)))
                .collect(),
            fill_color: None,
            thickness: 2.0,
            metadata: Vec::new(),
        };
        self.out.write(
            &camera_topic(camera, "pairings"),
            stamp,
            &ImageAnnotations {
                timestamp: Some(ts),
                circles: Vec::new(),
                points: vec![annotation],
                texts: Vec::new(),
                metadata: Vec::new(),
            },
        )
    }

    /// `cloud` on `topic`: its points back where they were recorded (the augmentation
    /// undone), with [`POINT_FIELDS`].
    fn write_cloud(
        &mut self,
        topic: &str,
        stamp: Stamp,
        frame_id: &str,
        cloud: &Cloud,
    ) -> Result<(), ViewError> {
        let xyz = cloud.augmentation.unapplied(&cloud.xyz);
        let mut superpixel = vec![-1i32; xyz.len()];
        for pair in cloud.pairings.iter().rev() {
            if let Some(s) = superpixel.get_mut(pair.point as usize) {
                *s = i32::try_from(pair.superpixel).unwrap_or(i32::MAX);
            }
        }
        let paired: Vec<u8> = superpixel.iter().map(|&s| u8::from(s >= 0)).collect();
        let [intensity, source_sweep, paired_name, superpixel_name, voxel] = POINT_FIELDS;
        self.out.write_cloud(
            topic,
            stamp,
            frame_id,
            &xyz,
            &[
                Column::F32(intensity, &cloud.intensity),
                Column::U8(source_sweep, &cloud.source_sweep),
                Column::U8(paired_name, &paired),
                Column::I32(superpixel_name, &superpixel),
                Column::U32(voxel, &cloud.voxels.point_to_voxel),
            ],
        )
    }

    /// Writes the summary and index and closes the file.
    pub fn finish(mut self) -> Result<ViewSummary, ViewError> {
        self.summary.messages = self.out.finish()?;
        Ok(self.summary)
    }
}

fn colour([r, g, b]: [u8; 3]) -> Color {
    Color {
        r: f64::from(r) / 255.0,
        g: f64::from(g) / 255.0,
        b: f64::from(b) / 255.0,
        a: 1.0,
    }
}

/// The calibration of the resized (and possibly mirrored) image: the raw one's
/// intrinsics scaled about pixel corners (pixel centres at integers, as OpenCV and ROS
/// have them), mirrored by a negative `fx` and skew; the distortion, a function of the
/// normalised coordinates, unchanged.
pub fn resized_calibration(
    ts: Timestamp,
    cal: &superflow_schemas::sensor::CameraCalibration,
    flipped: bool,
    width: u32,
    height: u32,
) -> CameraCalibration {
    let (sx, sy) = (
        f64::from(width) / f64::from(cal.width),
        f64::from(height) / f64::from(cal.height),
    );
    let k = &cal.k;
    let mut fx = k[(0, 0)] * sx;
    let mut skew = k[(0, 1)] * sx;
    let mut cx = (k[(0, 2)] + 0.5) * sx - 0.5;
    let fy = k[(1, 1)] * sy;
    let cy = (k[(1, 2)] + 0.5) * sy - 0.5;
    if flipped {
        fx = -fx;
        skew = -skew;
        cx = f64::from(width) - 1.0 - cx;
    }
    let distortion_model = match cal.distortion {
        Distortion::Equidistant { .. } => "kannala_brandt",
        ref d => d.model_name(),
    };
    CameraCalibration {
        timestamp: Some(ts),
        frame_id: cal.frame_id.clone(),
        width,
        height,
        distortion_model: distortion_model.to_string(),
        d: cal.distortion.coeffs(),
        k: vec![fx, skew, cx, 0.0, fy, cy, 0.0, 0.0, 1.0],
        r: vec![1.0, 0.0, 0.0, 0.0, 1.0, 0.0, 0.0, 0.0, 1.0],
        p: vec![fx, skew, cx, 0.0, 0.0, fy, cy, 0.0, 0.0, 0.0, 1.0, 0.0],
    }
}
