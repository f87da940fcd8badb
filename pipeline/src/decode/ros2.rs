//! ROS 2 messages into the sensor model: `/tf` transforms ([`transforms`]) and camera
//! calibrations ([`camera_info`]). Clouds and images are converted in
//! [`super::points`] and [`super::image`].
//!
//! The messages themselves (serde mirrors, schema names and `ros2msg` texts, the CDR
//! codec and [`CdrError`]) live in [`superflow_schemas::ros2`], shared with the
//! recording generator; they are re-exported here so `decode::ros2::PointCloud2`,
//! `decode::ros2::decode`, ... keep working. `Ros2Time::stamp` (a [`Ros2Time`] as a
//! `Stamp`) is defined there too.

pub use superflow_schemas::ros2::*;

use superflow_schemas::sensor::{CameraCalibration, StampedTransform};

use super::calibration::calibration;
use super::error::DecodeError;
use super::transform::isometry;

/// The transforms of a `tf2_msgs/msg/TFMessage`, each as `parent_from_child`
/// (`header.frame_id` is the parent). `is_static` is true for `/tf_static`.
pub fn transforms(msg: &TfMessage, is_static: bool) -> Vec<Result<StampedTransform, DecodeError>> {
    msg.transforms
        .iter()
        .map(|t| {
            let stamp = t.header.stamp.stamp();
            let tr = &t.transform.translation;
            let q = &t.transform.rotation;
            Ok(StampedTransform {
                stamp,
                parent_frame: t.header.frame_id.clone(),
                child_frame: t.child_frame_id.clone(),
                parent_from_child: isometry(
                    stamp,
                    &t.header.frame_id,
                    &t.child_frame_id,
                    [tr.x, tr.y, tr.z],
                    [q.x, q.y, q.z, q.w],
                )?,
                is_static,
            })
        })
        .collect()
}

/// A `sensor_msgs/msg/CameraInfo` as the intrinsics of the raw image: `k` and `d` with
/// its distortion model (`p` describes the rectified image and is not used).
pub fn camera_info(msg: &CameraInfo) -> Result<CameraCalibration, DecodeError> {
    calibration(
        msg.header.stamp.stamp(),
        &msg.header.frame_id,
        (msg.width, msg.height),
        &msg.k,
        &msg.distortion_model,
        &msg.d,
    )
}

#[cfg(test)]
mod tests {
    use superflow_schemas::Stamp;
    use superflow_schemas::sensor::Distortion;

    use super::*;

    fn header(frame_id: &str) -> Header {
        Header {
            stamp: Ros2Time { sec: 7, nanosec: 8 },
            frame_id: frame_id.to_owned(),
        }
    }

    #[test]
    fn transforms_are_parent_from_child_and_reject_zero_quaternions() {
        let good = TransformStamped {
            header: header("map"),
            child_frame_id: "base_link".to_owned(),
            transform: Transform {
                translation: Vector3 {
                    x: 1.0,
                    y: 2.0,
                    z: 3.0,
                },
                rotation: Quaternion::default(),
            },
        };
        let mut zero = good.clone();
        zero.transform.rotation.w = 0.0;
        let out = transforms(
            &TfMessage {
                transforms: vec![good, zero],
            },
            true,
        );
        let first = out[0].as_ref().unwrap();
        assert_eq!(first.stamp, Stamp::from_nanos(7_000_000_008));
        assert_eq!(first.parent_frame, "map");
        assert_eq!(first.child_frame, "base_link");
        assert!(first.is_static);
        let t = first.parent_from_child.translation.vector;
        assert_eq!([t.x, t.y, t.z], [1.0, 2.0, 3.0]);
        let err = out[1].as_ref().unwrap_err().to_string();
        assert!(err.contains("zero quaternion"), "{err}");
        assert!(err.contains("map -> base_link"), "{err}");
    }

    #[test]
    fn camera_info_takes_k_and_d_of_the_raw_image() {
        let info = CameraInfo {
            header: header("cam_front_optical_frame"),
            height: 900,
            width: 1600,
            distortion_model: "plumb_bob".to_owned(),
            d: vec![-0.1, 0.01, 0.001, -0.002, 0.0],
            k: [1266.4, 0.0, 816.3, 0.0, 1266.4, 491.5, 0.0, 0.0, 1.0],
            ..Default::default()
        };
        let calibration = camera_info(&info).unwrap();
        assert_eq!(calibration.stamp, Stamp::from_nanos(7_000_000_008));
        assert_eq!(calibration.frame_id, "cam_front_optical_frame");
        assert_eq!((calibration.width, calibration.height), (1600, 900));
        assert_eq!(calibration.k[(0, 2)], 816.3);
        assert_eq!(calibration.k[(1, 2)], 491.5);
        assert!(matches!(
            calibration.distortion,
            Distortion::PlumbBob { coeffs } if coeffs[0] == -0.1
        ));
        let err = camera_info(&CameraInfo { width: 0, ..info })
            .unwrap_err()
            .to_string();
        assert!(err.contains("cam_front_optical_frame"), "{err}");
    }
}
