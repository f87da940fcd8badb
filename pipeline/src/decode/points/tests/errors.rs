//! Malformed clouds: every error names the frame and stamp.

use super::*;

#[test]
fn truncated_or_padded_data_is_an_error() {
    let mut msg = velodyne(false);
    msg.data.pop();
    let e = decode_ros2(&msg, None).unwrap_err();
    assert!(
        matches!(
            e,
            PointsError::DataLength {
                got: 65,
                expected: 66,
                ..
            }
        ),
        "{e}"
    );
    text(&e, "velodyne");
    let mut msg = velodyne(false);
    msg.data.extend_from_slice(&[0; 22]);
    let e = decode_ros2(&msg, None).unwrap_err();
    assert!(matches!(e, PointsError::DataLength { got: 88, .. }), "{e}");
    // width × height disagreeing with the data.
    let mut msg = velodyne(false);
    msg.width = 2;
    msg.row_step = 44;
    assert!(matches!(
        decode_ros2(&msg, None),
        Err(PointsError::DataLength { .. })
    ));
    // Foxglove: not a multiple of the stride.
    let mut msg = nuscenes([0.0; 3]);
    msg.data = msg.data.slice(..59);
    let e = decode_foxglove(&msg, None).unwrap_err();
    assert!(
        matches!(
            e,
            PointsError::NotMultipleOfStride {
                got: 59,
                point_stride: 20,
                ..
            }
        ),
        "{e}"
    );
    text(&e, "LIDAR_TOP");
}

#[test]
fn row_step_shorter_than_a_row_is_an_error() {
    let mut msg = velodyne(false);
    msg.row_step = 65;
    let e = decode_ros2(&msg, None).unwrap_err();
    assert!(matches!(e, PointsError::RowStepTooShort { .. }), "{e}");
    text(&e, "velodyne");
    // row_step 0 means unpadded rows.
    msg.row_step = 0;
    assert_eq!(decode_ros2(&msg, None).unwrap().cloud.len(), 3);
}

#[test]
fn missing_coordinate_is_an_error() {
    let mut msg = velodyne(false);
    msg.fields.retain(|f| f.name != "z");
    let e = decode_ros2(&msg, None).unwrap_err();
    assert!(
        matches!(e, PointsError::MissingCoordinate { axis: "z", .. }),
        "{e}"
    );
    let s = text(&e, "velodyne");
    assert!(
        s.contains("no `z` field") && s.contains("x, y, intensity, ring, time"),
        "{s}"
    );
    let mut msg = nuscenes([0.0; 3]);
    msg.fields.remove(0);
    let e = decode_foxglove(&msg, None).unwrap_err();
    assert!(
        matches!(e, PointsError::MissingCoordinate { axis: "x", .. }),
        "{e}"
    );
    text(&e, "LIDAR_TOP");
}

#[test]
fn field_past_point_step_is_an_error() {
    let mut msg = velodyne(false);
    msg.fields[5].offset = 19; // a FLOAT32 at 19..23 in a 22-byte point
    let e = decode_ros2(&msg, None).unwrap_err();
    assert!(
        matches!(&e, PointsError::FieldPastPointStep { field, offset: 19, size: 4, point_step: 22, .. } if field == "time"),
        "{e}"
    );
    text(&e, "velodyne");
    let mut msg = velodyne(false);
    msg.fields[0].offset = u32::MAX;
    assert!(matches!(
        decode_ros2(&msg, None),
        Err(PointsError::FieldPastPointStep { .. })
    ));
    let mut msg = nuscenes([0.0; 3]);
    msg.point_stride = 16; // ring at 16..20
    msg.data = msg.data.slice(..48);
    let e = decode_foxglove(&msg, None).unwrap_err();
    assert!(matches!(e, PointsError::FieldPastPointStep { .. }), "{e}");
    text(&e, "LIDAR_TOP");
}

#[test]
fn unknown_datatype_is_an_error_in_used_fields_only() {
    let mut msg = velodyne(false);
    msg.fields[4].datatype = 9;
    let e = decode_ros2(&msg, None).unwrap_err();
    assert!(
        matches!(&e, PointsError::UnknownDatatype { field, datatype: 9, dialect: "ROS PointField", .. } if field == "ring"),
        "{e}"
    );
    text(&e, "velodyne");
    // An unused field may have any datatype.
    let mut msg = velodyne(false);
    msg.fields.push(field("ambient", 0, 0));
    assert!(decode_ros2(&msg, None).is_ok());
    for bad in [0, 9, -1] {
        let mut msg = nuscenes([0.0; 3]);
        msg.fields[1].r#type = bad;
        let e = decode_foxglove(&msg, None).unwrap_err();
        assert!(
            matches!(&e, PointsError::UnknownDatatype { datatype, dialect: "Foxglove NumericType", .. } if *datatype == i64::from(bad)),
            "{e}"
        );
        text(&e, "LIDAR_TOP");
    }
}

#[test]
fn count_other_than_one_is_an_error() {
    for count in [0, 3] {
        let mut msg = velodyne(false);
        msg.fields[0].count = count;
        let e = decode_ros2(&msg, None).unwrap_err();
        assert!(
            matches!(&e, PointsError::FieldCount { field, count: c, .. } if field == "x" && *c == count),
            "{e}"
        );
        text(&e, "velodyne");
    }
}

#[test]
fn bad_ring_values_are_errors_naming_the_value() {
    let e = decode_foxglove(&nuscenes([0.0, 3.5, 1.0]), None).unwrap_err();
    assert!(
        matches!(
            e,
            PointsError::BadRing {
                index: 1,
                value: 3.5,
                ..
            }
        ),
        "{e}"
    );
    assert!(text(&e, "LIDAR_TOP").contains("3.5"));
    for bad in [f32::NAN, -1.0, 65536.0] {
        let e = decode_foxglove(&nuscenes([0.0, 1.0, bad]), None).unwrap_err();
        assert!(matches!(e, PointsError::BadRing { index: 2, .. }), "{e}");
    }
    assert!(decode_foxglove(&nuscenes([0.0, 1.0, 65535.0]), None).is_ok());
    let fields = vec![
        field("x", 0, PointField::FLOAT32),
        field("y", 4, PointField::FLOAT32),
        field("z", 8, PointField::FLOAT32),
        field("laser_id", 12, PointField::UINT32),
    ];
    let data = points(2, 16, false, |i, pt| {
        write_xyz(pt, i);
        pt.u32(12, [1, 70_000][i]);
    });
    let e = decode_ros2(&ros("r32", fields, 16, data), None).unwrap_err();
    assert!(
        matches!(
            e,
            PointsError::BadRing {
                index: 1,
                value: 70_000.0,
                ..
            }
        ),
        "{e}"
    );
    assert!(text(&e, "r32").contains("`laser_id` = 70000"));
}

#[test]
fn non_finite_time_on_a_kept_point_is_an_error() {
    let mut msg = velodyne(false);
    msg.data[22 + 18..22 + 22].copy_from_slice(&f32::NAN.to_le_bytes());
    let e = decode_ros2(&msg, None).unwrap_err();
    assert!(matches!(e, PointsError::BadTime { index: 1, .. }), "{e}");
    text(&e, "velodyne");
    // On a dropped point it does not matter.
    msg.data[22..26].copy_from_slice(&f32::NAN.to_le_bytes());
    let d = decode_ros2(&msg, None).unwrap();
    assert_eq!((d.cloud.len(), d.dropped_non_finite), (2, 1));
}

#[test]
fn foxglove_without_timestamp_is_an_error() {
    let mut msg = nuscenes([0.0; 3]);
    msg.timestamp = None;
    let e = decode_foxglove(&msg, None).unwrap_err();
    assert!(matches!(e, PointsError::MissingTimestamp { .. }), "{e}");
    assert!(e.to_string().contains("`LIDAR_TOP`"));
}

#[test]
fn empty_clouds_decode_to_no_points() {
    let mut msg = velodyne(false);
    msg.width = 0;
    msg.row_step = 0;
    msg.data.clear();
    let d = decode_ros2(&msg, None).unwrap();
    assert!(d.cloud.is_empty());
    assert_eq!(d.cloud.ring, Some(vec![]));
    msg.height = u32::MAX; // zero-width rows: nothing to visit
    assert!(decode_ros2(&msg, None).unwrap().cloud.is_empty());
    let mut msg = nuscenes([0.0; 3]);
    msg.data = Default::default();
    assert!(decode_foxglove(&msg, None).unwrap().cloud.is_empty());
}
