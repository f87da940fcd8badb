//! Per-point labels: the field found by name regardless of case, any integer type or a
//! float holding integers, the SemanticKITTI mask, bad values and a missing field as
//! errors naming the cloud, label-only clouds (a sidecar's), and the message index of
//! every kept point.

use super::*;

/// x y z (FLOAT32) and a UINT32 `label` with the instance in the upper 16 bits, as
/// SemanticKITTI packs it; point 1 is a NaN no-return.
fn kitti_labels() -> PointCloud2 {
    let data = points(3, 16, false, |i, pt| {
        write_xyz(pt, i);
        if i == 1 {
            pt.f32(0, f32::NAN);
        }
        pt.u32(12, [(7 << 16) | 40, (3 << 16) | 10, 44][i]);
    });
    let fields = vec![
        field("x", 0, PointField::FLOAT32),
        field("y", 4, PointField::FLOAT32),
        field("z", 8, PointField::FLOAT32),
        field("label", 12, PointField::UINT32),
    ];
    ros("velodyne", fields, 16, data)
}

fn with_label(spec: &LabelFieldSpec) -> CloudOptions<'_> {
    CloudOptions {
        label: Some(spec),
        ..CloudOptions::default()
    }
}

#[test]
fn the_mask_keeps_the_class_bits_of_a_u32_label() {
    let msg = kitti_labels();
    let masked = LabelFieldSpec {
        name: None,
        mask: Some(0xFFFF),
    };
    let d = decode_ros2_with(&msg, &with_label(&masked)).unwrap();
    assert_eq!(d.cloud.label.as_deref(), Some(&[40, 44][..]));
    assert_eq!(d.dropped_non_finite, 1);
    d.cloud.validate().unwrap();
    // Without the mask, the whole value.
    let whole = LabelFieldSpec::default();
    let d = decode_ros2_with(&msg, &with_label(&whole)).unwrap();
    assert_eq!(d.cloud.label.as_deref(), Some(&[(7 << 16) | 40, 44][..]));
    // Not asked for: not read, and the cloud is the plain decoder's.
    let plain = decode_ros2(&msg, None).unwrap();
    assert_eq!(plain.cloud.label, None);
    assert_eq!(plain.cloud.xyz, d.cloud.xyz);
}

#[test]
fn a_signed_label_with_instance_bits_masks_its_twos_complement() {
    // INT32 with instance 0x8001 in the upper bits is negative as stored.
    let raw = ((0x8001u32 << 16) | 9) as i32;
    assert!(raw < 0);
    let data = points(1, 16, false, |i, pt| {
        write_xyz(pt, i);
        pt.u32(12, raw as u32);
    });
    let fields = vec![
        field("x", 0, PointField::FLOAT32),
        field("y", 4, PointField::FLOAT32),
        field("z", 8, PointField::FLOAT32),
        field("Label", 12, PointField::INT32),
    ];
    let msg = ros("velodyne", fields, 16, data);
    let masked = LabelFieldSpec {
        name: None,
        mask: Some(0xFFFF),
    };
    let d = decode_ros2_with(&msg, &with_label(&masked)).unwrap();
    assert_eq!(d.cloud.label.as_deref(), Some(&[9][..]));
    // Unmasked, a negative id is an error naming the cloud, the field and the point.
    let e = decode_ros2_with(&msg, &with_label(&LabelFieldSpec::default())).unwrap_err();
    let s = text(&e, "velodyne");
    assert!(matches!(e, PointsError::BadLabel { index: 0, .. }), "{s}");
    assert!(s.contains("`Label`") && s.contains("not a class id"), "{s}");
}

#[test]
fn float_labels_must_hold_integers_and_names_match_regardless_of_case() {
    let fields = [
        ("x", 0, FoxType::Float32),
        ("y", 4, FoxType::Float32),
        ("z", 8, FoxType::Float32),
        ("SEMANTIC", 12, FoxType::Float32),
    ];
    let cloud = |labels: [f32; 3]| {
        let data = points(3, 16, false, |i, pt| {
            write_xyz(pt, i);
            pt.f32(12, labels[i]);
        });
        fox_cloud("LIDAR_TOP", &fields, 16, data)
    };
    let spec = LabelFieldSpec::default();
    let d = decode_foxglove_with(&cloud([0.0, 11.0, 16.0]), &with_label(&spec)).unwrap();
    assert_eq!(d.cloud.label.as_deref(), Some(&[0, 11, 16][..]));
    for bad in [11.5, f32::NAN, -1.0] {
        let e = decode_foxglove_with(&cloud([0.0, bad, 16.0]), &with_label(&spec)).unwrap_err();
        let s = text(&e, "LIDAR_TOP");
        assert!(
            matches!(e, PointsError::BadLabel { index: 1, .. }) && s.contains("`SEMANTIC`"),
            "{s}"
        );
    }
    // A configured name, in any case; absent, an error listing the fields.
    let named = LabelFieldSpec {
        name: Some("semantic".into()),
        mask: None,
    };
    assert!(decode_foxglove_with(&cloud([1.0, 2.0, 3.0]), &with_label(&named)).is_ok());
    let other = LabelFieldSpec {
        name: Some("lidarseg".into()),
        mask: None,
    };
    let e = decode_foxglove_with(&cloud([1.0, 2.0, 3.0]), &with_label(&other)).unwrap_err();
    let s = text(&e, "LIDAR_TOP");
    assert!(
        matches!(e, PointsError::MissingLabelField { .. })
            && s.contains("`lidarseg`")
            && s.contains("x, y, z, SEMANTIC"),
        "{s}"
    );
    // A cloud without labels has none to read.
    let e = decode_foxglove_with(&nuscenes([0.0; 3]), &with_label(&spec)).unwrap_err();
    assert!(text(&e, "LIDAR_TOP").contains("one of label, class"), "{e}");
}

#[test]
fn kept_indices_carry_parallel_labels_through_the_dropping() {
    let (msg, xyz, _, _) = organized(false);
    let options = CloudOptions {
        kept_indices: true,
        ..CloudOptions::default()
    };
    let d = decode_ros2_with(&msg, &options).unwrap();
    let kept = d.kept_indices.as_deref().unwrap();
    assert_eq!(kept.len(), xyz.len());
    // Every third point is a no-return and point 50 has z = +inf: the rest are kept.
    let expected: Vec<u32> = (0..128u32).filter(|i| i % 3 != 0 && *i != 50).collect();
    assert_eq!(kept, expected);
    assert_eq!(decode_ros2(&msg, None).unwrap().kept_indices, None);
}

#[test]
fn a_label_only_cloud_reads_every_point_of_its_only_field() {
    let data: Vec<u8> = vec![0, 4, 11, 255];
    let fields = vec![field("seg", 0, PointField::UINT8)];
    let msg = ros("lidar_top", fields, 1, data);
    let labels = decode_labels_ros2(&msg, &LabelFieldSpec::default()).unwrap();
    assert_eq!(labels.labels, [0, 4, 11, 255]);
    assert_eq!((labels.field.as_str(), labels.stamp), ("seg", stamp()));
    // Through an MCAP message, in either dialect.
    let ros_channel = channel("/lidar/labels", "sensor_msgs/msg/PointCloud2", "cdr");
    let bytes = ros2::encode(&msg).unwrap();
    let via = decode_labels_message(&message(&ros_channel, &bytes), &LabelFieldSpec::default());
    assert_eq!(via.unwrap(), labels);
    let fox = fox_cloud(
        "LIDAR_TOP",
        &[("label", 0, FoxType::Uint16)],
        2,
        points(2, 2, false, |i, pt| {
            pt.u16(0, [300, 7][i]);
        }),
    );
    let fox_channel = channel("/LIDAR_TOP/labels", "foxglove.PointCloud", "protobuf");
    let bytes = fox.encode_to_vec();
    let labels = decode_labels_message(&message(&fox_channel, &bytes), &LabelFieldSpec::default());
    assert_eq!(labels.unwrap().labels, [300, 7]);
    // Two fields, neither a label name: which is it?
    let fields = vec![
        field("a", 0, PointField::UINT8),
        field("b", 1, PointField::UINT8),
    ];
    let e = decode_labels_ros2(
        &ros("lidar_top", fields, 2, vec![0; 4]),
        &Default::default(),
    )
    .unwrap_err();
    assert!(matches!(e, PointsError::MissingLabelField { .. }), "{e}");
}
