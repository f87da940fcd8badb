//! The committed sample drives decode with the `mcap` crate to exactly what their ground
//! truth states, and their geometry reproduces the truth's landmark pixels.

#![allow(clippy::unwrap_used, clippy::expect_used)] // tests fail loudly on purpose

use ::foxglove::messages::packed_element_field::NumericType;
use nalgebra::Point3;
use std::collections::BTreeMap;
use superflow_pipeline::decode::{foxglove, ros2};
use superflow_recordings::Dialect;
use superflow_schemas::Stamp;
use superflow_tests::{SampleDrive, calibrations, sample_drive, transform_tree};

fn drives() -> Vec<SampleDrive> {
    Dialect::ALL
        .iter()
        .map(|d| sample_drive(*d).expect("sample drive present"))
        .collect()
}

#[test]
fn header_channels_schemas_and_counts_match_the_truth() {
    for drive in drives() {
        let truth = &drive.truth;
        let mut reader = mcap::read::LinearReader::new(&drive.bytes).unwrap();
        match reader.next() {
            Some(Ok(mcap::records::Record::Header(header))) => {
                assert_eq!(header.profile, truth.profile, "{}", drive.path.display());
            }
            other => panic!("first record is not a header: {other:?}"),
        }
        let summary = mcap::Summary::read(&drive.bytes)
            .unwrap()
            .expect("summary section");
        let mut found: BTreeMap<String, (String, String, String)> = BTreeMap::new();
        for channel in summary.channels.values() {
            let schema = channel.schema.as_ref().expect("every channel has a schema");
            found.insert(
                channel.topic.clone(),
                (
                    schema.name.clone(),
                    schema.encoding.clone(),
                    channel.message_encoding.clone(),
                ),
            );
        }
        let expected: BTreeMap<String, (String, String, String)> = truth
            .channels
            .iter()
            .map(|c| {
                (
                    c.topic.clone(),
                    (
                        c.schema_name.clone(),
                        c.schema_encoding.clone(),
                        c.message_encoding.clone(),
                    ),
                )
            })
            .collect();
        assert_eq!(found, expected, "{}", drive.path.display());

        let mut counts: BTreeMap<String, u64> = BTreeMap::new();
        for message in mcap::MessageStream::new(&drive.bytes).unwrap() {
            *counts
                .entry(message.unwrap().channel.topic.clone())
                .or_default() += 1;
        }
        for channel in &truth.channels {
            assert_eq!(
                counts.get(&channel.topic).copied().unwrap_or(0),
                channel.message_count,
                "{}: {}",
                drive.path.display(),
                channel.topic
            );
        }
        let stats = summary.stats.expect("statistics");
        assert_eq!(stats.message_count, counts.values().sum::<u64>());
        // 60 sweeps at 20 Hz and 36 images per camera at ~12 Hz over 3 s.
        assert_eq!(truth.lidar.sweeps.len(), 60);
        assert!(truth.cameras.iter().all(|c| c.stamps_nanos.len() == 36));
        assert_eq!(truth.cameras.len(), 6);
    }
}

#[test]
fn lidar_sweeps_carry_the_truth_stamps_and_point_counts() {
    for drive in drives() {
        let lidar = &drive.truth.lidar;
        let mut sweeps = Vec::new();
        for message in mcap::MessageStream::new(&drive.bytes).unwrap() {
            let message = message.unwrap();
            if message.channel.topic != lidar.topic {
                continue;
            }
            let (stamp, points, finite) = match drive.dialect {
                Dialect::Foxglove => {
                    let cloud: foxglove::PointCloud =
                        foxglove::decode("foxglove.PointCloud", &message.data).unwrap();
                    assert_eq!(cloud.frame_id, lidar.frame_id);
                    // Every FLOAT32 field of every point (the `label` field is UINT8).
                    let float_offsets: Vec<usize> = cloud
                        .fields
                        .iter()
                        .filter(|f| f.r#type == NumericType::Float32 as i32)
                        .map(|f| f.offset as usize)
                        .collect();
                    assert!(float_offsets.len() >= 3);
                    let floats: Vec<f32> = cloud
                        .data
                        .chunks_exact(cloud.point_stride as usize)
                        .flat_map(|p| {
                            float_offsets.iter().map(move |&o| {
                                f32::from_le_bytes([p[o], p[o + 1], p[o + 2], p[o + 3]])
                            })
                        })
                        .collect();
                    (
                        foxglove::stamp("foxglove.PointCloud", cloud.timestamp.as_ref()).unwrap(),
                        cloud.data.len() as u64 / u64::from(cloud.point_stride),
                        floats.iter().all(|v| v.is_finite()),
                    )
                }
                Dialect::Ros2 => {
                    let cloud: ros2::PointCloud2 = ros2::decode(&message.data).unwrap();
                    assert_eq!(cloud.header.frame_id, lidar.frame_id);
                    assert_eq!(cloud.data.len() as u32, cloud.point_step * cloud.width);
                    let finite = cloud.data.chunks_exact(cloud.point_step as usize).all(|p| {
                        (0..3).all(|i| {
                            f32::from_le_bytes([p[4 * i], p[4 * i + 1], p[4 * i + 2], p[4 * i + 3]])
                                .is_finite()
                        })
                    });
                    (
                        cloud.header.stamp.stamp(),
                        u64::from(cloud.width * cloud.height),
                        finite,
                    )
                }
            };
            assert!(finite, "non-finite point in {}", drive.path.display());
            sweeps.push((stamp.nanos(), points));
        }
        let expected: Vec<(i64, u64)> = lidar
            .sweeps
            .iter()
            .map(|s| (s.stamp_nanos, s.points))
            .collect();
        assert_eq!(sweeps, expected, "{}", drive.path.display());
        // A 16 x 300 scan of a street returns most rays.
        assert!(
            expected.iter().all(|(_, n)| (3_000..=4_800).contains(n)),
            "{expected:?}"
        );
    }
}

#[test]
fn calibrations_match_the_truth() {
    for drive in drives() {
        let calibrations = calibrations(&drive).unwrap();
        for camera in &drive.truth.cameras {
            let calibration = &calibrations[&camera.calibration_topic];
            assert_eq!(calibration.frame_id, camera.frame_id);
            assert_eq!(
                (calibration.width, calibration.height),
                (camera.width, camera.height)
            );
            let k: Vec<f64> = calibration.k.transpose().iter().copied().collect();
            assert_eq!(k, camera.k);
            assert_eq!(calibration.distortion.model_name(), camera.distortion_model);
            assert_eq!(calibration.distortion.coeffs(), camera.d);
        }
    }
}

#[test]
fn recorded_transforms_reproduce_the_truth_poses_and_extrinsics() {
    for drive in drives() {
        let truth = &drive.truth;
        let tree = transform_tree(&drive).unwrap();
        // The Foxglove drive records the ego pose at every sensor stamp: lookups there are
        // exact. The ROS 2 drive records odom -> base_link at 50 Hz and map -> odom at
        // 10 Hz, so camera and LiDAR stamps fall between samples: linear interpolation of
        // the weave (yaw'' <= 0.21 rad/s^2, lateral accel <= 1.7 m/s^2) over 20 ms is off
        // by at most 0.21 * 0.02^2 / 8 = 1.1e-5 rad and 1.7 * 0.02^2 / 8 = 85 um.
        let (max_m, max_rad) = match drive.dialect {
            Dialect::Foxglove => (1e-9, 1e-9),
            Dialect::Ros2 => (1e-4, 1.2e-5),
        };
        for sample in &truth.ego_poses {
            let expected = sample.map_from_ego.isometry();
            let got = tree
                .lookup(
                    &truth.frames.map,
                    &truth.frames.ego,
                    Stamp::from_nanos(sample.stamp_nanos),
                )
                .unwrap();
            let dt = (got.translation.vector - expected.translation.vector).norm();
            let dr = got.rotation.angle_to(&expected.rotation);
            assert!(
                dt < max_m && dr < max_rad,
                "{} at {}: {dt} m, {dr} rad",
                drive.path.display(),
                sample.stamp_nanos
            );
        }
        let any = Stamp::from_nanos(truth.start_stamp_nanos + 1_000_000_000);
        let ego_from_lidar = tree
            .lookup(&truth.frames.ego, &truth.frames.lidar, any)
            .unwrap();
        let expected = truth.lidar.ego_from_lidar.isometry();
        assert!((ego_from_lidar.to_homogeneous() - expected.to_homogeneous()).norm() < 1e-9);
        for camera in &truth.cameras {
            let got = tree
                .lookup(&truth.frames.ego, &camera.frame_id, any)
                .unwrap();
            let expected = camera.ego_from_camera.isometry();
            assert!(
                (got.to_homogeneous() - expected.to_homogeneous()).norm() < 1e-9,
                "{}: {}",
                drive.path.display(),
                camera.name
            );
        }
    }
}

/// Each landmark of the ground truth, projected with the calibration and the transforms
/// decoded from the recording (ego pose interpolated at the camera stamp), lands within
/// 0.5 px of the pixel the ground truth states.
#[test]
fn landmarks_project_to_their_truth_pixels() {
    for drive in drives() {
        let truth = &drive.truth;
        let tree = transform_tree(&drive).unwrap();
        let calibrations = calibrations(&drive).unwrap();
        let mut checked = 0;
        let mut cameras_seen = std::collections::BTreeSet::new();
        for landmark in &truth.landmarks {
            let [x, y, z] = landmark.point_in_map;
            for obs in &landmark.observations {
                let camera = truth.cameras.iter().find(|c| c.name == obs.camera).unwrap();
                let calibration = &calibrations[&camera.calibration_topic];
                let camera_from_map = tree
                    .lookup(
                        &camera.frame_id,
                        &truth.frames.map,
                        Stamp::from_nanos(obs.stamp_nanos),
                    )
                    .unwrap();
                let in_camera = camera_from_map * Point3::new(x, y, z);
                let pixel = calibration.project(&in_camera).unwrap();
                let error =
                    ((pixel.x - obs.pixel[0]).powi(2) + (pixel.y - obs.pixel[1]).powi(2)).sqrt();
                assert!(
                    error < 0.5,
                    "{} {} in {}: projected {pixel:?}, truth {:?} ({error:.3} px)",
                    drive.path.display(),
                    landmark.name,
                    obs.camera,
                    obs.pixel
                );
                assert!((in_camera.z - obs.depth).abs() < 0.01);
                checked += 1;
                cameras_seen.insert(obs.camera.clone());
            }
        }
        assert!(checked >= 12, "only {checked} observations");
        assert_eq!(
            cameras_seen.len(),
            truth.cameras.len(),
            "every camera has a landmark"
        );
    }
}

/// Every camera's images and class maps decode to the calibrated size; class ids are
/// below the class count; the front camera sees road at the bottom centre.
#[test]
fn images_and_class_maps_decode_to_the_truth_sizes() {
    use superflow_pipeline::decode::image::Target;
    use superflow_pipeline::source::ChunkCache;
    use superflow_schemas::sensor::PixelFormat;
    for drive in drives() {
        let dataset = superflow_tests::dataset(&drive).unwrap();
        let classes = drive.truth.classes.len() as u8;
        let mut cache = ChunkCache::new(4);
        assert_eq!(dataset.cameras.len(), drive.truth.cameras.len());
        for camera in &dataset.cameras {
            let truth = drive
                .truth
                .cameras
                .iter()
                .find(|c| c.image_topic == camera.image_topic)
                .unwrap();
            assert_eq!(camera.frames.len(), truth.stamps_nanos.len());
            assert_eq!(camera.superpixels.len(), truth.stamps_nanos.len());
            for i in [0, camera.frames.len() / 2, camera.frames.len() - 1] {
                let image = dataset
                    .read_image(camera, &camera.frames[i], Target::Rgb, &mut cache)
                    .unwrap();
                assert_eq!(
                    (image.width, image.height, image.format),
                    (truth.width, truth.height, PixelFormat::Rgb8)
                );
                assert_eq!(image.stamp.nanos(), truth.stamps_nanos[i]);
                assert_eq!(image.frame_id, truth.frame_id);
                let map = dataset
                    .read_image(camera, &camera.superpixels[i], Target::Mono, &mut cache)
                    .unwrap();
                assert_eq!(
                    (map.width, map.height, map.format),
                    (truth.width, truth.height, PixelFormat::Mono8)
                );
                assert_eq!(
                    map.stamp, image.stamp,
                    "class map and image share the stamp"
                );
                assert!(map.data.iter().all(|c| *c < classes));
                if truth.name == "CAM_FRONT" {
                    let bottom_centre = map.pixel(truth.width / 2, truth.height - 2).unwrap()[0];
                    assert_eq!(
                        drive.truth.classes[bottom_centre as usize],
                        "driveable_surface"
                    );
                    // Road is grey in the image: the three channels are close.
                    let rgb = image.pixel(truth.width / 2, truth.height - 2).unwrap();
                    let spread = rgb.iter().max().unwrap() - rgb.iter().min().unwrap();
                    assert!(spread < 20, "{rgb:?}");
                }
            }
        }
    }
}

/// Every sweep decodes (through the pipeline's field-layout decoder) to the truth's point
/// count; the Foxglove sweeps are in LIDAR_TOP at the sweep end, the ROS 2 ones carry the
/// per-point time over one 50 ms revolution.
#[test]
fn sweeps_decode_to_the_truth_point_counts() {
    use superflow_pipeline::source::ChunkCache;
    for drive in drives() {
        let dataset = superflow_tests::dataset(&drive).unwrap();
        let lidar = dataset.lidar.as_ref().unwrap();
        let mut cache = ChunkCache::new(2);
        for (sweep, truth) in lidar.sweeps.iter().zip(&drive.truth.lidar.sweeps) {
            let decoded = dataset.read_sweep(sweep, &mut cache).unwrap();
            assert_eq!(decoded.cloud.len() as u64, truth.points);
            assert_eq!(decoded.dropped_non_finite, 0);
            assert!(decoded.has_intensity);
            assert_eq!(decoded.cloud.stamp.nanos(), truth.stamp_nanos);
            assert_eq!(decoded.cloud.frame_id, drive.truth.lidar.frame_id);
            let rings = decoded.cloud.ring.as_ref().unwrap();
            assert!(rings.iter().all(|r| *r < drive.truth.lidar.beams as u16));
            // Everything the 70 m LiDAR returns lies within range of the sensor.
            assert!(
                decoded
                    .cloud
                    .xyz
                    .iter()
                    .all(|p| (p[0] * p[0] + p[1] * p[1] + p[2] * p[2]).sqrt() < 71.0)
            );
            match drive.dialect {
                Dialect::Foxglove => assert!(decoded.cloud.time_offset_secs.is_none()),
                Dialect::Ros2 => {
                    let time = decoded.cloud.time_offset_secs.as_ref().unwrap();
                    let (lo, hi) = time
                        .iter()
                        .fold((f32::MAX, f32::MIN), |(a, b), t| (a.min(*t), b.max(*t)));
                    assert!(lo >= 0.0 && hi < 0.05 && hi > 0.045, "{lo}..{hi}");
                }
            }
        }
    }
}
