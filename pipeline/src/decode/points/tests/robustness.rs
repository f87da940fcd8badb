//! Malformed input never panics: truncations and random layouts.

use super::*;
use crate::test_rng::TestRng as Rng;

#[test]
fn every_truncation_is_an_error_not_a_panic() {
    let (organized, ..) = organized(false);
    for msg in [velodyne(false), velodyne(true), organized] {
        let n = msg.data.len();
        for len in 0..n {
            let mut cut = msg.clone();
            cut.data.truncate(len);
            let trimmed_ok = len == n - 8 && msg.height > 1;
            assert_eq!(decode_ros2(&cut, None).is_ok(), trimmed_ok, "{len}");
        }
    }
    let msg = nuscenes([0.0, 1.0, 2.0]);
    for len in 0..msg.data.len() {
        let mut cut = msg.clone();
        cut.data = msg.data.slice(..len);
        let result = decode_foxglove(&cut, None);
        assert_eq!(result.is_ok(), len % 20 == 0, "{len}");
        if let Ok(d) = result {
            assert_eq!(d.cloud.len(), len / 20);
        }
    }
}

#[test]
fn random_layouts_never_panic() {
    const NAMES: [&str; 16] = [
        "x",
        "y",
        "z",
        "intensity",
        "i",
        "reflectivity",
        "ring",
        "channel",
        "line",
        "time",
        "t",
        "timestamp",
        "offset_time",
        "time_offset",
        "ambient",
        "",
    ];
    let mut rng = Rng(0x9E37_79B9_7F4A_7C15);
    let mut decoded = 0;
    for iteration in 0..20_000 {
        let point_step = rng.below(40) as u32;
        let mut fields: Vec<PointField> = ["x", "y", "z"]
            .iter()
            .map(|name| PointField {
                name: (*name).into(),
                offset: rng.below(u64::from(point_step) + 1) as u32,
                datatype: if rng.below(8) == 0 {
                    rng.below(11) as u8
                } else {
                    7
                },
                count: if rng.below(16) == 0 { 2 } else { 1 },
            })
            .collect();
        for _ in 0..rng.below(5) {
            fields.push(PointField {
                name: NAMES[rng.below(16) as usize].into(),
                offset: rng.below(u64::from(point_step) + 4) as u32,
                datatype: rng.below(10) as u8,
                count: 1,
            });
        }
        if rng.below(10) == 0 {
            fields.swap_remove(rng.below(3) as usize);
        }
        let width = rng.below(6) as u32;
        let height = rng.below(4) as u32;
        let row_step = width * point_step + rng.below(3) as u32 * 4;
        let mut len = (row_step * height) as usize;
        if rng.below(4) == 0 {
            len = len.saturating_sub(rng.below(8) as usize) + rng.below(3) as usize;
        }
        let data: Vec<u8> = (0..len).map(|_| rng.next() as u8).collect();
        let msg = PointCloud2 {
            height,
            width,
            row_step: if rng.below(10) == 0 {
                rng.below(64) as u32
            } else {
                row_step
            },
            is_bigendian: rng.below(2) == 0,
            ..ros("fuzz", fields, point_step, data)
        };
        let spec = (rng.below(4) == 0).then(|| {
            spec(
                NAMES[rng.below(16) as usize],
                [
                    TimeUnit::Seconds,
                    TimeUnit::Microseconds,
                    TimeUnit::Nanoseconds,
                ][rng.below(3) as usize],
                [TimeReference::Absolute, TimeReference::RelativeToStamp][rng.below(2) as usize],
            )
        });
        match decode_ros2(&msg, spec.as_ref()) {
            Ok(d) => {
                decoded += 1;
                d.cloud.validate().unwrap();
                assert_eq!(
                    d.cloud.len() + d.dropped_non_finite,
                    (msg.width * msg.height) as usize,
                    "{iteration}"
                );
                assert!(d.cloud.xyz.iter().flatten().all(|v| v.is_finite()));
            }
            Err(e) => {
                text(&e, "fuzz");
            }
        }
        // The same layout as a Foxglove cloud (types renumbered at random).
        let fox = fox::PointCloud {
            timestamp: Some(Timestamp::new(SEC as u32, NSEC)),
            frame_id: "fuzz".into(),
            pose: None,
            point_stride: msg.point_step,
            fields: msg
                .fields
                .iter()
                .map(|f| PackedElementField {
                    name: f.name.clone(),
                    offset: f.offset,
                    r#type: i32::from(f.datatype),
                })
                .collect(),
            data: msg.data.clone().into(),
        };
        match decode_foxglove(&fox, spec.as_ref()) {
            Ok(d) => {
                d.cloud.validate().unwrap();
                assert!(d.cloud.xyz.iter().flatten().all(|v| v.is_finite()));
            }
            Err(e) => {
                text(&e, "fuzz");
            }
        }
    }
    // The loop exercises the decoding path, not only the error paths.
    assert!(decoded > 1_000, "{decoded}");
}
