//! Writes a simulated drive as `ros2 bag record -s mcap` would: `ros2msg` schemas, CDR
//! messages, zstd chunks, receive-time `log_time`s; a velodyne-layout raw cloud with
//! per-point time (not motion compensated), `image_transport` compressed JPEGs with
//! plumb_bob distortion, `CameraInfo`, `map → odom → base_link` on `/tf` and the
//! extrinsics (`base_link → cam_*_link → cam_*_optical_frame`) once on `/tf_static`;
//! class maps as raw `mono8` images in the bag, or as `png` compressed images in a
//! sidecar file. The LiDAR's per-point labels are `PointCloud2`s of one UINT8 `label`
//! field on `/lidar_top/points_raw/labels` in a `<drive>.labels.mcap` sidecar (same
//! stamp, frame and point order as the sweep), or a `label` field of the sweep itself.

use crate::dialect::Dialect;
use crate::drive::{GeneratedDrive, WrittenDrive};
use crate::encode::{class_map_pngs, jpegs};
use crate::error::{GenerateError, Result};
use crate::options::{ClassMapStorage, LidarLabels};
use crate::out::McapOut;
use crate::render::CameraFrame;
use crate::sim::{CameraRig, Return, body_from_optical};
use crate::simulation::Simulation;
use crate::truth::{CameraTruth, FramesTruth, PoseTruth, SweepTruth};
use nalgebra::{Isometry3, Translation3, UnitQuaternion};
use std::collections::BTreeMap;
use superflow_schemas::Stamp;
use superflow_schemas::ros2::{
    self, CameraInfo, CompressedImage, Header, Image, PointCloud2, PointField, Quaternion,
    Ros2Message, Ros2Time, TfMessage, Transform, TransformStamped, Vector3,
};
use superflow_schemas::sensor::CameraCalibration;

/// The world frame.
pub const MAP_FRAME: &str = "map";
/// The odometry frame.
pub const ODOM_FRAME: &str = "odom";
/// The vehicle frame.
pub const EGO_FRAME: &str = "base_link";
/// The LiDAR frame.
pub const LIDAR_FRAME: &str = "lidar_top";
/// The LiDAR topic.
pub const LIDAR_TOPIC: &str = "/lidar_top/points_raw";
/// The topic of the label clouds in the labels sidecar.
pub const LABELS_TOPIC: &str = "/lidar_top/points_raw/labels";

/// Lower-case ROS name of a camera (`CAM_FRONT` → `cam_front`).
pub fn camera_base(name: &str) -> String {
    name.to_ascii_lowercase()
}

/// Localisation's correction `map_from_odom`: a slow drift, published at 10 Hz.
pub fn map_from_odom(start: Stamp, at: Stamp) -> Isometry3<f64> {
    let s = at.secs_since(start);
    Isometry3::from_parts(
        Translation3::new(0.5 + 0.02 * s, -0.3 - 0.01 * s, 0.0),
        UnitQuaternion::from_euler_angles(0.0, 0.0, 0.01 + 0.001 * s),
    )
}

fn header(stamp: Stamp, frame_id: &str) -> Result<Header> {
    Ok(Header {
        stamp: Ros2Time::from_nanos(stamp.nanos()).ok_or(GenerateError::StampOutOfRange {
            format: "ROS 2",
            stamp,
        })?,
        frame_id: frame_id.to_string(),
    })
}

fn transform_stamped(
    stamp: Stamp,
    parent: &str,
    child: &str,
    parent_from_child: &Isometry3<f64>,
) -> Result<TransformStamped> {
    let t = parent_from_child.translation.vector;
    let q = parent_from_child.rotation.quaternion();
    Ok(TransformStamped {
        header: header(stamp, parent)?,
        child_frame_id: child.to_string(),
        transform: Transform {
            translation: Vector3 {
                x: t.x,
                y: t.y,
                z: t.z,
            },
            rotation: Quaternion {
                x: q.i,
                y: q.j,
                z: q.k,
                w: q.w,
            },
        },
    })
}

fn qos(transient_local: bool) -> BTreeMap<String, String> {
    let durability = if transient_local {
        "transient_local"
    } else {
        "volatile"
    };
    let profile = format!(
        "- history: 3\n  depth: 0\n  reliability: reliable\n  durability: {durability}\n  deadline:\n    sec: 9223372036\n    nsec: 854775807\n  lifespan:\n    sec: 9223372036\n    nsec: 854775807\n  liveliness: automatic\n  liveliness_lease_duration:\n    sec: 9223372036\n    nsec: 854775807\n  avoid_ros_namespace_conventions: false"
    );
    BTreeMap::from([("offered_qos_profiles".to_string(), profile)])
}

fn schema<T: Ros2Message>() -> (&'static str, &'static str, &'static [u8]) {
    (
        T::SCHEMA_NAME,
        ros2::SCHEMA_ENCODING,
        T::SCHEMA_DEFINITION.as_bytes(),
    )
}

/// Recorder latency: `log_time` is when the message reached the recorder.
const LIDAR_LATENCY_NANOS: i64 = 62_000_000;
const CAMERA_LATENCY_NANOS: i64 = 21_000_000;
const TF_LATENCY_NANOS: i64 = 1_200_000;
/// `publish_time` precedes `log_time` by this.
const TRANSPORT_NANOS: i64 = 400_000;

/// Queues `data`, stamped `stamp`, as received `latency` after it (`log_time`) and
/// published [`TRANSPORT_NANOS`] before that.
fn queue(out: &mut McapOut, channel: usize, stamp: Stamp, latency: i64, data: Vec<u8>) {
    let log_time = stamp.nanos() + latency;
    out.message(channel, log_time, log_time - TRANSPORT_NANOS, data);
}

/// Declares a channel of `T` with the volatile QoS of a sensor topic.
fn channel<T: Ros2Message>(out: &mut McapOut, topic: &str, role: &str) -> usize {
    out.channel(
        topic,
        role,
        schema::<T>(),
        ros2::MESSAGE_ENCODING,
        qos(false),
    )
}

/// Writes the drive; returns the MCAP bytes and the ground truth.
pub fn write(sim: &Simulation) -> Result<GeneratedDrive> {
    let mut out = McapOut::default();
    out.set_chunk_size(sim.options.chunk_size);
    let tf_static = out.channel(
        "/tf_static",
        "static_transforms",
        schema::<TfMessage>(),
        ros2::MESSAGE_ENCODING,
        qos(true),
    );
    let tf = channel::<TfMessage>(&mut out, "/tf", "transforms");
    let lidar = channel::<PointCloud2>(&mut out, LIDAR_TOPIC, "lidar");

    write_static_transforms(&mut out, tf_static, sim)?;
    write_odometry(&mut out, tf, sim)?;
    let mut labels =
        (sim.options.labels.resolve(Dialect::Ros2) == LidarLabels::Sidecar).then(|| {
            let mut side = McapOut::default();
            side.set_chunk_size(sim.options.chunk_size);
            let channel = channel::<PointCloud2>(&mut side, LABELS_TOPIC, "labels");
            (side, channel)
        });
    let (sweeps, lidar_stamps) = write_lidar(&mut out, lidar, labels.as_mut(), sim)?;
    let mut sidecar = (sim.options.class_maps == ClassMapStorage::PngSidecar).then(|| {
        let mut side = McapOut::default();
        side.set_chunk_size(sim.options.chunk_size);
        side
    });
    let cameras = sim
        .rig
        .cameras
        .iter()
        .enumerate()
        .map(|(i, cam)| write_camera(&mut out, sidecar.as_mut(), sim, i, cam))
        .collect::<Result<Vec<_>>>()?;

    let metadata = format!(
        "rosbag2_bagfile_information:\n  version: 8\n  storage_identifier: mcap\n  relative_file_paths:\n    - {}.mcap\n",
        sim.options.drive_name(Dialect::Ros2)
    );
    out.metadata("rosbag2", &[("serialized_metadata", &metadata)]);
    let (mcap, channels) = out.finish("ros2", Some(mcap::Compression::Zstd))?;
    let (sidecar, sidecar_channels) = sidecar
        .map(|side| side.finish("ros2", Some(mcap::Compression::Zstd)))
        .transpose()?
        .unzip();
    let (labels_sidecar, labels_channels) = labels
        .map(|(side, _)| side.finish("ros2", Some(mcap::Compression::Zstd)))
        .transpose()?
        .unzip();
    let labels = sim.labels_truth(Dialect::Ros2, LIDAR_TOPIC, LABELS_TOPIC, labels_channels);
    let truth = sim.ground_truth(WrittenDrive {
        dialect: Dialect::Ros2,
        profile: "ros2",
        compression: "zstd",
        frames: FramesTruth {
            map: MAP_FRAME.into(),
            ego: EGO_FRAME.into(),
            lidar: LIDAR_FRAME.into(),
        },
        lidar_topic: LIDAR_TOPIC.into(),
        motion_compensated: false,
        stamp_at: "sweep_start",
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

/// The static extrinsics, once, at the start (latched): `base_link → lidar_top` and,
/// per camera, `base_link → cam_*_link → cam_*_optical_frame`.
fn write_static_transforms(out: &mut McapOut, channel: usize, sim: &Simulation) -> Result<()> {
    let start = sim.timing.start;
    let mut statics = vec![transform_stamped(
        start,
        EGO_FRAME,
        LIDAR_FRAME,
        &sim.rig.ego_from_lidar,
    )?];
    for cam in &sim.rig.cameras {
        let base = camera_base(cam.name);
        let link = format!("{base}_link");
        statics.push(transform_stamped(
            start,
            EGO_FRAME,
            &link,
            &cam.ego_from_camera_body,
        )?);
        statics.push(transform_stamped(
            start,
            &link,
            &format!("{base}_optical_frame"),
            &body_from_optical(),
        )?);
    }
    queue(
        out,
        channel,
        start,
        0,
        ros2::encode(&TfMessage {
            transforms: statics,
        })?,
    );
    Ok(())
}

/// Odometry (`odom → base_link`) at 50 Hz and localisation (`map → odom`) at 10 Hz on
/// `/tf`, covering the drive with a margin.
fn write_odometry(out: &mut McapOut, channel: usize, sim: &Simulation) -> Result<()> {
    let start = sim.timing.start;
    let end = start.add_nanos(sim.timing.duration_nanos);
    let mut n = -2i64;
    loop {
        let stamp = start.add_nanos(n * 20_000_000);
        if stamp > end.add_nanos(40_000_000) {
            break;
        }
        let odom_from_ego = map_from_odom(start, stamp).inverse() * sim.map_from_ego(stamp);
        let mut transforms = vec![transform_stamped(
            stamp,
            ODOM_FRAME,
            EGO_FRAME,
            &odom_from_ego,
        )?];
        if n.rem_euclid(5) == 0 {
            transforms.push(transform_stamped(
                stamp,
                MAP_FRAME,
                ODOM_FRAME,
                &map_from_odom(start, stamp),
            )?);
        }
        queue(
            out,
            channel,
            stamp,
            TF_LATENCY_NANOS,
            ros2::encode(&TfMessage { transforms })?,
        );
        n += 1;
    }
    Ok(())
}

/// The LiDAR: velodyne XYZIRT layout (point_step 22; 23 with a UINT8 `label` field),
/// stamped at the start of the sweep, each point in the LiDAR frame at its own firing
/// time; with `labels`, a label cloud per sweep in the labels sidecar (its file and
/// channel). Returns the sweeps' truth and stamps.
fn write_lidar(
    out: &mut McapOut,
    channel: usize,
    mut labels: Option<&mut (McapOut, usize)>,
    sim: &Simulation,
) -> Result<(Vec<SweepTruth>, Vec<Stamp>)> {
    let label_field = sim.options.labels.resolve(Dialect::Ros2) == LidarLabels::InCloud;
    let field = |name: &str, offset, datatype| PointField {
        name: name.into(),
        offset,
        datatype,
        count: 1,
    };
    let mut fields = vec![
        field("x", 0, PointField::FLOAT32),
        field("y", 4, PointField::FLOAT32),
        field("z", 8, PointField::FLOAT32),
        field("intensity", 12, PointField::FLOAT32),
        field("ring", 16, PointField::UINT16),
        field("time", 18, PointField::FLOAT32),
    ];
    if label_field {
        fields.push(field("label", 22, PointField::UINT8));
    }
    let point_step = if label_field { 23 } else { 22 };
    let mut sweeps = Vec::new();
    let mut lidar_stamps = Vec::new();
    for (k, returns) in sim.sweeps.iter().enumerate() {
        let (begin, _) = sim.timing.sweep_span(k);
        let data = sweep_data(sim, begin, returns, label_field);
        let width = u32::try_from(returns.len()).map_err(|_| GenerateError::TooManyPoints {
            sweep: k,
            points: returns.len(),
        })?;
        let cloud = PointCloud2 {
            header: header(begin, LIDAR_FRAME)?,
            height: 1,
            width,
            fields: fields.clone(),
            is_bigendian: false,
            point_step,
            row_step: point_step * width,
            data,
            is_dense: true,
        };
        queue(
            out,
            channel,
            begin,
            LIDAR_LATENCY_NANOS,
            ros2::encode(&cloud)?,
        );
        if let Some((side, labels_channel)) = labels.as_deref_mut() {
            let cloud = PointCloud2 {
                header: header(begin, LIDAR_FRAME)?,
                height: 1,
                width,
                fields: vec![field("label", 0, PointField::UINT8)],
                is_bigendian: false,
                point_step: 1,
                row_step: width,
                data: sim.sweep_classes(k),
                is_dense: true,
            };
            queue(
                side,
                *labels_channel,
                begin,
                LIDAR_LATENCY_NANOS,
                ros2::encode(&cloud)?,
            );
        }
        sweeps.push(SweepTruth {
            stamp_nanos: begin.nanos(),
            points: u64::from(width),
        });
        lidar_stamps.push(begin);
    }
    Ok((sweeps, lidar_stamps))
}

/// The points of a sweep that began at `begin`, 22 bytes each: x, y, z and intensity
/// (`f32`) in the LiDAR frame at the point's firing time, ring (`u16`), time since
/// `begin` in seconds (`f32`); with `label`, the return's class (`u8`) after them.
fn sweep_data(sim: &Simulation, begin: Stamp, returns: &[Return], label: bool) -> Vec<u8> {
    let step = if label { 23 } else { 22 };
    let mut data = Vec::with_capacity(returns.len() * step);
    let mut column_stamp = None;
    let mut lidar_from_map = Isometry3::identity();
    for r in returns {
        if column_stamp != Some(r.stamp) {
            column_stamp = Some(r.stamp);
            lidar_from_map = (sim.map_from_ego(r.stamp) * sim.rig.ego_from_lidar).inverse();
        }
        let p = lidar_from_map * r.point_in_map;
        for v in [p.x as f32, p.y as f32, p.z as f32, r.intensity] {
            data.extend_from_slice(&v.to_le_bytes());
        }
        data.extend_from_slice(&r.ring.to_le_bytes());
        data.extend_from_slice(&(r.stamp.secs_since(begin) as f32).to_le_bytes());
        if label {
            data.push(r.class);
        }
    }
    data
}

/// A camera's calibration as `CameraInfo` puts it: row-major `K`, `D` of the
/// distortion model, `P` = `[K | 0]`.
struct Intrinsics {
    k: [f64; 9],
    d: Vec<f64>,
    p: [f64; 12],
}

impl Intrinsics {
    fn of(calibration: &CameraCalibration) -> Self {
        let k: [f64; 9] = std::array::from_fn(|i| calibration.k[(i / 3, i % 3)]); // row-major
        let mut p = [0.0; 12];
        for row in 0..3 {
            p[row * 4..row * 4 + 3].copy_from_slice(&k[row * 3..row * 3 + 3]);
        }
        Self {
            k,
            d: calibration.distortion.coeffs(),
            p,
        }
    }
}

/// Camera `i`: its three channels (compressed image, `CameraInfo`, superpixel class
/// map, the last in `sidecar` when there is one), every frame on each; returns the
/// camera's truth.
fn write_camera(
    out: &mut McapOut,
    mut sidecar: Option<&mut McapOut>,
    sim: &Simulation,
    i: usize,
    cam: &CameraRig,
) -> Result<CameraTruth> {
    let base = camera_base(cam.name);
    let optical = format!("{base}_optical_frame");
    let image_topic = format!("/{base}/image_raw/compressed");
    let info_topic = format!("/{base}/camera_info");
    let superpixel_topic = format!("/{base}/superpixels");
    let image_channel = channel::<CompressedImage>(out, &image_topic, "image");
    let info_channel = channel::<CameraInfo>(out, &info_topic, "calibration");
    let superpixel_channel = match sidecar.as_deref_mut() {
        Some(side) => channel::<CompressedImage>(side, &superpixel_topic, "superpixels"),
        None => channel::<Image>(out, &superpixel_topic, "superpixels"),
    };
    let calibration = &cam.calibration;
    let intrinsics = Intrinsics::of(calibration);
    let stamps = &sim.camera_stamps[i];
    let frames = &sim.frames[i];
    let mut jpegs = jpegs(frames, sim.options.jpeg_coding)?.into_iter();
    let mut pngs = match sidecar {
        Some(_) => class_map_pngs(frames)?,
        None => Vec::new(),
    }
    .into_iter();
    for (frame, stamp) in frames.iter().zip(stamps) {
        let header = header(*stamp, &optical)?;
        let image = CompressedImage {
            header: header.clone(),
            format: "rgb8; jpeg compressed bgr8".into(),
            data: jpegs.next().unwrap_or_default(),
        };
        queue(
            out,
            image_channel,
            *stamp,
            CAMERA_LATENCY_NANOS,
            ros2::encode(&image)?,
        );
        let info = CameraInfo {
            header: header.clone(),
            height: calibration.height,
            width: calibration.width,
            distortion_model: calibration.distortion.model_name().into(),
            d: intrinsics.d.clone(),
            k: intrinsics.k,
            r: [1.0, 0.0, 0.0, 0.0, 1.0, 0.0, 0.0, 0.0, 1.0],
            p: intrinsics.p,
            ..Default::default()
        };
        queue(
            out,
            info_channel,
            *stamp,
            CAMERA_LATENCY_NANOS,
            ros2::encode(&info)?,
        );
        let superpixels = class_map(frame, header, pngs.next())?;
        let latency = CAMERA_LATENCY_NANOS + 9_000_000;
        let file = match sidecar.as_deref_mut() {
            Some(side) => side,
            None => &mut *out,
        };
        queue(file, superpixel_channel, *stamp, latency, superpixels);
    }
    Ok(CameraTruth {
        name: cam.name.to_string(),
        image_topic,
        calibration_topic: info_topic,
        superpixel_topic,
        frame_id: optical,
        width: calibration.width,
        height: calibration.height,
        k: intrinsics.k,
        distortion_model: calibration.distortion.model_name().into(),
        d: intrinsics.d,
        ego_from_camera: PoseTruth::from(&cam.ego_from_optical()),
        stamps_nanos: stamps.iter().map(|s| s.nanos()).collect(),
    })
}

/// The class-map message of `frame`: a raw `mono8` image, or with `png` (the class map
/// as PNG, for the sidecar) a compressed image of format `png`.
fn class_map(frame: &CameraFrame, header: Header, png: Option<Vec<u8>>) -> Result<Vec<u8>> {
    Ok(match png {
        Some(data) => ros2::encode(&CompressedImage {
            header,
            format: "png".into(),
            data,
        })?,
        None => ros2::encode(&Image {
            header,
            height: frame.classes.height,
            width: frame.classes.width,
            encoding: "mono8".into(),
            is_bigendian: 0,
            step: frame.classes.width,
            data: frame.classes.data.clone(),
        })?,
    })
}
