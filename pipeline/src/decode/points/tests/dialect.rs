//! `decode_message`: dispatch on the channel's schema and encoding.

use super::*;

#[test]
fn decode_message_dispatches_on_the_schema() {
    let msg = velodyne(false);
    let bytes = ros2::encode(&msg).unwrap();
    let ch = channel("/points", ros2::POINT_CLOUD2, "cdr");
    let d = decode_message(&message(&ch, &bytes), None).unwrap();
    assert_eq!(d, decode_ros2(&msg, None).unwrap());
    let e = decode_message(&message(&ch, &bytes[..10]), None).unwrap_err();
    assert!(matches!(e, PointsError::Message { .. }), "{e}");
    assert!(e.to_string().starts_with("`/points`: "), "{e}");
    let fox_ch = channel("/LIDAR_TOP", "foxglove.PointCloud", "protobuf");
    let e = decode_message(&message(&fox_ch, &[0xFF, 0xFF]), None).unwrap_err();
    assert!(matches!(e, PointsError::Message { .. }), "{e}");
    let image = channel("/cam", ros2::IMAGE, "cdr");
    let e = decode_message(&message(&image, &bytes), None).unwrap_err();
    assert!(matches!(e, PointsError::NotAPointCloud { .. }), "{e}");
    let json = channel("/points", ros2::POINT_CLOUD2, "json");
    assert!(matches!(
        decode_message(&message(&json, &bytes), None),
        Err(PointsError::NotAPointCloud { .. })
    ));
}
