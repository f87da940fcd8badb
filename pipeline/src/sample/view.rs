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

use super::export::{id_colour, ramp};
use super::recipe::SampleConfig;
use super::types::{Cloud, Sample, SampleImage};
use crate::drive::Drive;
use foxglove::messages::{
    CameraCalibration, Color, CompressedImage, FrameTransform, FrameTransforms, ImageAnnotations,
    PackedElementField, Point2, PointCloud, PointsAnnotation, Quaternion, Timestamp, Vector3,
    packed_element_field::NumericType, points_annotation,
};
use nalgebra::Isometry3;
use std::collections::{BTreeMap, HashMap, HashSet};
use std::fs::File;
use std::io::BufWriter;
use std::path::{Path, PathBuf};
use superflow_schemas::Stamp;
use superflow_schemas::sensor::Distortion;

/// Depth at the red end of the pairings' colour ramp, metres.
const DEPTH_RAMP_METRES: f32 = 50.0;

/// The fields of every cloud written, in order: name, type, byte offset.
pub const POINT_FIELDS: [(&str, NumericType, u32); 8] = [
    ("x", NumericType::Float32, 0),
    ("y", NumericType::Float32, 4),
    ("z", NumericType::Float32, 8),
    ("intensity", NumericType::Float32, 12),
    // 0 = the keyframe's sweep, k = the k-th sweep before it (dense cloud).
    ("source_sweep", NumericType::Uint8, 16),
    // 1 when a chosen camera sees the point (it has a pairing).
    ("paired", NumericType::Uint8, 17),
    // The superpixel of its first pairing, −1 when unpaired.
    ("superpixel", NumericType::Int32, 20),
    // Its voxel (cell) of UNet level 0.
    ("voxel", NumericType::Uint32, 24),
];
/// Bytes per point.
const POINT_STRIDE: u32 = 28;

/// Writing the view failed.
#[derive(Debug, thiserror::Error)]
pub enum ViewError {
    /// The file could not be written.
    #[error("{path}: {source}")]
    Io {
        /// The file.
        path: PathBuf,
        /// What failed.
        #[source]
        source: std::io::Error,
    },
    /// The MCAP writer failed.
    #[error("{path}: {source}")]
    Mcap {
        /// The file.
        path: PathBuf,
        /// What failed.
        #[source]
        source: mcap::McapError,
    },
    /// An image could not be encoded as PNG.
    #[error("{path}: {camera} at {stamp}: {source}")]
    Png {
        /// The file.
        path: PathBuf,
        /// The camera.
        camera: String,
        /// The frame's stamp.
        stamp: Stamp,
        /// What failed.
        #[source]
        source: png::EncodingError,
    },
    /// A stamp Foxglove's `Timestamp` cannot hold (before 1970 or past 2106).
    #[error("{path}: stamp {stamp} is out of the range of Foxglove's timestamps")]
    Stamp {
        /// The file.
        path: PathBuf,
        /// The stamp.
        stamp: Stamp,
    },
    /// A Foxglove message type without a schema (a build of the `foxglove` crate without
    /// its descriptors).
    #[error("the Foxglove message type {0} has no schema in this build")]
    NoSchema(&'static str),
}

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
pub struct SampleMcap {
    path: PathBuf,
    writer: mcap::Writer<BufWriter<File>>,
    schemas: HashMap<&'static str, u16>,
    channels: HashMap<String, u16>,
    /// Frames written, by drive and LiDAR stamp: consecutive keyframes of a drive share
    /// sweeps, and a frame is written once.
    frames: HashSet<(u32, Stamp)>,
    /// The size of the sample's images (`[sample] image_width × image_height`).
    image_size: (u32, u32),
    summary: ViewSummary,
}

impl std::fmt::Debug for SampleMcap {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.debug_struct("SampleMcap")
            .field("path", &self.path)
            .field("summary", &self.summary)
            .finish_non_exhaustive()
    }
}

impl SampleMcap {
    /// Creates `path` (replacing a file there) for samples built with `config`.
    pub fn create(path: &Path, config: &SampleConfig) -> Result<Self, ViewError> {
        let file = File::create(path).map_err(|source| ViewError::Io {
            path: path.to_path_buf(),
            source,
        })?;
        let writer = mcap::WriteOptions::new()
            .profile("")
            .library(format!("superflow-pipeline/{}", env!("CARGO_PKG_VERSION")))
            .compression(Some(mcap::Compression::Zstd))
            .create(BufWriter::new(file))
            .map_err(|source| ViewError::Mcap {
                path: path.to_path_buf(),
                source,
            })?;
        Ok(Self {
            path: path.to_path_buf(),
            writer,
            schemas: HashMap::new(),
            channels: HashMap::new(),
            frames: HashSet::new(),
            image_size: (config.image_width, config.image_height),
            summary: ViewSummary::default(),
        })
    }

    fn mcap_error(&self, source: mcap::McapError) -> ViewError {
        ViewError::Mcap {
            path: self.path.clone(),
            source,
        }
    }

    fn timestamp(&self, stamp: Stamp) -> Result<Timestamp, ViewError> {
        let (sec, nanosec) = stamp.to_sec_nanosec();
        u32::try_from(sec)
            .ok()
            .and_then(|sec| Timestamp::new_checked(sec, nanosec))
            .ok_or(ViewError::Stamp {
                path: self.path.clone(),
                stamp,
            })
    }

    /// The channel of `topic` for message type `T`, declared on first use.
    fn channel<T: foxglove::Encode>(&mut self, topic: &str) -> Result<u16, ViewError> {
        if let Some(id) = self.channels.get(topic) {
            return Ok(*id);
        }
        let type_name = std::any::type_name::<T>();
        let schema_id = match self.schemas.get(type_name) {
            Some(id) => *id,
            None => {
                let schema = T::get_schema().ok_or(ViewError::NoSchema(type_name))?;
                let id = self
                    .writer
                    .add_schema(&schema.name, &schema.encoding, &schema.data)
                    .map_err(|e| self.mcap_error(e))?;
                self.schemas.insert(type_name, id);
                id
            }
        };
        let id = self
            .writer
            .add_channel(schema_id, topic, "protobuf", &BTreeMap::new())
            .map_err(|e| self.mcap_error(e))?;
        self.channels.insert(topic.to_string(), id);
        Ok(id)
    }

    /// Writes `message` on `topic` at `stamp`.
    fn write<T: foxglove::Encode + prost::Message>(
        &mut self,
        topic: &str,
        stamp: Stamp,
        message: &T,
    ) -> Result<(), ViewError> {
        let channel_id = self.channel::<T>(topic)?;
        let time = u64::try_from(stamp.nanos()).unwrap_or(0);
        self.writer
            .write_to_known_channel(
                &mcap::records::MessageHeader {
                    channel_id,
                    sequence: 0,
                    log_time: time,
                    publish_time: time,
                },
                &message.encode_to_vec(),
            )
            .map_err(|e| self.mcap_error(e))?;
        self.summary.messages += 1;
        Ok(())
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
            let ts = self.timestamp(stamp)?;
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
            self.write(
                "/tf",
                stamp,
                &FrameTransforms {
                    transforms: transforms.clone(),
                },
            )?;
            let cloud = point_cloud(ts, lidar_frame, &frame.cloud);
            self.write("/superflow/cloud", stamp, &cloud)?;
            for (slot, image) in frame.images.iter().enumerate() {
                self.write_image(stamp, ts, slot, image, &frame.cloud)?;
            }
        }
        let key = &sample.frames[sample.key_frame];
        let ts = self.timestamp(key.lidar_stamp)?;
        let dense = point_cloud(ts, lidar_frame, &sample.dense);
        self.write("/superflow/dense", key.lidar_stamp, &dense)?;
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
        self.writer
            .write_metadata(&mcap::records::Metadata {
                name: format!("superflow.sample.{}", sample.id.keyframe),
                metadata: BTreeMap::from([("draws".to_string(), draws.to_string())]),
            })
            .map_err(|e| self.mcap_error(e))?;
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
        let topic = |what: &str| format!("/superflow/{}/{what}", topic_name(&image.camera));
        let frame_id = image.calibration.frame_id.clone();
        let png = self.png(stamp, image, width, height, &image.rgb)?;
        self.write(
            &topic("image"),
            stamp,
            &CompressedImage {
                timestamp: Some(ts),
                frame_id: frame_id.clone(),
                data: png.into(),
                format: "png".into(),
            },
        )?;
        self.write(
            &topic("calibration"),
            stamp,
            &resized_calibration(ts, image, width, height),
        )?;
        let colours: Vec<u8> = image
            .superpixels
            .iter()
            .flat_map(|id| id_colour(*id))
            .collect();
        let png = self.png(stamp, image, width, height, &colours)?;
        self.write(
            &topic("superpixels"),
            stamp,
            &CompressedImage {
                timestamp: Some(ts),
                frame_id,
                data: png.into(),
                format: "png".into(),
            },
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
        self.write(
            &topic("pairings"),
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

    /// `rgb` (`width × height × 3`) as PNG.
    fn png(
        &self,
        stamp: Stamp,
        image: &SampleImage,
        width: u32,
        height: u32,
        rgb: &[u8],
    ) -> Result<Vec<u8>, ViewError> {
        let mut out = Vec::new();
        let mut encoder = png::Encoder::new(&mut out, width, height);
        encoder.set_color(png::ColorType::Rgb);
        encoder.set_depth(png::BitDepth::Eight);
        encoder.set_compression(png::Compression::Fast);
        encoder
            .write_header()
            .and_then(|mut w| w.write_image_data(rgb).and_then(|()| w.finish()))
            .map_err(|source| ViewError::Png {
                path: self.path.clone(),
                camera: image.camera.clone(),
                stamp,
                source,
            })?;
        Ok(out)
    }

    /// Writes the summary and index and closes the file.
    pub fn finish(mut self) -> Result<ViewSummary, ViewError> {
        self.writer.finish().map_err(|e| self.mcap_error(e))?;
        Ok(self.summary)
    }
}

/// A camera name as one topic level.
fn topic_name(camera: &str) -> String {
    camera
        .trim_matches('/')
        .chars()
        .map(|c| {
            if c.is_ascii_alphanumeric() || c == '_' || c == '-' {
                c
            } else {
                '_'
            }
        })
        .collect()
}

fn colour([r, g, b]: [u8; 3]) -> Color {
    Color {
        r: f64::from(r) / 255.0,
        g: f64::from(g) / 255.0,
        b: f64::from(b) / 255.0,
        a: 1.0,
    }
}

fn frame_transform(
    ts: Timestamp,
    parent: &str,
    child: &str,
    parent_from_child: &Isometry3<f64>,
) -> FrameTransform {
    let t = parent_from_child.translation.vector;
    let q = parent_from_child.rotation.quaternion();
    FrameTransform {
        timestamp: Some(ts),
        parent_frame_id: parent.to_string(),
        child_frame_id: child.to_string(),
        translation: Some(Vector3 {
            x: t.x,
            y: t.y,
            z: t.z,
        }),
        rotation: Some(Quaternion {
            x: q.i,
            y: q.j,
            z: q.k,
            w: q.w,
        }),
    }
}

/// The calibration of the resized (and possibly mirrored) image: the raw one's
/// intrinsics scaled about pixel corners (pixel centres at integers, as OpenCV and ROS
/// have them), mirrored by a negative `fx` and skew; the distortion, a function of the
/// normalised coordinates, unchanged.
pub fn resized_calibration(
    ts: Timestamp,
    image: &SampleImage,
    width: u32,
    height: u32,
) -> CameraCalibration {
    let cal = &image.calibration;
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
    if image.flipped {
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

/// `cloud` as a Foxglove point cloud in `frame_id`, its points back where they were
/// recorded (the augmentation undone).
fn point_cloud(ts: Timestamp, frame_id: &str, cloud: &Cloud) -> PointCloud {
    let xyz = cloud.augmentation.unapplied(&cloud.xyz);
    let n = xyz.len();
    let mut superpixel = vec![-1i32; n];
    for pair in cloud.pairings.iter().rev() {
        if let Some(s) = superpixel.get_mut(pair.point as usize) {
            *s = i32::try_from(pair.superpixel).unwrap_or(i32::MAX);
        }
    }
    let mut data = Vec::with_capacity(n * POINT_STRIDE as usize);
    for (i, p) in xyz.iter().enumerate() {
        for c in p {
            data.extend_from_slice(&c.to_le_bytes());
        }
        let intensity = cloud.intensity.get(i).copied().unwrap_or(0.0);
        data.extend_from_slice(&intensity.to_le_bytes());
        data.push(cloud.source_sweep.get(i).copied().unwrap_or(0));
        data.push(u8::from(superpixel[i] >= 0));
        data.extend_from_slice(&[0, 0]);
        data.extend_from_slice(&superpixel[i].to_le_bytes());
        let voxel = cloud
            .voxels
            .point_to_voxel
            .get(i)
            .copied()
            .unwrap_or(u32::MAX);
        data.extend_from_slice(&voxel.to_le_bytes());
    }
    PointCloud {
        timestamp: Some(ts),
        frame_id: frame_id.to_string(),
        pose: None,
        point_stride: POINT_STRIDE,
        fields: POINT_FIELDS
            .iter()
            .map(|(name, ty, offset)| PackedElementField {
                name: (*name).to_string(),
                offset: *offset,
                r#type: *ty as i32,
            })
            .collect(),
        data: data.into(),
    }
}
