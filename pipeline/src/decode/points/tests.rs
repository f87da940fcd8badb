//! Tests of the point-cloud decoders, by concern: the recorders' real layouts, Foxglove
//! clouds, per-point time, errors, dispatch on the schema, and robustness. This file holds
//! the shared fixtures (point writers, the velodyne, nuScenes and organized clouds).

use super::*;
use crate::decode::foxglove as fox;
use crate::decode::ros2::{self, PointCloud2};
use crate::decode::ros2::{Header, PointField, Ros2Time};
use crate::source::MessageRef;
use crate::source::{ChannelInfo, MessageLoc, SchemaInfo};
use ::foxglove::messages::packed_element_field::NumericType as FoxType;
use ::foxglove::messages::{PackedElementField, Pose, Quaternion, Timestamp, Vector3};
use prost::Message as _;
use std::collections::BTreeMap;
use std::sync::Arc;
use superflow_schemas::Stamp;

mod dialect;
mod errors;
mod foxglove;
mod labels;
mod robustness;
mod ros_layouts;
mod time;

const SEC: i32 = 1_700_000_000;
const NSEC: u32 = 125_000_000;
const STAMP_TEXT: &str = "1700000000.125000000";
const FILL: u8 = 0xAB;

fn stamp() -> Stamp {
    Stamp::from_sec_nanosec(i64::from(SEC), NSEC)
}

/// Writes the fields of one point with the chosen byte order.
struct Pt<'a> {
    buf: &'a mut [u8],
    big: bool,
}

macro_rules! writer {
    ($($name:ident: $t:ty),*) => {
        impl Pt<'_> {
            $(
                fn $name(&mut self, offset: usize, v: $t) -> &mut Self {
                    let bytes = if self.big { v.to_be_bytes() } else { v.to_le_bytes() };
                    self.buf[offset..offset + bytes.len()].copy_from_slice(&bytes);
                    self
                }
            )*
        }
    };
}
writer!(u8: u8, i16: i16, u16: u16, u32: u32, f32: f32, f64: f64);

/// `n` points of `step` bytes (filled with `FILL`), each written by `write(index, pt)`.
fn points(n: usize, step: usize, big: bool, mut write: impl FnMut(usize, &mut Pt<'_>)) -> Vec<u8> {
    let mut data = vec![FILL; n * step];
    for (i, buf) in data.chunks_mut(step).enumerate() {
        write(i, &mut Pt { buf, big });
    }
    data
}

fn field(name: &str, offset: u32, datatype: u8) -> PointField {
    PointField {
        name: name.into(),
        offset,
        datatype,
        count: 1,
    }
}

/// An unorganized little-endian ROS cloud (`height` 1, unpadded rows).
fn ros(frame: &str, fields: Vec<PointField>, point_step: u32, data: Vec<u8>) -> PointCloud2 {
    let width = data.len().checked_div(point_step as usize).unwrap_or(0) as u32;
    PointCloud2 {
        header: Header {
            stamp: Ros2Time {
                sec: SEC,
                nanosec: NSEC,
            },
            frame_id: frame.into(),
        },
        height: 1,
        width,
        fields,
        is_bigendian: false,
        point_step,
        row_step: width * point_step,
        data,
        is_dense: false,
    }
}

fn fox_cloud(
    frame: &str,
    fields: &[(&str, u32, FoxType)],
    stride: u32,
    data: Vec<u8>,
) -> fox::PointCloud {
    fox::PointCloud {
        timestamp: Some(Timestamp::new(SEC as u32, NSEC)),
        frame_id: frame.into(),
        pose: None,
        point_stride: stride,
        fields: fields
            .iter()
            .map(|&(name, offset, ty)| PackedElementField {
                name: name.into(),
                offset,
                r#type: ty as i32,
            })
            .collect(),
        data: data.into(),
    }
}

fn spec(name: &str, unit: TimeUnit, reference: TimeReference) -> TimeFieldSpec {
    TimeFieldSpec {
        name: name.into(),
        unit,
        reference,
    }
}

/// Checks the whole decoded cloud against the expected values.
#[track_caller]
fn check(
    d: &DecodedCloud,
    frame: &str,
    xyz: &[[f32; 3]],
    intensity: &[f32],
    ring: Option<&[u16]>,
    time: Option<&[f32]>,
) {
    assert_eq!(d.cloud.frame_id, frame);
    assert_eq!(d.cloud.stamp, stamp());
    assert_eq!(d.cloud.xyz, xyz);
    assert_eq!(d.cloud.intensity, intensity);
    assert_eq!(d.cloud.ring.as_deref(), ring);
    assert_eq!(d.cloud.time_offset_secs.as_deref(), time);
    d.cloud.validate().unwrap();
}

/// The error's text, checked to name the frame and the stamp.
#[track_caller]
fn text(e: &PointsError, frame: &str) -> String {
    let s = e.to_string();
    assert!(s.contains(&format!("`{frame}`")), "{s}");
    assert!(s.contains(STAMP_TEXT), "{s}");
    s
}

const XYZ3: [[f32; 3]; 3] = [[1.5, -2.25, 0.5], [10.0, 20.0, -1.75], [-3.0, 0.0, 2.0]];

fn write_xyz(pt: &mut Pt<'_>, i: usize) {
    pt.f32(0, XYZ3[i][0]).f32(4, XYZ3[i][1]).f32(8, XYZ3[i][2]);
}

// ----- velodyne -----

fn velodyne_fields() -> Vec<PointField> {
    vec![
        field("x", 0, PointField::FLOAT32),
        field("y", 4, PointField::FLOAT32),
        field("z", 8, PointField::FLOAT32),
        field("intensity", 12, PointField::FLOAT32),
        field("ring", 16, PointField::UINT16),
        field("time", 18, PointField::FLOAT32),
    ]
}

fn velodyne(big: bool) -> PointCloud2 {
    let data = points(3, 22, big, |i, pt| {
        write_xyz(pt, i);
        pt.f32(12, [17.0, 100.0, 0.5][i])
            .u16(16, [5, 15, 0][i])
            .f32(18, [0.0, 0.03125, 0.0625][i]);
    });
    PointCloud2 {
        is_bigendian: big,
        ..ros("velodyne", velodyne_fields(), 22, data)
    }
}

// ----- nuScenes / Foxglove -----

const NUSCENES_FIELDS: [(&str, u32, FoxType); 5] = [
    ("x", 0, FoxType::Float32),
    ("y", 4, FoxType::Float32),
    ("z", 8, FoxType::Float32),
    ("intensity", 12, FoxType::Float32),
    ("ring", 16, FoxType::Float32),
];

fn nuscenes(rings: [f32; 3]) -> fox::PointCloud {
    let data = points(3, 20, false, |i, pt| {
        write_xyz(pt, i);
        pt.f32(12, [3.0, 45.0, 255.0][i]).f32(16, rings[i]);
    });
    fox_cloud("LIDAR_TOP", &NUSCENES_FIELDS, 20, data)
}

// ----- organized clouds, FLOAT64 coordinates -----

/// 16 rows of 8 points (x y z intensity FLOAT32, ring UINT16, 2 bytes of padding),
/// rows padded by 8 bytes; every third point is a NaN no-return, one has z = +inf.
fn organized(trim_last_padding: bool) -> (PointCloud2, Vec<[f32; 3]>, Vec<f32>, Vec<u16>) {
    const W: usize = 8;
    const H: usize = 16;
    const STEP: usize = 20;
    const ROW_STEP: usize = W * STEP + 8;
    let mut data = vec![0xFF; ROW_STEP * H]; // 0xFFFFFFFF is a NaN if ever read
    let (mut xyz, mut intensity, mut ring) = (vec![], vec![], vec![]);
    for r in 0..H {
        for c in 0..W {
            let start = r * ROW_STEP + c * STEP;
            let mut pt = Pt {
                buf: &mut data[start..start + STEP],
                big: false,
            };
            let i = r * W + c;
            let p = [c as f32 * 0.5, r as f32 - 8.0, 0.25 * i as f32];
            if i.is_multiple_of(3) {
                pt.f32(0, f32::NAN).f32(4, f32::NAN).f32(8, f32::NAN);
            } else if i == 50 {
                pt.f32(0, p[0]).f32(4, p[1]).f32(8, f32::INFINITY);
            } else {
                pt.f32(0, p[0]).f32(4, p[1]).f32(8, p[2]);
                xyz.push(p);
                intensity.push(i as f32);
                ring.push(r as u16);
            }
            pt.f32(12, i as f32).u16(16, r as u16);
        }
    }
    if trim_last_padding {
        data.truncate(ROW_STEP * (H - 1) + W * STEP);
    }
    let fields = vec![
        field("x", 0, PointField::FLOAT32),
        field("y", 4, PointField::FLOAT32),
        field("z", 8, PointField::FLOAT32),
        field("intensity", 12, PointField::FLOAT32),
        field("ring", 16, PointField::UINT16),
    ];
    let msg = PointCloud2 {
        height: H as u32,
        width: W as u32,
        row_step: ROW_STEP as u32,
        data,
        ..ros("organized", fields, STEP as u32, vec![])
    };
    (msg, xyz, intensity, ring)
}

/// A channel of `schema` in `encoding`.
fn channel(topic: &str, schema: &str, encoding: &str) -> ChannelInfo {
    ChannelInfo {
        id: 1,
        topic: topic.into(),
        schema: Some(Arc::new(SchemaInfo {
            id: 1,
            name: schema.into(),
            encoding: String::new(),
            data: vec![],
        })),
        message_encoding: encoding.into(),
        metadata: BTreeMap::new(),
    }
}

/// A message of `channel` holding `data`.
fn message<'a>(channel: &'a ChannelInfo, data: &'a [u8]) -> MessageRef<'a> {
    MessageRef {
        channel,
        sequence: 0,
        log_time: 0,
        publish_time: 0,
        data,
        loc: MessageLoc::Direct { offset: 0 },
    }
}
