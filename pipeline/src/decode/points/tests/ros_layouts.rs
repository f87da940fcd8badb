//! The layouts real ROS 2 recorders write (velodyne, PCL, ouster, KITTI, Autoware),
//! big-endian clouds, organized clouds with padding and FLOAT64 coordinates.

use super::*;

#[test]
fn velodyne_xyzirt_packed() {
    let d = decode_ros2(&velodyne(false), None).unwrap();
    check(
        &d,
        "velodyne",
        &XYZ3,
        &[17.0, 100.0, 0.5],
        Some(&[5, 15, 0]),
        Some(&[0.0, 0.03125, 0.0625]),
    );
    assert_eq!(d.dropped_non_finite, 0);
    assert!(d.has_intensity);
    assert_eq!(
        d.time_field,
        Some(spec(
            "time",
            TimeUnit::Seconds,
            TimeReference::RelativeToStamp
        ))
    );
}

#[test]
fn big_endian_ros_cloud_decodes_like_little_endian() {
    let big = velodyne(true);
    let little = velodyne(false);
    assert_ne!(big.data, little.data);
    let d = decode_ros2(&big, None).unwrap();
    check(
        &d,
        "velodyne",
        &XYZ3,
        &[17.0, 100.0, 0.5],
        Some(&[5, 15, 0]),
        Some(&[0.0, 0.03125, 0.0625]),
    );
    assert_eq!(d, decode_ros2(&little, None).unwrap());
    let layout = PointLayout::from_ros2(&big, None).unwrap();
    assert_eq!(layout.xyz()[0].endianness, Endianness::Big);
    // Integers too: a big-endian UINT16 intensity and an INT16 ring.
    let data = points(2, 16, true, |i, pt| {
        write_xyz(pt, i);
        pt.u16(12, [0x0102, 0xFF00][i]).i16(14, [7, 300][i]);
    });
    let fields = vec![
        field("x", 0, PointField::FLOAT32),
        field("y", 4, PointField::FLOAT32),
        field("z", 8, PointField::FLOAT32),
        field("intensity", 12, PointField::UINT16),
        field("ring", 14, PointField::INT16),
    ];
    let msg = PointCloud2 {
        is_bigendian: true,
        ..ros("be", fields, 16, data)
    };
    let d = decode_ros2(&msg, None).unwrap();
    check(
        &d,
        "be",
        &XYZ3[..2],
        &[258.0, 65280.0],
        Some(&[7, 300]),
        None,
    );
}

// ----- PCL aligned -----

#[test]
fn pcl_aligned_point_xyzirt() {
    let fields = vec![
        field("x", 0, PointField::FLOAT32),
        field("y", 4, PointField::FLOAT32),
        field("z", 8, PointField::FLOAT32),
        field("intensity", 16, PointField::FLOAT32),
        field("ring", 20, PointField::UINT16),
        field("time", 24, PointField::FLOAT32),
    ];
    let data = points(3, 32, false, |i, pt| {
        write_xyz(pt, i);
        pt.f32(16, [1.0, 2.0, 3.0][i])
            .u16(20, [31, 0, 16][i])
            .f32(24, [0.0, 0.05, 0.099][i]);
    });
    let d = decode_ros2(&ros("pcl", fields, 32, data), None).unwrap();
    check(
        &d,
        "pcl",
        &XYZ3,
        &[1.0, 2.0, 3.0],
        Some(&[31, 0, 16]),
        Some(&[0.0, 0.05, 0.099]),
    );
    assert_eq!(d.dropped_non_finite, 0);
    assert_eq!(
        d.time_field.unwrap().reference,
        TimeReference::RelativeToStamp
    );
}

// ----- ouster -----

#[test]
fn ouster_point() {
    let fields = vec![
        field("x", 0, PointField::FLOAT32),
        field("y", 4, PointField::FLOAT32),
        field("z", 8, PointField::FLOAT32),
        field("intensity", 16, PointField::FLOAT32),
        field("t", 20, PointField::UINT32),
        field("reflectivity", 24, PointField::UINT16),
        field("ring", 26, PointField::UINT16),
        field("ambient", 28, PointField::UINT16),
        field("range", 32, PointField::UINT32),
    ];
    let data = points(3, 48, false, |i, pt| {
        write_xyz(pt, i);
        pt.f32(16, [12.0, 400.0, 7.5][i])
            .u32(20, [0, 25_000_000, 75_000_000][i])
            .u16(24, [9999, 9998, 9997][i])
            .u16(26, [0, 63, 127][i])
            .u16(28, 555)
            .u32(32, 123_456);
    });
    let msg = ros("os_lidar", fields, 48, data);
    let d = decode_ros2(&msg, None).unwrap();
    check(
        &d,
        "os_lidar",
        &XYZ3,
        &[12.0, 400.0, 7.5],
        Some(&[0, 63, 127]),
        Some(&[0.0, 0.025, 0.075]),
    );
    assert_eq!(
        d.time_field,
        Some(spec(
            "t",
            TimeUnit::Nanoseconds,
            TimeReference::RelativeToStamp
        ))
    );
    let layout = PointLayout::from_ros2(&msg, None).unwrap();
    assert_eq!(layout.intensity().unwrap().name, "intensity");
    assert_eq!(layout.ring().unwrap().plan.offset, 26);
    assert_eq!(layout.time().unwrap().plan.numeric, NumericType::Uint32);
    assert_eq!(layout.point_step(), 48);
}

#[test]
fn reflectivity_is_the_intensity_fallback_only() {
    let fields = vec![
        field("x", 0, PointField::FLOAT32),
        field("y", 4, PointField::FLOAT32),
        field("z", 8, PointField::FLOAT32),
        field("reflectivity", 12, PointField::UINT16),
    ];
    let data = points(2, 14, false, |i, pt| {
        write_xyz(pt, i);
        pt.u16(12, [3, 4][i]);
    });
    let d = decode_ros2(&ros("r", fields, 14, data), None).unwrap();
    check(&d, "r", &XYZ3[..2], &[3.0, 4.0], None, None);
    assert!(d.has_intensity);
}

// ----- KITTI -----

#[test]
fn kitti_xyzi() {
    let fields = vec![
        field("x", 0, PointField::FLOAT32),
        field("y", 4, PointField::FLOAT32),
        field("z", 8, PointField::FLOAT32),
        field("intensity", 12, PointField::FLOAT32),
    ];
    let data = points(3, 16, false, |i, pt| {
        write_xyz(pt, i);
        pt.f32(12, [0.0, 0.25, 1.0][i]);
    });
    let d = decode_ros2(&ros("velodyne", fields, 16, data), None).unwrap();
    check(&d, "velodyne", &XYZ3, &[0.0, 0.25, 1.0], None, None);
    assert_eq!(d.dropped_non_finite, 0);
    assert!(d.has_intensity);
    assert_eq!(d.time_field, None);
}

#[test]
fn no_intensity_gives_zeros_and_reports_it() {
    let fields = vec![
        field("x", 0, PointField::FLOAT32),
        field("y", 4, PointField::FLOAT32),
        field("z", 8, PointField::FLOAT32),
    ];
    let data = points(3, 12, false, |i, pt| write_xyz(pt, i));
    let d = decode_ros2(&ros("xyz", fields, 12, data), None).unwrap();
    check(&d, "xyz", &XYZ3, &[0.0; 3], None, None);
    assert!(!d.has_intensity);
}

#[test]
fn autoware_xyzirc_small_integers() {
    let fields = vec![
        field("x", 0, PointField::FLOAT32),
        field("y", 4, PointField::FLOAT32),
        field("z", 8, PointField::FLOAT32),
        field("intensity", 12, PointField::UINT8),
        field("return_type", 13, PointField::UINT8),
        field("channel", 14, PointField::UINT16),
    ];
    let data = points(3, 16, false, |i, pt| {
        write_xyz(pt, i);
        pt.u8(12, [200, 0, 255][i])
            .u8(13, 1)
            .u16(14, [127, 0, 64][i]);
    });
    let d = decode_ros2(&ros("lidar_top", fields, 16, data), None).unwrap();
    check(
        &d,
        "lidar_top",
        &XYZ3,
        &[200.0, 0.0, 255.0],
        Some(&[127, 0, 64]),
        None,
    );
}

#[test]
fn organized_cloud_with_nans_and_row_padding() {
    for trim in [false, true] {
        let (msg, xyz, intensity, ring) = organized(trim);
        let d = decode_ros2(&msg, None).unwrap();
        check(&d, "organized", &xyz, &intensity, Some(&ring), None);
        // 128 points: 43 multiples of 3 and one infinite z.
        assert_eq!(d.dropped_non_finite, 44);
        assert_eq!(d.cloud.len(), 128 - 44);
    }
}

#[test]
fn float64_coordinates() {
    let fields = vec![
        field("x", 0, PointField::FLOAT64),
        field("y", 8, PointField::FLOAT64),
        field("z", 16, PointField::FLOAT64),
        field("intensity", 24, PointField::FLOAT32),
    ];
    let values = [
        [0.1, -7.25, 1e3],
        [1e300, 0.0, 0.0],
        [-12.5, 3.0, f64::NAN],
        [2.0, 4.0, 8.0],
    ];
    let data = points(4, 28, false, |i, pt| {
        pt.f64(0, values[i][0])
            .f64(8, values[i][1])
            .f64(16, values[i][2])
            .f32(24, i as f32);
    });
    let d = decode_ros2(&ros("f64", fields, 28, data), None).unwrap();
    // 1e300 overflows f32 to infinity: dropped like the NaN.
    check(
        &d,
        "f64",
        &[[0.1, -7.25, 1000.0], [2.0, 4.0, 8.0]],
        &[0.0, 3.0],
        None,
        None,
    );
    assert_eq!(d.dropped_non_finite, 2);
}
