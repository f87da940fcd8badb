//! Ingest of file layouts other than the sample drives, built in the test: a
//! kitti2mcap-shaped ROS 2 file and a 2026 (lower-case) nuScenes-converter file.

#![allow(clippy::unwrap_used, clippy::expect_used)] // tests fail loudly on purpose

use foxglove::Encode;
use nalgebra::{Isometry3, Point3, Translation3, UnitQuaternion, Vector3};
use prost::Message as _;
use std::collections::BTreeMap;
use superflow_pipeline::decode::foxglove as fx;
use superflow_pipeline::decode::ros2::{self, Ros2Message};
use superflow_pipeline::drive::{Drive, IngestConfig, Role};
use superflow_recordings::out::McapOut;
use superflow_schemas::Stamp;

const T0: i64 = 1_317_000_000_000_000_000; // 2011-09-26, a KITTI date

fn write(out: McapOut, profile: &str, name: &str) -> std::path::PathBuf {
    let (bytes, _) = out.finish(profile, Some(mcap::Compression::Zstd)).unwrap();
    let dir = std::env::temp_dir().join(format!("superflow-ingest-{}", std::process::id()));
    std::fs::create_dir_all(&dir).unwrap();
    let path = dir.join(name);
    std::fs::write(&path, bytes).unwrap();
    path
}

fn ros_schema<T: Ros2Message>() -> (&'static str, &'static str, &'static [u8]) {
    (
        T::SCHEMA_NAME,
        ros2::SCHEMA_ENCODING,
        T::SCHEMA_DEFINITION.as_bytes(),
    )
}

fn header(stamp: i64, frame: &str) -> ros2::Header {
    ros2::Header {
        stamp: ros2::Ros2Time::from_nanos(stamp).unwrap(),
        frame_id: frame.into(),
    }
}

fn ros_tf(stamp: i64, parent: &str, child: &str, iso: &Isometry3<f64>) -> ros2::TransformStamped {
    let t = iso.translation.vector;
    let q = iso.rotation.quaternion();
    ros2::TransformStamped {
        header: header(stamp, parent),
        child_frame_id: child.into(),
        transform: ros2::Transform {
            translation: ros2::Vector3 {
                x: t.x,
                y: t.y,
                z: t.z,
            },
            rotation: ros2::Quaternion {
                x: q.i,
                y: q.j,
                z: q.k,
                w: q.w,
            },
        },
    }
}

/// The OXTS trajectory of the synthetic KITTI drive: 5 m/s, turning at 0.1 rad/s.
fn map_from_base(stamp: i64) -> Isometry3<f64> {
    let s = (stamp - T0) as f64 * 1e-9;
    Isometry3::from_parts(
        Translation3::new(5.0 * s, 0.0, -0.93),
        UnitQuaternion::from_euler_angles(0.0, 0.0, 0.1 * s),
    )
}

/// kitti2mcap's layout: one `/tf_static` message, `map -> base_link` at 10 Hz on `/tf`,
/// `rgb8` and `mono8` raw images with `CameraInfo`, a 16-byte XYZI cloud, an IMU channel
/// superflow does not read, sensor stamps between the OXTS stamps, and a last sweep after
/// the last pose.
#[test]
fn kitti2mcap_shaped_file_is_discovered_and_poses_interpolate() {
    let mut out = McapOut::default();
    let none = BTreeMap::new;
    let cdr = ros2::MESSAGE_ENCODING;
    let tf_static = out.channel(
        "/tf_static",
        "static",
        ros_schema::<ros2::TfMessage>(),
        cdr,
        none(),
    );
    let tf = out.channel("/tf", "tf", ros_schema::<ros2::TfMessage>(), cdr, none());
    let velo = out.channel(
        "/kitti/velodyne_points",
        "lidar",
        ros_schema::<ros2::PointCloud2>(),
        cdr,
        none(),
    );
    let color = out.channel(
        "/kitti/camera_color_left/image_raw",
        "image",
        ros_schema::<ros2::Image>(),
        cdr,
        none(),
    );
    let color_info = out.channel(
        "/kitti/camera_color_left/camera_info",
        "calib",
        ros_schema::<ros2::CameraInfo>(),
        cdr,
        none(),
    );
    let gray = out.channel(
        "/kitti/camera_gray_left/image_raw",
        "image",
        ros_schema::<ros2::Image>(),
        cdr,
        none(),
    );
    let gray_info = out.channel(
        "/kitti/camera_gray_left/camera_info",
        "calib",
        ros_schema::<ros2::CameraInfo>(),
        cdr,
        none(),
    );
    let imu = out.channel(
        "/kitti/imu",
        "other",
        ("sensor_msgs/msg/Imu", "ros2msg", b"std_msgs/Header header"),
        cdr,
        none(),
    );

    let base_from_velo = Isometry3::new(
        Vector3::new(-0.81, 0.32, 0.80),
        Vector3::new(0.0, 0.0, 0.01),
    );
    let base_from_cam = Isometry3::new(
        Vector3::new(0.27, -0.06, 0.72),
        Vector3::new(-1.2, 0.0, -1.2),
    );
    let statics = ros2::TfMessage {
        transforms: vec![
            ros_tf(T0, "base_link", "velodyne", &base_from_velo),
            ros_tf(T0, "base_link", "camera_color_left", &base_from_cam),
            ros_tf(T0, "base_link", "camera_gray_left", &base_from_cam),
        ],
    };
    out.message(tf_static, T0, T0, ros2::encode(&statics).unwrap());
    for n in 0..10 {
        let stamp = T0 + n * 100_000_000;
        let msg = ros2::TfMessage {
            transforms: vec![ros_tf(stamp, "map", "base_link", &map_from_base(stamp))],
        };
        out.message(tf, stamp, stamp, ros2::encode(&msg).unwrap());
        out.message(imu, stamp, stamp, vec![0, 1, 0, 0, 1, 2, 3, 4]);
    }
    // Sweeps 37 ms after each pose: the last one (937 ms) lies after the last pose (900 ms).
    for n in 0..10 {
        let stamp = T0 + n * 100_000_000 + 37_000_000;
        let mut data = Vec::new();
        for p in [[1.0f32, 2.0, 3.0, 0.5], [4.0, 5.0, 6.0, 0.25]] {
            for v in p {
                data.extend_from_slice(&v.to_le_bytes());
            }
        }
        let field = |name: &str, offset| ros2::PointField {
            name: name.into(),
            offset,
            datatype: ros2::PointField::FLOAT32,
            count: 1,
        };
        let cloud = ros2::PointCloud2 {
            header: header(stamp, "velodyne"),
            height: 1,
            width: 2,
            fields: vec![
                field("x", 0),
                field("y", 4),
                field("z", 8),
                field("intensity", 12),
            ],
            is_bigendian: false,
            point_step: 16,
            row_step: 32,
            data,
            is_dense: true,
        };
        out.message(velo, stamp, stamp, ros2::encode(&cloud).unwrap());
        let cam_stamp = stamp + 5_000_000;
        let (w, h) = (4u32, 2u32);
        for (channel, info, frame, encoding, channels) in [
            (color, color_info, "camera_color_left", "rgb8", 3u32),
            (gray, gray_info, "camera_gray_left", "mono8", 1),
        ] {
            let image = ros2::Image {
                header: header(cam_stamp, frame),
                height: h,
                width: w,
                encoding: encoding.into(),
                is_bigendian: 0,
                step: w * channels,
                data: (0..w * h * channels).map(|i| i as u8).collect(),
            };
            out.message(channel, cam_stamp, cam_stamp, ros2::encode(&image).unwrap());
            let calibration = ros2::CameraInfo {
                header: header(cam_stamp, frame),
                height: h,
                width: w,
                distortion_model: "plumb_bob".into(),
                d: vec![0.0; 5],
                k: [721.5, 0.0, 609.6, 0.0, 721.5, 172.9, 0.0, 0.0, 1.0],
                r: [1.0, 0.0, 0.0, 0.0, 1.0, 0.0, 0.0, 0.0, 1.0],
                p: [
                    721.5, 0.0, 609.6, 44.9, 0.0, 721.5, 172.9, 0.0, 0.0, 0.0, 1.0, 0.0,
                ],
                ..Default::default()
            };
            out.message(
                info,
                cam_stamp,
                cam_stamp,
                ros2::encode(&calibration).unwrap(),
            );
        }
    }
    let path = write(out, "ros2", "kitti.mcap");

    let dataset = Drive::open(std::slice::from_ref(&path), &IngestConfig::default()).unwrap();
    let role = |topic: &str| {
        dataset
            .channels
            .iter()
            .find(|c| c.topic == topic)
            .unwrap()
            .role
            .clone()
    };
    assert_eq!(role("/kitti/velodyne_points"), Role::Lidar);
    assert_eq!(role("/kitti/camera_color_left/image_raw"), Role::Image);
    assert_eq!(
        role("/kitti/camera_color_left/camera_info"),
        Role::Calibration
    );
    assert_eq!(role("/tf_static"), Role::StaticTransforms);
    assert!(matches!(role("/kitti/imu"), Role::Ignored(_)));
    let lidar = dataset.lidar.as_ref().unwrap();
    assert_eq!(
        (lidar.frame_id.as_str(), lidar.sweeps.len()),
        ("velodyne", 10)
    );
    let names: Vec<&str> = dataset.cameras.iter().map(|c| c.name.as_str()).collect();
    assert_eq!(names, ["camera_color_left", "camera_gray_left"]);
    let color = &dataset.cameras[0];
    assert_eq!(
        color.calibration_topic.as_deref(),
        Some("/kitti/camera_color_left/camera_info")
    );
    assert_eq!(
        color.calibrations.len(),
        1,
        "identical CameraInfo messages are one calibration"
    );
    assert_eq!(
        color.calibrations[0].k[(0, 2)],
        609.6,
        "K (not P with its baseline) is used"
    );
    assert_eq!(
        (dataset.map_frame.as_deref(), dataset.ego_frame.as_deref()),
        (Some("map"), Some("base_link"))
    );
    dataset.check_sensors().unwrap();

    // Between two OXTS samples the pose is interpolated exactly (constant speed and turn rate).
    for sweep in &lidar.sweeps[..9] {
        let got = dataset.tf.lookup("map", "velodyne", sweep.stamp).unwrap();
        let expected = map_from_base(sweep.stamp.nanos()) * base_from_velo;
        let p = Point3::new(10.0, -3.0, 1.0);
        assert!(
            ((got * p) - (expected * p)).norm() < 1e-9,
            "at {}",
            sweep.stamp
        );
    }
    // The last sweep lies 37 ms after the last pose: within the default 60 ms tolerance it
    // holds the last pose; with a 10 ms tolerance it is a clear error.
    let last = lidar.sweeps[9].stamp;
    assert!(dataset.tf.lookup("map", "velodyne", last).is_ok());
    let strict = IngestConfig {
        tf_tolerance_ms: 10.0,
        ..IngestConfig::default()
    };
    let dataset = Drive::open(&[path], &strict).unwrap();
    let err = dataset
        .tf
        .lookup("map", "velodyne", last)
        .unwrap_err()
        .to_string();
    assert!(
        err.contains("map -> base_link") && err.contains("37.0 ms"),
        "{err}"
    );
    assert_eq!(dataset.keyframes(500_000_000).len(), 2);
}

fn fox_schema<T: Encode>() -> (String, String, Vec<u8>) {
    let schema = T::get_schema().unwrap();
    (schema.name, schema.encoding, schema.data.into_owned())
}

fn fox_stamp(stamp: i64) -> fx::Timestamp {
    let s = Stamp::from_nanos(stamp);
    let (sec, nsec) = s.to_sec_nanosec();
    fx::Timestamp::new(sec as u32, nsec)
}

/// The nuScenes converter since 2026 writes lower-case topics and frame ids; a radar
/// channel with more messages than the LiDAR must not be taken for it.
#[test]
fn lower_case_nuscenes_converter_topics_are_discovered() {
    let mut out = McapOut::default();
    let none = BTreeMap::new;
    let pc = fox_schema::<fx::PointCloud>();
    let ci = fox_schema::<fx::CompressedImage>();
    let cc = fox_schema::<fx::CameraCalibration>();
    let ft = fox_schema::<fx::FrameTransform>();
    let as_ref = |s: &(String, String, Vec<u8>)| (s.0.clone(), s.1.clone(), s.2.clone());
    let (a, b, c) = as_ref(&pc);
    let lidar = out.channel("/lidar_top", "lidar", (&a, &b, &c), "protobuf", none());
    let radar = out.channel("/radar_front", "radar", (&a, &b, &c), "protobuf", none());
    let (a, b, c) = as_ref(&ci);
    let image = out.channel(
        "/cam_front/image_rect_compressed",
        "image",
        (&a, &b, &c),
        "protobuf",
        none(),
    );
    let (a, b, c) = as_ref(&cc);
    let info = out.channel(
        "/cam_front/camera_info",
        "calib",
        (&a, &b, &c),
        "protobuf",
        none(),
    );
    let (a, b, c) = as_ref(&ft);
    let tf = out.channel("/tf", "tf", (&a, &b, &c), "protobuf", none());
    let transform = |stamp, parent: &str, child: &str, x: f64| fx::FrameTransform {
        timestamp: Some(fox_stamp(stamp)),
        parent_frame_id: parent.into(),
        child_frame_id: child.into(),
        translation: Some(foxglove::messages::Vector3 { x, y: 0.0, z: 0.0 }),
        rotation: Some(foxglove::messages::Quaternion {
            x: 0.0,
            y: 0.0,
            z: 0.0,
            w: 1.0,
        }),
    };
    for n in 0..4i64 {
        let stamp = T0 + n * 50_000_000;
        let cloud = fx::PointCloud {
            timestamp: Some(fox_stamp(stamp)),
            frame_id: "lidar_top".into(),
            ..Default::default()
        };
        out.message(lidar, stamp, stamp, cloud.encode_to_vec());
        for k in 0..3 {
            let radar_cloud = fx::PointCloud {
                timestamp: Some(fox_stamp(stamp + k)),
                frame_id: "radar_front".into(),
                ..Default::default()
            };
            out.message(radar, stamp, stamp, radar_cloud.encode_to_vec());
        }
        out.message(
            tf,
            stamp,
            stamp,
            transform(stamp, "map", "base_link", n as f64).encode_to_vec(),
        );
        let cam_stamp = stamp + 10_000_000;
        out.message(
            tf,
            cam_stamp,
            cam_stamp,
            transform(cam_stamp, "map", "base_link", n as f64 + 0.2).encode_to_vec(),
        );
        out.message(
            tf,
            stamp,
            stamp,
            transform(stamp, "base_link", "lidar_top", 0.9).encode_to_vec(),
        );
        out.message(
            tf,
            cam_stamp,
            cam_stamp,
            transform(cam_stamp, "base_link", "cam_front", 1.7).encode_to_vec(),
        );
        let img = fx::CompressedImage {
            timestamp: Some(fox_stamp(cam_stamp)),
            frame_id: "cam_front".into(),
            data: vec![0xFF, 0xD8].into(),
            format: "jpeg".into(),
        };
        out.message(image, stamp, stamp, img.encode_to_vec());
        let calibration = fx::CameraCalibration {
            timestamp: Some(fox_stamp(cam_stamp)),
            frame_id: "cam_front".into(),
            width: 1600,
            height: 900,
            k: vec![1266.4, 0.0, 816.3, 0.0, 1266.4, 491.5, 0.0, 0.0, 1.0],
            ..Default::default()
        };
        out.message(info, stamp, stamp, calibration.encode_to_vec());
    }
    let path = write(out, "", "nuscenes_lower.mcap");
    let dataset = Drive::open(&[path], &IngestConfig::default()).unwrap();
    let lidar = dataset.lidar.as_ref().unwrap();
    assert_eq!(
        (lidar.topic.as_str(), lidar.frame_id.as_str()),
        ("/lidar_top", "lidar_top")
    );
    let role = |topic: &str| {
        dataset
            .channels
            .iter()
            .find(|c| c.topic == topic)
            .unwrap()
            .role
            .clone()
    };
    assert!(matches!(role("/radar_front"), Role::Ignored(_)));
    assert_eq!(dataset.cameras.len(), 1);
    let camera = &dataset.cameras[0];
    assert_eq!(
        (camera.name.as_str(), camera.frame_id.as_str()),
        ("cam_front", "cam_front")
    );
    assert_eq!(
        camera.calibration_topic.as_deref(),
        Some("/cam_front/camera_info")
    );
    // Extrinsics re-published on /tf are frozen into static edges.
    assert!(
        dataset
            .frozen_edges
            .contains(&("base_link".to_string(), "cam_front".to_string()))
    );
    dataset.check_sensors().unwrap();
    // Poses: the stamp of the message is used, never its log time (images here are logged
    // at the LiDAR time, 10 ms before their stamp).
    assert_eq!(camera.frames[0].stamp, Stamp::from_nanos(T0 + 10_000_000));
    // Its JPEGs are cut short: a SLIC sidecar skips every one, counted and named.
    use superflow_pipeline::sample::sidecar::{sidecar_path, write_sidecar};
    let sidecar = sidecar_path(&dataset).unwrap();
    let config = superflow_pipeline::sample::SampleConfig::default();
    let summary = write_sidecar(&dataset, &config, &sidecar, &|| {}).unwrap();
    assert_eq!(
        (summary.images, summary.skipped.len()),
        (0, camera.frames.len())
    );
    let first = &summary.skipped[0];
    assert!(
        first.contains("/cam_front/image_rect_compressed"),
        "{first}"
    );
    std::fs::remove_file(&sidecar).unwrap();
}

/// rosbag2 splits long recordings into several files in one directory next to its
/// `metadata.yaml`: they form one drive (one transform tree, one sweep stream), while
/// separate files given together are separate drives.
#[test]
fn rosbag2_split_directory_is_one_drive() {
    let dir = std::env::temp_dir().join(format!("superflow-split-{}", std::process::id()));
    std::fs::create_dir_all(&dir).unwrap();
    std::fs::write(
        dir.join("metadata.yaml"),
        "rosbag2_bagfile_information:\n  version: 8\n",
    )
    .unwrap();
    for part in 0..2i64 {
        let mut out = McapOut::default();
        let none = BTreeMap::new;
        let cdr = ros2::MESSAGE_ENCODING;
        let tf = out.channel("/tf", "tf", ros_schema::<ros2::TfMessage>(), cdr, none());
        let velo = out.channel(
            "/points",
            "lidar",
            ros_schema::<ros2::PointCloud2>(),
            cdr,
            none(),
        );
        if part == 0 {
            let statics = out.channel(
                "/tf_static",
                "static",
                ros_schema::<ros2::TfMessage>(),
                cdr,
                none(),
            );
            let msg = ros2::TfMessage {
                transforms: vec![ros_tf(T0, "base_link", "lidar", &Isometry3::identity())],
            };
            out.message(statics, T0, T0, ros2::encode(&msg).unwrap());
        }
        for n in part * 5..part * 5 + 5 {
            let stamp = T0 + n * 100_000_000;
            let msg = ros2::TfMessage {
                transforms: vec![ros_tf(stamp, "map", "base_link", &map_from_base(stamp))],
            };
            out.message(tf, stamp, stamp, ros2::encode(&msg).unwrap());
            let cloud = ros2::PointCloud2 {
                header: header(stamp + 50_000_000, "lidar"),
                ..Default::default()
            };
            out.message(velo, stamp, stamp, ros2::encode(&cloud).unwrap());
        }
        let (bytes, _) = out.finish("ros2", Some(mcap::Compression::Zstd)).unwrap();
        std::fs::write(dir.join(format!("drive_{part}.mcap")), bytes).unwrap();
    }
    let dataset = superflow_pipeline::drive::Dataset::open(
        std::slice::from_ref(&dir),
        &IngestConfig::default(),
    )
    .unwrap();
    assert_eq!(dataset.drives.len(), 1);
    let drive = &dataset.drives[0];
    assert_eq!(drive.files.len(), 2);
    let sweeps = &drive.lidar.as_ref().unwrap().sweeps;
    assert_eq!(sweeps.len(), 10);
    assert_eq!((sweeps[4].file, sweeps[5].file), (0, 1));
    // The sweep at 450 ms lies between the last pose of the first file (400 ms) and the
    // first pose of the second (500 ms).
    let stamp = sweeps[4].stamp;
    assert_eq!(stamp, Stamp::from_nanos(T0 + 450_000_000));
    let got = drive.tf.lookup("map", "lidar", stamp).unwrap();
    assert!(
        (got.translation.vector - map_from_base(stamp.nanos()).translation.vector).norm() < 1e-9
    );

    std::fs::remove_file(dir.join("metadata.yaml")).unwrap();
    let dataset =
        superflow_pipeline::drive::Dataset::open(&[dir], &IngestConfig::default()).unwrap();
    assert_eq!(
        dataset.drives.len(),
        2,
        "without metadata.yaml each file is a drive"
    );
}
