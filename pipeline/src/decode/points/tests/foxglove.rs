//! Foxglove clouds: the nuScenes layout, the Foxglove numbering of element types, and
//! the cloud pose.

use super::*;

#[test]
fn nuscenes_foxglove_all_float32() {
    let msg = nuscenes([0.0, 17.0, 31.0]);
    let d = decode_foxglove(&msg, None).unwrap();
    check(
        &d,
        "LIDAR_TOP",
        &XYZ3,
        &[3.0, 45.0, 255.0],
        Some(&[0, 17, 31]),
        None,
    );
    assert_eq!(d.dropped_non_finite, 0);
    assert!(d.has_intensity);
    assert_eq!(d.time_field, None);
    // The same through protobuf and `decode_message`.
    let channel = channel("/LIDAR_TOP", "foxglove.PointCloud", "protobuf");
    let bytes = msg.encode_to_vec();
    assert_eq!(decode_message(&message(&channel, &bytes), None).unwrap(), d);
}

#[test]
fn foxglove_numeric_types_use_their_own_numbering() {
    // UINT8 = 1 (INT8 in ROS), UINT16 = 3 (INT16 in ROS): 200 and 40000 would read as
    // negative with ROS numbering.
    let fields = [
        ("x", 0, FoxType::Float32),
        ("y", 4, FoxType::Float32),
        ("z", 8, FoxType::Float32),
        ("intensity", 12, FoxType::Uint8),
        ("ring", 13, FoxType::Uint16),
        ("t", 15, FoxType::Uint32),
    ];
    let data = points(2, 19, false, |i, pt| {
        write_xyz(pt, i);
        pt.u8(12, [200, 7][i])
            .u16(13, [40_000, 2][i])
            .u32(15, [0, 1_000][i]);
    });
    let d = decode_foxglove(&fox_cloud("fx", &fields, 19, data), None).unwrap();
    check(
        &d,
        "fx",
        &XYZ3[..2],
        &[200.0, 7.0],
        Some(&[40_000, 2]),
        Some(&[0.0, 1e-6]),
    );
}

#[test]
fn foxglove_pose_is_applied() {
    let mut msg = nuscenes([0.0, 1.0, 2.0]);
    let half = std::f64::consts::FRAC_1_SQRT_2;
    msg.pose = Some(Pose {
        position: Some(Vector3 {
            x: 1.0,
            y: 2.0,
            z: 3.0,
        }),
        // 90° about z: x -> y, y -> -x.
        orientation: Some(Quaternion {
            x: 0.0,
            y: 0.0,
            z: half,
            w: half,
        }),
    });
    let d = decode_foxglove(&msg, None).unwrap();
    for (got, p) in d.cloud.xyz.iter().zip(XYZ3) {
        let want = [1.0 - p[1], 2.0 + p[0], 3.0 + p[2]];
        for k in 0..3 {
            assert!((got[k] - want[k]).abs() < 1e-5, "{got:?} vs {want:?}");
        }
    }
    // An identity or empty pose changes nothing.
    for pose in [
        Pose::default(),
        Pose {
            position: Some(Vector3::default()),
            orientation: Some(Quaternion {
                w: 1.0,
                ..Default::default()
            }),
        },
    ] {
        msg.pose = Some(pose);
        assert_eq!(decode_foxglove(&msg, None).unwrap().cloud.xyz, XYZ3);
    }
    // A zero quaternion is not a rotation.
    msg.pose = Some(Pose {
        position: None,
        orientation: Some(Quaternion::default()),
    });
    let e = decode_foxglove(&msg, None).unwrap_err();
    assert!(matches!(e, PointsError::BadPose { .. }), "{e}");
    assert!(text(&e, "LIDAR_TOP").contains("zero quaternion"));
}
