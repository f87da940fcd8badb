//! Writes a simulated drive as the nuScenes converter does (2024 layout, Foxglove
//! protobuf schemas): `/LIDAR_TOP`, `/CAM_*/image_rect_compressed`, `/CAM_*/camera_info`,
//! `/tf` with the ego pose at every sensor stamp and the extrinsics re-published at every
//! keyframe, plus `/CAM_*/superpixels` class maps (raw `mono8` images in the drive, or
//! `png` compressed images in a sidecar file) and an unrelated JSON `/odom` channel. The
//! LiDAR's per-point labels are a UINT8 `label` field of `/LIDAR_TOP` (as a
//! nuScenes-lidarseg conversion has them) or clouds of that one field on
//! `/LIDAR_TOP/labels` in a `<drive>.labels.mcap` sidecar.

use crate::dialect::Dialect;
use crate::drive::{GeneratedDrive, WrittenDrive};
use crate::encode::{class_map_pngs, jpegs};
use crate::error::{GenerateError, Result};
use crate::options::{ClassMapStorage, LidarLabels};
use crate::out::McapOut;
use crate::render::CameraFrame;
use crate::sim::CameraRig;
use crate::simulation::Simulation;
use crate::truth::{CameraTruth, FramesTruth, PoseTruth, SweepTruth};
use foxglove::Encode;
use foxglove::messages::{
    CameraCalibration, CompressedImage, FrameTransform, PackedElementField, PointCloud, Quaternion,
    RawImage, Timestamp, Vector3, packed_element_field::NumericType,
};
use nalgebra::Isometry3;
use prost::Message as _;
use std::collections::BTreeMap;
use superflow_schemas::Stamp;

/// Frame of the ego vehicle.
pub const EGO_FRAME: &str = "base_link";
/// The world frame.
pub const MAP_FRAME: &str = "map";
/// Frame and topic of the LiDAR.
pub const LIDAR: &str = "LIDAR_TOP";
/// Sweeps with index divisible by this are keyframes (2 Hz).
const KEYFRAME_EVERY: usize = 10;

fn timestamp(stamp: Stamp) -> Result<Timestamp> {
    let (sec, nanosec) = stamp.to_sec_nanosec();
    u32::try_from(sec)
        .ok()
        .and_then(|sec| Timestamp::new_checked(sec, nanosec))
        .ok_or(GenerateError::StampOutOfRange {
            format: "Foxglove",
            stamp,
        })
}

fn frame_transform(
    stamp: Stamp,
    parent: &str,
    child: &str,
    parent_from_child: &Isometry3<f64>,
) -> Result<Vec<u8>> {
    let t = parent_from_child.translation.vector;
    let q = parent_from_child.rotation.quaternion();
    Ok(FrameTransform {
        timestamp: Some(timestamp(stamp)?),
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
    .encode_to_vec())
}

/// A Foxglove schema: name, encoding and data.
#[derive(Debug)]
struct Schema {
    name: String,
    encoding: String,
    data: Vec<u8>,
}

impl Schema {
    /// The schema of the Foxglove message `T`.
    fn of<T: Encode>() -> Result<Self> {
        let schema = T::get_schema().ok_or(GenerateError::MissingSchema {
            type_name: std::any::type_name::<T>(),
        })?;
        Ok(Self {
            name: schema.name,
            encoding: schema.encoding,
            data: schema.data.into_owned(),
        })
    }

    /// Declares a protobuf channel of this schema without metadata.
    fn channel(&self, out: &mut McapOut, topic: &str, role: &str) -> usize {
        let schema = (
            self.name.as_str(),
            self.encoding.as_str(),
            self.data.as_slice(),
        );
        out.channel(topic, role, schema, "protobuf", BTreeMap::new())
    }
}

/// The channels of a camera.
#[derive(Debug, Clone, Copy)]
struct CameraChannels {
    image: usize,
    info: usize,
    /// In the drive, or in the sidecar when there is one.
    superpixels: usize,
}

/// The drive file and, with [`ClassMapStorage::PngSidecar`], the class-map sidecar;
/// with [`LidarLabels::Sidecar`], the labels sidecar.
#[derive(Debug)]
struct Files {
    drive: McapOut,
    sidecar: Option<McapOut>,
    labels: Option<McapOut>,
}

impl Files {
    /// The file the class maps go into.
    fn class_maps(&mut self) -> &mut McapOut {
        self.sidecar.as_mut().unwrap_or(&mut self.drive)
    }
}

/// The channels of the file.
#[derive(Debug)]
struct Channels {
    lidar: usize,
    /// The label clouds, in the labels sidecar.
    labels: Option<usize>,
    tf: usize,
    cameras: Vec<CameraChannels>,
    odom: usize,
}

impl Channels {
    /// Declares every channel, in the order the converter does; class maps in the
    /// sidecar, if there is one, as compressed images.
    fn declare(files: &mut Files, sim: &Simulation) -> Result<Self> {
        let point_cloud = Schema::of::<PointCloud>()?;
        let compressed_image = Schema::of::<CompressedImage>()?;
        let calibration = Schema::of::<CameraCalibration>()?;
        let class_map = match files.sidecar {
            Some(_) => Schema::of::<CompressedImage>()?,
            None => Schema::of::<RawImage>()?,
        };
        let frame_transform = Schema::of::<FrameTransform>()?;
        let out = &mut files.drive;
        let lidar = point_cloud.channel(out, &format!("/{LIDAR}"), "lidar");
        let tf = frame_transform.channel(out, "/tf", "transforms");
        let labels = files
            .labels
            .as_mut()
            .map(|side| point_cloud.channel(side, &labels_topic(), "labels"));
        let mut cameras = Vec::with_capacity(sim.rig.cameras.len());
        for cam in &sim.rig.cameras {
            let image = compressed_image.channel(
                &mut files.drive,
                &format!("/{}/image_rect_compressed", cam.name),
                "image",
            );
            let info = calibration.channel(
                &mut files.drive,
                &format!("/{}/camera_info", cam.name),
                "calibration",
            );
            let superpixels = class_map.channel(
                files.class_maps(),
                &format!("/{}/superpixels", cam.name),
                "superpixels",
            );
            cameras.push(CameraChannels {
                image,
                info,
                superpixels,
            });
        }
        let out = &mut files.drive;
        let odom_schema = br#"{"type":"object","properties":{"timestamp":{"type":"object"},"pos":{"type":"array"},"orientation":{"type":"array"},"vel":{"type":"array"}}}"#;
        let odom = out.channel(
            "/odom",
            "other",
            ("Pose", "jsonschema", odom_schema),
            "json",
            BTreeMap::new(),
        );
        Ok(Self {
            lidar,
            labels,
            tf,
            cameras,
            odom,
        })
    }
}

/// Writes the drive; returns the MCAP bytes (and the class-map sidecar's) and the
/// ground truth.
pub fn write(sim: &Simulation) -> Result<GeneratedDrive> {
    let new_file = || {
        let mut out = McapOut::default();
        out.set_chunk_size(sim.options.chunk_size);
        out
    };
    let labels = sim.options.labels.resolve(Dialect::Foxglove);
    let mut files = Files {
        drive: new_file(),
        sidecar: (sim.options.class_maps == ClassMapStorage::PngSidecar).then(new_file),
        labels: (labels == LidarLabels::Sidecar).then(new_file),
    };
    let channels = Channels::declare(&mut files, sim)?;
    let (sweeps, lidar_stamps) = write_lidar(&mut files, &channels, sim)?;
    let keyframe_stamps: Vec<Stamp> = lidar_stamps
        .iter()
        .step_by(KEYFRAME_EVERY)
        .copied()
        .collect();
    let cameras = sim
        .rig
        .cameras
        .iter()
        .enumerate()
        .map(|(i, cam)| write_camera(&mut files, &channels, sim, (i, cam), &keyframe_stamps))
        .collect::<Result<Vec<_>>>()?;
    let Files {
        drive: mut out,
        sidecar,
        labels: labels_sidecar,
    } = files;
    write_odometry(&mut out, channels.odom, sim);

    let description = format!(
        "superflow synthetic street, {} s, {} cameras, {}-beam LiDAR",
        sim.options.duration_secs(),
        sim.rig.cameras.len(),
        sim.rig.beam_elevations.len()
    );
    let name = sim.options.drive_name(Dialect::Foxglove);
    out.metadata(
        "scene-info",
        &[
            ("description", &description),
            ("name", &name),
            ("location", "procedural"),
            ("vehicle", "superflow-sim"),
            ("date_captured", "2023-11-14"),
        ],
    );

    let compression = sim.options.foxglove_compression;
    let (mcap, channels) = out.finish("", Some(compression.mcap()))?;
    let (sidecar, sidecar_channels) = sidecar
        .map(|side| side.finish("", Some(compression.mcap())))
        .transpose()?
        .unzip();
    let (labels_sidecar, labels_channels) = labels_sidecar
        .map(|side| side.finish("", Some(compression.mcap())))
        .transpose()?
        .unzip();
    let labels = sim.labels_truth(
        Dialect::Foxglove,
        &format!("/{LIDAR}"),
        &labels_topic(),
        labels_channels,
    );
    let truth = sim.ground_truth(WrittenDrive {
        dialect: Dialect::Foxglove,
        profile: "",
        compression: compression.name(),
        frames: FramesTruth {
            map: MAP_FRAME.into(),
            ego: EGO_FRAME.into(),
            lidar: LIDAR.into(),
        },
        lidar_topic: format!("/{LIDAR}"),
        motion_compensated: true,
        stamp_at: "sweep_end",
        channels,
        sweeps,
        lidar_stamps,
        cameras,
        sidecar_channels,
        labels,
    });
    Ok(GeneratedDrive {
        mcap,
        sidecar,
        labels_sidecar,
        truth,
    })
}

/// Topic of the label clouds in the labels sidecar.
fn labels_topic() -> String {
    format!("/{LIDAR}/labels")
}

/// The LiDAR, motion compensated into the LiDAR frame at the end of the sweep, with the
/// ego pose on `/tf` at every sweep and the LiDAR's extrinsics at every keyframe; the
/// labels as a field of the points or as label clouds in the labels sidecar. Returns
/// the sweeps' truth and stamps.
fn write_lidar(
    files: &mut Files,
    channels: &Channels,
    sim: &Simulation,
) -> Result<(Vec<SweepTruth>, Vec<Stamp>)> {
    let label_field = sim.options.labels.resolve(Dialect::Foxglove) == LidarLabels::InCloud;
    let field = |name: &str, offset: u32, numeric: NumericType| PackedElementField {
        name: name.to_string(),
        offset,
        r#type: numeric as i32,
    };
    let mut fields: Vec<PackedElementField> = ["x", "y", "z", "intensity", "ring"]
        .iter()
        .enumerate()
        .map(|(i, name)| field(name, 4 * i as u32, NumericType::Float32))
        .collect();
    if label_field {
        fields.push(field("label", 20, NumericType::Uint8));
    }
    let point_stride = if label_field { 21 } else { 20 };
    let mut sweeps = Vec::new();
    let mut lidar_stamps = Vec::new();
    for (k, returns) in sim.sweeps.iter().enumerate() {
        let (_, end) = sim.timing.sweep_span(k);
        let lidar_from_map = (sim.map_from_ego(end) * sim.rig.ego_from_lidar).inverse();
        let mut data = Vec::with_capacity(returns.len() * point_stride as usize);
        for r in returns {
            let p = lidar_from_map * r.point_in_map;
            for v in [
                p.x as f32,
                p.y as f32,
                p.z as f32,
                r.intensity,
                f32::from(r.ring),
            ] {
                data.extend_from_slice(&v.to_le_bytes());
            }
            if label_field {
                data.push(r.class);
            }
        }
        let msg = PointCloud {
            timestamp: Some(timestamp(end)?),
            frame_id: LIDAR.to_string(),
            pose: None,
            point_stride,
            fields: fields.clone(),
            data: data.into(),
        };
        let at = end.nanos();
        let out = &mut files.drive;
        out.message(channels.lidar, at, at, msg.encode_to_vec());
        let ego = frame_transform(end, MAP_FRAME, EGO_FRAME, &sim.map_from_ego(end))?;
        out.message(channels.tf, at, at, ego);
        if k % KEYFRAME_EVERY == 0 {
            let extrinsics = frame_transform(end, EGO_FRAME, LIDAR, &sim.rig.ego_from_lidar)?;
            out.message(channels.tf, at, at, extrinsics);
        }
        if let (Some(side), Some(channel)) = (files.labels.as_mut(), channels.labels) {
            let labels = PointCloud {
                timestamp: Some(timestamp(end)?),
                frame_id: LIDAR.to_string(),
                pose: None,
                point_stride: 1,
                fields: vec![field("label", 0, NumericType::Uint8)],
                data: sim.sweep_classes(k).into(),
            };
            side.message(channel, at, at, labels.encode_to_vec());
        }
        sweeps.push(SweepTruth {
            stamp_nanos: end.nanos(),
            points: returns.len() as u64,
        });
        lidar_stamps.push(end);
    }
    Ok((sweeps, lidar_stamps))
}

/// Camera `i`: every frame's image, calibration and superpixel class map, the ego pose
/// at its stamp and, at keyframes, the camera's extrinsics. Keyframe images are logged
/// at the keyframe LiDAR stamp, as the converter does. Returns the camera's truth.
fn write_camera(
    files: &mut Files,
    channels: &Channels,
    sim: &Simulation,
    (i, cam): (usize, &CameraRig),
    keyframe_stamps: &[Stamp],
) -> Result<CameraTruth> {
    let camera = channels.cameras[i];
    let stamps = &sim.camera_stamps[i];
    let mut keyframe_log = BTreeMap::new();
    for key in keyframe_stamps {
        if let Some(nearest) = stamps.iter().min_by_key(|s| s.nanos_since(*key).abs()) {
            keyframe_log.insert(*nearest, *key);
        }
    }
    let calibration = &cam.calibration;
    let k: [f64; 9] = std::array::from_fn(|i| calibration.k[(i / 3, i % 3)]); // row-major
    let mut p = Vec::with_capacity(12);
    for row in 0..3 {
        p.extend_from_slice(&k[row * 3..row * 3 + 3]);
        p.push(0.0);
    }
    let frames = &sim.frames[i];
    let mut jpegs = jpegs(frames, sim.options.jpeg_coding)?.into_iter();
    let mut pngs = match files.sidecar {
        Some(_) => class_map_pngs(frames)?,
        None => Vec::new(),
    }
    .into_iter();
    for (frame, stamp) in frames.iter().zip(stamps) {
        let log_time = keyframe_log.get(stamp).unwrap_or(stamp).nanos();
        let out = &mut files.drive;
        let image = CompressedImage {
            timestamp: Some(timestamp(*stamp)?),
            frame_id: cam.name.to_string(),
            data: jpegs.next().unwrap_or_default().into(),
            format: "jpeg".into(),
        };
        out.message(camera.image, log_time, log_time, image.encode_to_vec());
        let info = CameraCalibration {
            timestamp: Some(timestamp(*stamp)?),
            frame_id: cam.name.to_string(),
            width: calibration.width,
            height: calibration.height,
            distortion_model: String::new(),
            d: Vec::new(),
            k: k.to_vec(),
            r: vec![1.0, 0.0, 0.0, 0.0, 1.0, 0.0, 0.0, 0.0, 1.0],
            p: p.clone(),
        };
        out.message(camera.info, log_time, log_time, info.encode_to_vec());
        let superpixels = class_map(frame, *stamp, cam.name, pngs.next())?;
        files
            .class_maps()
            .message(camera.superpixels, log_time, log_time, superpixels);
        let out = &mut files.drive;
        let ego = frame_transform(*stamp, MAP_FRAME, EGO_FRAME, &sim.map_from_ego(*stamp))?;
        out.message(channels.tf, stamp.nanos(), stamp.nanos(), ego);
        if keyframe_log.contains_key(stamp) {
            let extrinsics = frame_transform(*stamp, EGO_FRAME, cam.name, &cam.ego_from_optical())?;
            out.message(channels.tf, log_time, log_time, extrinsics);
        }
    }
    Ok(CameraTruth {
        name: cam.name.to_string(),
        image_topic: format!("/{}/image_rect_compressed", cam.name),
        calibration_topic: format!("/{}/camera_info", cam.name),
        superpixel_topic: format!("/{}/superpixels", cam.name),
        frame_id: cam.name.to_string(),
        width: calibration.width,
        height: calibration.height,
        k,
        distortion_model: String::new(),
        d: Vec::new(),
        ego_from_camera: PoseTruth::from(&cam.ego_from_optical()),
        stamps_nanos: stamps.iter().map(|s| s.nanos()).collect(),
    })
}

/// The class-map message of `frame`: a raw `mono8` image, or with `png` (the class map
/// as PNG, for the sidecar) a compressed image of format `png`.
fn class_map(
    frame: &CameraFrame,
    stamp: Stamp,
    name: &str,
    png: Option<Vec<u8>>,
) -> Result<Vec<u8>> {
    Ok(match png {
        Some(png) => CompressedImage {
            timestamp: Some(timestamp(stamp)?),
            frame_id: name.to_string(),
            data: png.into(),
            format: "png".into(),
        }
        .encode_to_vec(),
        None => RawImage {
            timestamp: Some(timestamp(stamp)?),
            frame_id: name.to_string(),
            width: frame.classes.width,
            height: frame.classes.height,
            encoding: "mono8".into(),
            step: frame.classes.width,
            data: frame.classes.data.clone().into(),
        }
        .encode_to_vec(),
    })
}

/// CAN-bus style odometry at 10 Hz: JSON, not used by superflow.
fn write_odometry(out: &mut McapOut, channel: usize, sim: &Simulation) {
    let end = sim.timing.start.add_nanos(sim.timing.duration_nanos);
    let mut stamp = sim.timing.start;
    while stamp < end {
        let pose = sim.map_from_ego(stamp);
        let (sec, nsec) = stamp.to_sec_nanosec();
        let q = pose.rotation.quaternion();
        let t = pose.translation.vector;
        let json = format!(
            r#"{{"timestamp":{{"sec":{sec},"nsec":{nsec}}},"pos":[{},{},{}],"orientation":[{},{},{},{}],"vel":[{},0.0,0.0]}}"#,
            t.x,
            t.y,
            t.z,
            q.w,
            q.i,
            q.j,
            q.k,
            crate::sim::EGO_SPEED
        );
        out.message(channel, stamp.nanos(), stamp.nanos(), json.into_bytes());
        stamp = stamp.add_nanos(100_000_000);
    }
}
