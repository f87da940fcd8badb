//! Writes a simulated drive as `ros2 bag record -s mcap` would: `ros2msg` schemas, CDR
//! messages, zstd chunks, receive-time `log_time`s; a velodyne-layout raw cloud with
//! per-point time (not motion compensated), `image_transport` compressed JPEGs with
//! plumb_bob distortion, `CameraInfo`, `map → odom → base_link` on `/tf` and the
//! extrinsics (`base_link → cam_*_link → cam_*_optical_frame`) once on `/tf_static`.

use crate::out::McapOut;
use crate::sim::body_from_optical;
use crate::truth::{CameraTruth, FramesTruth, PoseTruth, SweepTruth};
use crate::{Dialect, GeneratedDrive, Simulation, WrittenDrive, encode_jpeg};
use anyhow::Context as _;
use nalgebra::{Isometry3, Translation3, UnitQuaternion};
use std::collections::BTreeMap;
use superflow_schemas::Stamp;
use superflow_schemas::ros2::{
    self, CameraInfo, CompressedImage, Header, Image, PointCloud2, PointField, Quaternion,
    Ros2Message, Ros2Time, TfMessage, Transform, TransformStamped, Vector3,
};

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

fn header(stamp: Stamp, frame_id: &str) -> anyhow::Result<Header> {
    Ok(Header {
        stamp: Ros2Time::from_nanos(stamp.nanos()).context("stamp out of ROS 2 range")?,
        frame_id: frame_id.to_string(),
    })
}

fn transform_stamped(
    stamp: Stamp,
    parent: &str,
    child: &str,
    parent_from_child: &Isometry3<f64>,
) -> anyhow::Result<TransformStamped> {
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

/// Writes the drive; returns the MCAP bytes and the ground truth.
pub fn write(sim: &Simulation) -> anyhow::Result<GeneratedDrive> {
    let mut out = McapOut::default();
    out.set_chunk_size(sim.options.chunk_size);
    let enc = ros2::MESSAGE_ENCODING;
    let start = sim.timing.start;
    let end = start.add_nanos(sim.timing.duration_nanos);
    let queue = |out: &mut McapOut, channel, stamp: Stamp, latency: i64, data: Vec<u8>| {
        let log_time = stamp.nanos() + latency;
        out.message(channel, log_time, log_time - TRANSPORT_NANOS, data);
    };

    let tf_static = out.channel(
        "/tf_static",
        "static_transforms",
        schema::<TfMessage>(),
        enc,
        qos(true),
    );
    let tf = out.channel("/tf", "transforms", schema::<TfMessage>(), enc, qos(false));
    let lidar = out.channel(
        LIDAR_TOPIC,
        "lidar",
        schema::<PointCloud2>(),
        enc,
        qos(false),
    );

    // Static extrinsics, once, at the start (latched).
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
        &mut out,
        tf_static,
        start,
        0,
        ros2::encode(&TfMessage {
            transforms: statics,
        })?,
    );

    // Odometry at 50 Hz and localisation at 10 Hz, covering the drive with a margin.
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
            &mut out,
            tf,
            stamp,
            TF_LATENCY_NANOS,
            ros2::encode(&TfMessage { transforms })?,
        );
        n += 1;
    }

    // LiDAR: velodyne XYZIRT layout (point_step 22), stamped at the start of the sweep,
    // each point in the LiDAR frame at its own firing time.
    let field = |name: &str, offset, datatype| PointField {
        name: name.into(),
        offset,
        datatype,
        count: 1,
    };
    let fields = vec![
        field("x", 0, PointField::FLOAT32),
        field("y", 4, PointField::FLOAT32),
        field("z", 8, PointField::FLOAT32),
        field("intensity", 12, PointField::FLOAT32),
        field("ring", 16, PointField::UINT16),
        field("time", 18, PointField::FLOAT32),
    ];
    let mut sweeps = Vec::new();
    let mut lidar_stamps = Vec::new();
    for (k, returns) in sim.sweeps.iter().enumerate() {
        let (begin, _) = sim.timing.sweep_span(k);
        let mut data = Vec::with_capacity(returns.len() * 22);
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
        }
        let width = u32::try_from(returns.len())?;
        let cloud = PointCloud2 {
            header: header(begin, LIDAR_FRAME)?,
            height: 1,
            width,
            fields: fields.clone(),
            is_bigendian: false,
            point_step: 22,
            row_step: 22 * width,
            data,
            is_dense: true,
        };
        queue(
            &mut out,
            lidar,
            begin,
            LIDAR_LATENCY_NANOS,
            ros2::encode(&cloud)?,
        );
        sweeps.push(SweepTruth {
            stamp_nanos: begin.nanos(),
            points: u64::from(width),
        });
        lidar_stamps.push(begin);
    }

    let mut cameras = Vec::new();
    for (i, cam) in sim.rig.cameras.iter().enumerate() {
        let base = camera_base(cam.name);
        let optical = format!("{base}_optical_frame");
        let image_topic = format!("/{base}/image_raw/compressed");
        let info_topic = format!("/{base}/camera_info");
        let superpixel_topic = format!("/{base}/superpixels");
        let image_channel = out.channel(
            &image_topic,
            "image",
            schema::<CompressedImage>(),
            enc,
            qos(false),
        );
        let info_channel = out.channel(
            &info_topic,
            "calibration",
            schema::<CameraInfo>(),
            enc,
            qos(false),
        );
        let superpixel_channel = out.channel(
            &superpixel_topic,
            "superpixels",
            schema::<Image>(),
            enc,
            qos(false),
        );
        let calibration = &cam.calibration;
        let k: Vec<f64> = calibration.k.transpose().iter().copied().collect(); // row-major
        let k9: [f64; 9] = k
            .clone()
            .try_into()
            .map_err(|_| anyhow::anyhow!("K is 3x3"))?;
        let d = calibration.distortion.coeffs();
        let mut p = [0.0; 12];
        for row in 0..3 {
            p[row * 4..row * 4 + 3].copy_from_slice(&k[row * 3..row * 3 + 3]);
        }
        let stamps = &sim.camera_stamps[i];
        for (frame, stamp) in sim.frames[i].iter().zip(stamps) {
            let jpeg = encode_jpeg(&frame.image)?;
            queue(
                &mut out,
                image_channel,
                *stamp,
                CAMERA_LATENCY_NANOS,
                ros2::encode(&CompressedImage {
                    header: header(*stamp, &optical)?,
                    format: "rgb8; jpeg compressed bgr8".into(),
                    data: jpeg,
                })?,
            );
            queue(
                &mut out,
                info_channel,
                *stamp,
                CAMERA_LATENCY_NANOS,
                ros2::encode(&CameraInfo {
                    header: header(*stamp, &optical)?,
                    height: calibration.height,
                    width: calibration.width,
                    distortion_model: calibration.distortion.model_name().into(),
                    d: d.clone(),
                    k: k9,
                    r: [1.0, 0.0, 0.0, 0.0, 1.0, 0.0, 0.0, 0.0, 1.0],
                    p,
                    ..Default::default()
                })?,
            );
            queue(
                &mut out,
                superpixel_channel,
                *stamp,
                CAMERA_LATENCY_NANOS + 9_000_000,
                ros2::encode(&Image {
                    header: header(*stamp, &optical)?,
                    height: frame.classes.height,
                    width: frame.classes.width,
                    encoding: "mono8".into(),
                    is_bigendian: 0,
                    step: frame.classes.width,
                    data: frame.classes.data.clone(),
                })?,
            );
        }
        cameras.push(CameraTruth {
            name: cam.name.to_string(),
            image_topic,
            calibration_topic: info_topic,
            superpixel_topic,
            frame_id: optical,
            width: calibration.width,
            height: calibration.height,
            k: k9,
            distortion_model: calibration.distortion.model_name().into(),
            d,
            ego_from_camera: PoseTruth::from(&cam.ego_from_optical()),
            stamps_nanos: stamps.iter().map(|s| s.nanos()).collect(),
        });
    }

    out.metadata(
        "rosbag2",
        &[(
            "serialized_metadata",
            "rosbag2_bagfile_information:\n  version: 8\n  storage_identifier: mcap\n  relative_file_paths:\n    - street_ros2.mcap\n",
        )],
    );
    let (mcap, channels) = out.finish("ros2", Some(mcap::Compression::Zstd))?;
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
    });
    Ok(GeneratedDrive { mcap, truth })
}
