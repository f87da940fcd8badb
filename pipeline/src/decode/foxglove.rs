//! Foxglove protobuf messages (schemas `foxglove.*`, encoding `protobuf`), as written by
//! the nuScenes converter and the Foxglove SDK. The message types are the Foxglove SDK's
//! own generated protobuf types; this module converts them into the sensor model.

use super::calibration::calibration;
use super::error::DecodeError;
use super::transform::isometry;
pub use foxglove::messages::{
    CameraCalibration, CompressedImage, FrameTransform, FrameTransforms, PointCloud, RawImage,
    Timestamp,
};
use superflow_schemas::Stamp;
use superflow_schemas::sensor::{self, StampedTransform};

/// Decodes a protobuf payload as message type `T`.
pub fn decode<T: prost::Message + Default>(
    schema: &'static str,
    bytes: &[u8],
) -> Result<T, DecodeError> {
    T::decode(bytes).map_err(|source| DecodeError::Protobuf { schema, source })
}

/// The sensor stamp of a message (`timestamp` field).
pub fn stamp(schema: &'static str, timestamp: Option<&Timestamp>) -> Result<Stamp, DecodeError> {
    let t = timestamp.ok_or(DecodeError::MissingField {
        schema,
        field: "timestamp",
    })?;
    Ok(Stamp::from_sec_nanosec(i64::from(t.sec()), t.nsec()))
}

/// A `foxglove.FrameTransform` as `parent_from_child`.
pub fn frame_transform(
    msg: &FrameTransform,
    is_static: bool,
) -> Result<StampedTransform, DecodeError> {
    const SCHEMA: &str = "foxglove.FrameTransform";
    let stamp = stamp(SCHEMA, msg.timestamp.as_ref())?;
    let t = msg.translation.unwrap_or_default();
    // An absent rotation is the identity, as in the Foxglove app.
    let q = msg
        .rotation
        .map_or([0.0, 0.0, 0.0, 1.0], |q| [q.x, q.y, q.z, q.w]);
    Ok(StampedTransform {
        stamp,
        parent_frame: msg.parent_frame_id.clone(),
        child_frame: msg.child_frame_id.clone(),
        parent_from_child: isometry(
            stamp,
            &msg.parent_frame_id,
            &msg.child_frame_id,
            [t.x, t.y, t.z],
            q,
        )?,
        is_static,
    })
}

/// A `foxglove.CameraCalibration` as the intrinsics of the raw image (`K`, `D`).
pub fn camera_calibration(
    msg: &CameraCalibration,
) -> Result<sensor::CameraCalibration, DecodeError> {
    const SCHEMA: &str = "foxglove.CameraCalibration";
    let stamp = stamp(SCHEMA, msg.timestamp.as_ref())?;
    calibration(
        stamp,
        &msg.frame_id,
        (msg.width, msg.height),
        &msg.k,
        &msg.distortion_model,
        &msg.d,
    )
}

#[cfg(test)]
mod tests {
    use super::*;
    use foxglove::messages::{Quaternion, Vector3};
    use prost::Message as _;

    #[test]
    fn frame_transform_round_trips_through_protobuf() {
        let msg = FrameTransform {
            timestamp: Some(Timestamp::new(1_700_000_000, 5)),
            parent_frame_id: "map".into(),
            child_frame_id: "base_link".into(),
            translation: Some(Vector3 {
                x: 1.0,
                y: 2.0,
                z: 3.0,
            }),
            rotation: Some(Quaternion {
                x: 0.0,
                y: 0.0,
                z: 2f64.sqrt() / 2.0,
                w: 2f64.sqrt() / 2.0,
            }),
        };
        let bytes = msg.encode_to_vec();
        let back: FrameTransform = decode("foxglove.FrameTransform", &bytes).unwrap();
        let tf = frame_transform(&back, false).unwrap();
        assert_eq!(tf.stamp, Stamp::from_nanos(1_700_000_000_000_000_005));
        // parent_from_child maps child x onto parent y (90° yaw), then translates.
        let p = tf.parent_from_child * nalgebra::Point3::new(1.0, 0.0, 0.0);
        assert!((p - nalgebra::Point3::new(1.0, 3.0, 3.0)).norm() < 1e-12);
        assert!(decode::<FrameTransform>("foxglove.FrameTransform", &[0xFF, 0xFF]).is_err());
    }

    #[test]
    fn bad_transforms_and_calibrations_are_errors() {
        let mut msg = FrameTransform {
            timestamp: Some(Timestamp::new(1, 0)),
            parent_frame_id: "a".into(),
            child_frame_id: "b".into(),
            translation: None,
            rotation: Some(Quaternion::default()),
        };
        let err = frame_transform(&msg, false).unwrap_err().to_string();
        assert!(
            err.contains("a -> b") && err.contains("zero quaternion"),
            "{err}"
        );
        msg.timestamp = None;
        assert!(matches!(
            frame_transform(&msg, false),
            Err(DecodeError::MissingField { .. })
        ));
        let calibration = CameraCalibration {
            timestamp: Some(Timestamp::new(1, 0)),
            frame_id: "CAM_FRONT".into(),
            width: 100,
            height: 50,
            k: vec![1.0; 4],
            ..Default::default()
        };
        let err = camera_calibration(&calibration).unwrap_err().to_string();
        assert!(
            err.contains("CAM_FRONT") && err.contains("K has 4 entries"),
            "{err}"
        );
    }
}
