//! Per-point time: absolute fields (Hesai, Livox) and their unit by magnitude, and a
//! `TimeFieldSpec` overriding the inference.

use super::*;

#[test]
fn hesai_absolute_float64_timestamp() {
    let fields = vec![
        field("x", 0, PointField::FLOAT32),
        field("y", 4, PointField::FLOAT32),
        field("z", 8, PointField::FLOAT32),
        field("intensity", 16, PointField::FLOAT32),
        field("timestamp", 24, PointField::FLOAT64),
        field("ring", 32, PointField::UINT16),
    ];
    let base = f64::from(SEC);
    let data = points(4, 48, false, |i, pt| {
        if i == 3 {
            // A no-return point with a zero time must not flip the inference.
            pt.f32(0, f32::NAN)
                .f32(4, f32::NAN)
                .f32(8, f32::NAN)
                .f64(24, 0.0)
                .u16(32, 1);
            return;
        }
        write_xyz(pt, i);
        pt.f32(16, [5.0, 6.0, 7.0][i])
            .f64(24, base + [0.125, 0.1875, 0.0625][i])
            .u16(32, [1, 2, 3][i]);
    });
    let d = decode_ros2(&ros("hesai_lidar", fields, 48, data), None).unwrap();
    check(
        &d,
        "hesai_lidar",
        &XYZ3,
        &[5.0, 6.0, 7.0],
        Some(&[1, 2, 3]),
        Some(&[0.0, 0.0625, -0.0625]),
    );
    assert_eq!(d.dropped_non_finite, 1);
    assert_eq!(
        d.time_field,
        Some(spec(
            "timestamp",
            TimeUnit::Seconds,
            TimeReference::Absolute
        ))
    );
}

#[test]
fn livox_absolute_nanoseconds_and_offset_time() {
    // livox_ros_driver2: FLOAT64 `timestamp` in ns since the epoch, UINT8 `line`.
    let fields = vec![
        field("x", 0, PointField::FLOAT32),
        field("y", 4, PointField::FLOAT32),
        field("z", 8, PointField::FLOAT32),
        field("intensity", 12, PointField::FLOAT32),
        field("tag", 16, PointField::UINT8),
        field("line", 17, PointField::UINT8),
        field("timestamp", 18, PointField::FLOAT64),
    ];
    let stamp_ns = stamp().nanos() as f64;
    let data = points(3, 26, false, |i, pt| {
        write_xyz(pt, i);
        pt.f32(12, 10.0)
            .u8(16, 0x10)
            .u8(17, [0, 3, 5][i])
            .f64(18, stamp_ns + [0.0, 1_048_576.0, -2048.0][i]);
    });
    let d = decode_ros2(&ros("livox_frame", fields, 26, data), None).unwrap();
    check(
        &d,
        "livox_frame",
        &XYZ3,
        &[10.0; 3],
        Some(&[0, 3, 5]),
        Some(&[0.0, (1_048_576.0 / 1e9) as f32, (-2048.0 / 1e9) as f32]),
    );
    assert_eq!(
        d.time_field,
        Some(spec(
            "timestamp",
            TimeUnit::Nanoseconds,
            TimeReference::Absolute
        ))
    );

    // Livox custom points converted to PointCloud2: UINT32 `offset_time` in ns.
    let fields = vec![
        field("x", 0, PointField::FLOAT32),
        field("y", 4, PointField::FLOAT32),
        field("z", 8, PointField::FLOAT32),
        field("reflectivity", 12, PointField::UINT8),
        field("offset_time", 13, PointField::UINT32),
    ];
    let data = points(3, 17, false, |i, pt| {
        write_xyz(pt, i);
        pt.u8(12, [1, 2, 3][i])
            .u32(13, [0, 500_000, 100_000_000][i]);
    });
    let d = decode_ros2(&ros("livox", fields, 17, data), None).unwrap();
    check(
        &d,
        "livox",
        &XYZ3,
        &[1.0, 2.0, 3.0],
        None,
        Some(&[0.0, 0.0005, 0.1]),
    );
    assert_eq!(
        d.time_field,
        Some(spec(
            "offset_time",
            TimeUnit::Nanoseconds,
            TimeReference::RelativeToStamp
        ))
    );
}

#[test]
fn absolute_microseconds_and_seconds_are_inferred_from_magnitude() {
    let cloud = |name: &str, values: [f64; 2]| {
        let fields = vec![
            field("x", 0, PointField::FLOAT32),
            field("y", 4, PointField::FLOAT32),
            field("z", 8, PointField::FLOAT32),
            field(name, 12, PointField::FLOAT64),
        ];
        let data = points(2, 20, false, |i, pt| {
            write_xyz(pt, i);
            pt.f64(12, values[i]);
        });
        ros("abs", fields, 20, data)
    };
    let us = stamp().nanos() as f64 / 1e3; // 1.700000000125e15, exact
    let d = decode_ros2(&cloud("time", [us, us + 250.0]), None).unwrap();
    assert_eq!(d.cloud.time_offset_secs, Some(vec![0.0, 0.00025]));
    assert_eq!(
        d.time_field,
        Some(spec(
            "time",
            TimeUnit::Microseconds,
            TimeReference::Absolute
        ))
    );
    let s = f64::from(SEC);
    let d = decode_ros2(&cloud("time_offset", [s, s + 0.5]), None).unwrap();
    assert_eq!(d.cloud.time_offset_secs, Some(vec![-0.125, 0.375]));
    assert_eq!(
        d.time_field,
        Some(spec(
            "time_offset",
            TimeUnit::Seconds,
            TimeReference::Absolute
        ))
    );
}

#[test]
fn time_field_spec_overrides_the_inference() {
    let msg = velodyne(false);
    // Read `time` as microseconds instead of seconds.
    let us = spec(
        "time",
        TimeUnit::Microseconds,
        TimeReference::RelativeToStamp,
    );
    let d = decode_ros2(&msg, Some(&us)).unwrap();
    assert_eq!(
        d.cloud.time_offset_secs,
        Some(vec![0.0, (0.03125 / 1e6) as f32, (0.0625 / 1e6) as f32])
    );
    assert_eq!(d.time_field, Some(us));
    // Any field can be named, even one the inference would not pick.
    let ring = spec("ring", TimeUnit::Seconds, TimeReference::RelativeToStamp);
    let d = decode_ros2(&msg, Some(&ring)).unwrap();
    assert_eq!(d.cloud.time_offset_secs, Some(vec![5.0, 15.0, 0.0]));
    // An absolute spec on an integer field of whole seconds.
    let fields = vec![
        field("x", 0, PointField::FLOAT32),
        field("y", 4, PointField::FLOAT32),
        field("z", 8, PointField::FLOAT32),
        field("stamp_s", 12, PointField::UINT32),
    ];
    let data = points(2, 16, false, |i, pt| {
        write_xyz(pt, i);
        pt.u32(12, SEC as u32 + i as u32);
    });
    let abs = spec("stamp_s", TimeUnit::Seconds, TimeReference::Absolute);
    let d = decode_ros2(&ros("s", fields, 16, data), Some(&abs)).unwrap();
    assert_eq!(d.cloud.time_offset_secs, Some(vec![-0.125, 0.875]));
    // A spec naming an absent field is an error.
    let missing = spec("stamp", TimeUnit::Seconds, TimeReference::Absolute);
    let e = decode_ros2(&msg, Some(&missing)).unwrap_err();
    assert!(matches!(e, PointsError::MissingTimeField { .. }), "{e}");
    assert!(text(&e, "velodyne").contains("`stamp`"));
    let e = decode_foxglove(&nuscenes([0.0; 3]), Some(&missing)).unwrap_err();
    assert!(matches!(e, PointsError::MissingTimeField { .. }), "{e}");
}
