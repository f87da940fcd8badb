//! Point clouds as recorders write them — a packed array of points whose layout a list
//! of named fields describes — decoded into the sensor model's [`PointCloud`].
//!
//! # Messages
//!
//! | message | entry point | layout | endianness |
//! |---|---|---|---|
//! | ROS 2 `sensor_msgs/msg/PointCloud2` | [`decode_ros2`] | `fields` (`name`, `offset`, `datatype`, `count`), `point_step`, `row_step`, `width × height` | `is_bigendian` |
//! | `foxglove.PointCloud` | [`decode_foxglove`] | `fields` (`name`, `offset`, `type`), `point_stride`; the number of points is `data.len() / point_stride` | always little-endian |
//! | either, straight from an MCAP message | [`decode_message`] | by the channel's schema | |
//!
//! Both go through one core: the fields are parsed once per message into a
//! [`PointLayout`] (offset, [`NumericType`] and [`Endianness`] of each field that is used),
//! then every point is read at those fixed offsets with `from_le_bytes`/`from_be_bytes`.
//! Nothing is looked up by name and nothing is allocated per point.
//!
//! The two numbering schemes of the element types differ and are mapped separately:
//!
//! | type | ROS `PointField.datatype` | Foxglove `NumericType` |
//! |---|---|---|
//! | int8 / uint8 | 1 / 2 | 2 / 1 |
//! | int16 / uint16 | 3 / 4 | 4 / 3 |
//! | int32 / uint32 | 5 / 6 | 6 / 5 |
//! | float32 / float64 | 7 / 8 | 7 / 8 |
//!
//! # Fields
//!
//! | attribute | field names (first match in this order) | types | result |
//! |---|---|---|---|
//! | position | `x`, `y`, `z` (all three required, `count` 1) | any | `xyz` as `f32` |
//! | intensity | `intensity`, `i`; `reflectivity` only when neither exists | any | `intensity` as `f32`, the value as stored (UINT8 `0..255`, KITTI `0..1`, ...); 0 with [`DecodedCloud::has_intensity`] `false` when absent |
//! | ring | `ring`, `channel`, `laser_id`, `line` | any, FLOAT32 included (nuScenes) | `ring` as `u16`; a value that is not an integer in `0..=65535` is an error ([`PointsError::BadRing`]) |
//! | per-point time | `time`, `t`, `time_offset`, `offset_time`, `timestamp` | see below | `time_offset_secs`, seconds relative to the message stamp |
//!
//! Names are matched exactly (case-sensitive); the first field with a name wins. Fields
//! that are not used (`ambient`, `range`, `return_type`, padding, ...) are not checked:
//! an unknown datatype or a bad offset there does not matter. A used field must have
//! `count` 1, a known datatype, and lie inside the point (`offset + size <= point_step`).
//!
//! # Real layouts (each has a test)
//!
//! | source | fields (offset) | point_step |
//! |---|---|---|
//! | velodyne_pointcloud `PointcloudXYZIRT` (packed) | x0 y4 z8 intensity12 (FLOAT32), ring16 (UINT16), time18 (FLOAT32 s) | 22 |
//! | PCL `PointXYZIRT` via `pcl::toROSMsg` (aligned) | x0 y4 z8, intensity16, ring20 (UINT16), time24 | 32 |
//! | ouster-ros `Point` | x0 y4 z8, intensity16 (FLOAT32), t20 (UINT32 ns), reflectivity24, ring26 (UINT16), ambient28, range32 | 48 |
//! | KITTI (kitti2mcap) | x0 y4 z8 intensity12 (FLOAT32) | 16 |
//! | Hesai (PCL-aligned `PointXYZIT`-style; offsets vary by driver) | x0 y4 z8, intensity16 (FLOAT32), timestamp24 (FLOAT64 absolute s), ring32 (UINT16) | 48 |
//! | Livox (PointCloud2 output) | x y z intensity (FLOAT32), tag, line (UINT8), timestamp (FLOAT64 absolute) or offset_time (UINT32 ns) | — |
//! | Autoware `PointXYZIRC` | x0 y4 z8 (FLOAT32), intensity12 (UINT8), return_type13, channel14 (UINT16) | 16 |
//! | nuScenes `foxglove.PointCloud` | x0 y4 z8 intensity12 ring16, all FLOAT32 | 20 |
//!
//! # Per-point time
//!
//! `PointCloud::time_offset_secs` is each point's time **relative to the message stamp**,
//! in seconds. Recorders disagree on the unit and reference of their time field, so,
//! unless the caller passes a [`TimeFieldSpec`], they are inferred:
//!
//! | field type | values | unit | reference | typical source |
//! |---|---|---|---|---|
//! | integer (any width) | — | nanoseconds | relative | ouster `t` (UINT32), livox `offset_time` (UINT32) |
//! | FLOAT32 / FLOAT64 | max \|v\| ≤ 1e8 | seconds | relative | velodyne / PCL `time` (FLOAT32), `time_offset` |
//! | FLOAT32 / FLOAT64 | 1e8 < max \|v\| ≤ 1e14 | seconds | absolute | hesai / livox `timestamp` (FLOAT64 s since the epoch) |
//! | FLOAT32 / FLOAT64 | 1e14 < max \|v\| ≤ 1e17 | microseconds | absolute | absolute µs stamps |
//! | FLOAT32 / FLOAT64 | max \|v\| > 1e17 | nanoseconds | absolute | livox_ros_driver2 `timestamp` (FLOAT64 ns since the epoch) |
//!
//! `max |v|` is taken over the kept points (those with a finite position), so the zero
//! or garbage times of no-return points do not flip the decision. It costs nothing for
//! relative clouds: the field is read as relative seconds while the maximum is tracked,
//! and only a cloud that turns out absolute has its time column read a second time. A
//! relative field cannot reach 1e8 s (three years); an absolute one is at least 1e8 s
//! past the epoch for any date after 1973. A float field that holds time since boot
//! (< 1e8 s) is indistinguishable from a relative one: pass a [`TimeFieldSpec`] for such
//! a recorder.
//!
//! * **Relative** fields are taken as offsets from the message stamp as they are:
//!   `offset = value / units_per_second`. They are documented as relative to the *scan
//!   start* (velodyne, ouster, livox), which equals the stamp when the driver stamps the
//!   first packet (the velodyne driver's `timestamp_first_packet: true`, ouster, livox).
//!   When the velodyne driver stamps the **last** packet instead, the true offsets are
//!   `value − sweep duration`; the message does not say which, so the field value is kept
//!   and a configuration must correct it (a `TimeFieldSpec` cannot express a shift).
//! * **Absolute** fields are converted to the offset from the stamp:
//!   `offset = value − stamp`, computed without losing the sub-microsecond part of the
//!   stamp (the integral part of the stamp in the field's unit is subtracted first).
//!   The precision is then that of the stored value (a FLOAT64 of seconds since the epoch
//!   resolves about 0.24 µs).
//!
//! A time that is not finite on a kept point is an error ([`PointsError::BadTime`]); the
//! resolved interpretation is reported in [`DecodedCloud::time_field`].
//!
//! # Invalid points, organized clouds
//!
//! Points with a non-finite `x`, `y` or `z` (organized clouds write NaN for "no return";
//! a FLOAT64 coordinate beyond the `f32` range becomes infinite) are dropped and counted
//! in [`DecodedCloud::dropped_non_finite`]; the remaining points keep their order (row by
//! row). ROS rows are `row_step` bytes apart and may be padded after their
//! `width × point_step` bytes of points; `data` must hold `row_step × height` bytes (the
//! padding of the last row may be left out; `row_step` 0 means unpadded rows).
//!
//! # Foxglove pose
//!
//! `foxglove.PointCloud.pose` is "the origin of the point cloud relative to the frame of
//! reference": the points are stored in a cloud frame and `frame_id_from_cloud = pose`.
//! When it is set and not the identity, every decoded point becomes `pose * point`
//! (rotation then translation, in `f64`), so the result is expressed in `frame_id` like
//! every other cloud. Absent position = zero, absent orientation = identity; a
//! non-finite pose or a zero quaternion is an error. nuScenes leaves the pose unset.
//!
//! # Errors
//!
//! Every [`PointsError`] about a message names its frame id and stamp (the caller adds the
//! file and topic). Malformed input never panics: sizes are checked against the data
//! before anything is read, and allocation is bounded by the data's size.

use super::DecodeError;
use super::foxglove as fox;
use super::ros2::{self, PointCloud2};
use crate::drive::discover::{Dialect, SchemaKind, schema_kind};
use crate::source::MessageRef;
use superflow_schemas::Stamp;
use superflow_schemas::sensor::PointCloud;

/// Schema name of `foxglove.PointCloud`.
const FOXGLOVE_SCHEMA: &str = "foxglove.PointCloud";

/// Names of the intensity field, in order of preference.
const INTENSITY_NAMES: [&str; 2] = ["intensity", "i"];
/// Name of the intensity fallback, used only when no [`INTENSITY_NAMES`] field exists.
const INTENSITY_FALLBACK: &str = "reflectivity";
/// Names of the ring (beam index) field, in order of preference.
const RING_NAMES: [&str; 4] = ["ring", "channel", "laser_id", "line"];
/// Names of the per-point time field, in order of preference.
const TIME_NAMES: [&str; 5] = ["time", "t", "time_offset", "offset_time", "timestamp"];

/// Float time values above this magnitude are absolute (seconds since the epoch or finer).
const ABSOLUTE_THRESHOLD: f64 = 1e8;
/// Absolute float times above this magnitude are microseconds.
const MICROSECONDS_THRESHOLD: f64 = 1e14;
/// Absolute float times above this magnitude are nanoseconds.
const NANOSECONDS_THRESHOLD: f64 = 1e17;

// ---------------------------------------------------------------------------------------
// Public types
// ---------------------------------------------------------------------------------------

/// A point cloud that cannot be decoded. Errors about a message name its frame id and
/// stamp; the caller adds the file and topic.
#[derive(Debug, thiserror::Error)]
pub enum PointsError {
    /// One of the coordinate fields `x`, `y`, `z` is absent.
    #[error("point cloud `{frame_id}` at {stamp}: no `{axis}` field (fields: {fields})")]
    MissingCoordinate {
        /// Frame of the cloud.
        frame_id: String,
        /// Its stamp.
        stamp: Stamp,
        /// The missing coordinate.
        axis: &'static str,
        /// The field names present, comma-separated.
        fields: String,
    },
    /// The time field named by a [`TimeFieldSpec`] is absent.
    #[error(
        "point cloud `{frame_id}` at {stamp}: the configured time field `{name}` is absent (fields: {fields})"
    )]
    MissingTimeField {
        /// Frame of the cloud.
        frame_id: String,
        /// Its stamp.
        stamp: Stamp,
        /// The configured name.
        name: String,
        /// The field names present, comma-separated.
        fields: String,
    },
    /// A used field has more (or fewer) than one element per point.
    #[error(
        "point cloud `{frame_id}` at {stamp}: field `{field}` has count {count}, only 1 is supported"
    )]
    FieldCount {
        /// Frame of the cloud.
        frame_id: String,
        /// Its stamp.
        stamp: Stamp,
        /// Field name.
        field: String,
        /// Its `count`.
        count: u32,
    },
    /// A used field has a datatype outside the dialect's numbering.
    #[error(
        "point cloud `{frame_id}` at {stamp}: field `{field}` has unknown {dialect} datatype {datatype}"
    )]
    UnknownDatatype {
        /// Frame of the cloud.
        frame_id: String,
        /// Its stamp.
        stamp: Stamp,
        /// Field name.
        field: String,
        /// `"ROS PointField"` or `"Foxglove NumericType"`.
        dialect: &'static str,
        /// The recorded value.
        datatype: i64,
    },
    /// A used field does not fit inside a point.
    #[error(
        "point cloud `{frame_id}` at {stamp}: field `{field}` ({size} bytes at offset {offset}) extends past the point step of {point_step} bytes"
    )]
    FieldPastPointStep {
        /// Frame of the cloud.
        frame_id: String,
        /// Its stamp.
        stamp: Stamp,
        /// Field name.
        field: String,
        /// Its offset in the point.
        offset: u32,
        /// Its size in bytes.
        size: usize,
        /// Bytes per point (`point_step` or `point_stride`).
        point_step: u32,
    },
    /// A ROS row is shorter than its points.
    #[error(
        "point cloud `{frame_id}` at {stamp}: row_step {row_step} is shorter than width {width} x point_step {point_step}"
    )]
    RowStepTooShort {
        /// Frame of the cloud.
        frame_id: String,
        /// Its stamp.
        stamp: Stamp,
        /// Bytes per row.
        row_step: u32,
        /// Points per row.
        width: u32,
        /// Bytes per point.
        point_step: u32,
    },
    /// ROS point data whose length does not match `row_step × height`.
    #[error(
        "point cloud `{frame_id}` at {stamp}: {got} bytes of point data, expected {expected} ({height} rows of row_step {row_step} bytes holding {width} points of {point_step} bytes)"
    )]
    DataLength {
        /// Frame of the cloud.
        frame_id: String,
        /// Its stamp.
        stamp: Stamp,
        /// Bytes present.
        got: usize,
        /// Bytes expected (`row_step × height`).
        expected: u64,
        /// Points per row.
        width: u32,
        /// Rows.
        height: u32,
        /// Bytes per point.
        point_step: u32,
        /// Bytes per row.
        row_step: u32,
    },
    /// Foxglove point data whose length is not a multiple of the point stride.
    #[error(
        "point cloud `{frame_id}` at {stamp}: {got} bytes of point data is not a multiple of the point stride {point_stride}"
    )]
    NotMultipleOfStride {
        /// Frame of the cloud.
        frame_id: String,
        /// Its stamp.
        stamp: Stamp,
        /// Bytes present.
        got: usize,
        /// Bytes per point.
        point_stride: u32,
    },
    /// A ring value that is not an integer in `0..=65535`.
    #[error(
        "point cloud `{frame_id}` at {stamp}: point {index} has `{field}` = {value}, not a ring index (an integer in 0..=65535)"
    )]
    BadRing {
        /// Frame of the cloud.
        frame_id: String,
        /// Its stamp.
        stamp: Stamp,
        /// Name of the ring field.
        field: String,
        /// Index of the point in the message (invalid points counted).
        index: usize,
        /// The recorded value.
        value: f64,
    },
    /// A kept point whose time is not finite (or whose offset is not).
    #[error(
        "point cloud `{frame_id}` at {stamp}: point {index} has time field `{field}` = {value}, which gives no finite time offset"
    )]
    BadTime {
        /// Frame of the cloud.
        frame_id: String,
        /// Its stamp.
        stamp: Stamp,
        /// Name of the time field.
        field: String,
        /// Index of the point in the message (invalid points counted).
        index: usize,
        /// The recorded value.
        value: f64,
    },
    /// A `foxglove.PointCloud` pose that is not a rigid transform.
    #[error("point cloud `{frame_id}` at {stamp}: bad pose: {reason}")]
    BadPose {
        /// Frame of the cloud.
        frame_id: String,
        /// Its stamp.
        stamp: Stamp,
        /// What is wrong.
        reason: String,
    },
    /// A `foxglove.PointCloud` without `timestamp`.
    #[error("point cloud `{frame_id}`: foxglove.PointCloud has no timestamp")]
    MissingTimestamp {
        /// Frame of the cloud.
        frame_id: String,
    },
    /// [`decode_message`] on a channel that does not carry point clouds.
    #[error("`{topic}`: schema `{schema}` with message encoding `{encoding}` is not a point cloud")]
    NotAPointCloud {
        /// Topic of the channel.
        topic: String,
        /// Schema name.
        schema: String,
        /// Message encoding.
        encoding: String,
    },
    /// [`decode_message`] on a payload that does not decode as its schema.
    #[error("`{topic}`: {source}")]
    Message {
        /// Topic of the channel.
        topic: String,
        /// The payload's decoding error.
        source: Box<DecodeError>,
    },
}

/// Unit of a per-point time field.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Hash)]
pub enum TimeUnit {
    /// Seconds.
    Seconds,
    /// Microseconds.
    Microseconds,
    /// Nanoseconds.
    Nanoseconds,
}

impl TimeUnit {
    /// How many of this unit make one second.
    pub const fn per_second(self) -> f64 {
        match self {
            TimeUnit::Seconds => 1.0,
            TimeUnit::Microseconds => 1e6,
            TimeUnit::Nanoseconds => 1e9,
        }
    }

    /// Nanoseconds in one of this unit.
    const fn nanos(self) -> i64 {
        match self {
            TimeUnit::Seconds => 1_000_000_000,
            TimeUnit::Microseconds => 1_000,
            TimeUnit::Nanoseconds => 1,
        }
    }
}

/// What a per-point time field is measured from.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Hash)]
pub enum TimeReference {
    /// An offset from the message stamp (drivers document "since scan start"; see the
    /// module documentation for when that differs from the stamp).
    RelativeToStamp,
    /// A time since the epoch of the message stamp.
    Absolute,
}

/// How to read the per-point time: which field, in which unit, from which reference.
///
/// Passed to the decoders to override the inference of the module documentation; the
/// decoders also return the interpretation they used in [`DecodedCloud::time_field`].
#[derive(Debug, Clone, PartialEq, Eq, Hash)]
pub struct TimeFieldSpec {
    /// Field name (exact).
    pub name: String,
    /// Unit of the stored values.
    pub unit: TimeUnit,
    /// What the values are measured from.
    pub reference: TimeReference,
}

/// Element type of a field, independent of the dialect's numbering.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Hash)]
pub enum NumericType {
    /// `i8`.
    Int8,
    /// `u8`.
    Uint8,
    /// `i16`.
    Int16,
    /// `u16`.
    Uint16,
    /// `i32`.
    Int32,
    /// `u32`.
    Uint32,
    /// `f32`.
    Float32,
    /// `f64`.
    Float64,
}

impl NumericType {
    /// Size of one element in bytes.
    pub const fn size(self) -> usize {
        match self {
            NumericType::Int8 | NumericType::Uint8 => 1,
            NumericType::Int16 | NumericType::Uint16 => 2,
            NumericType::Int32 | NumericType::Uint32 | NumericType::Float32 => 4,
            NumericType::Float64 => 8,
        }
    }

    /// Whether the type is a floating-point type.
    pub const fn is_float(self) -> bool {
        matches!(self, NumericType::Float32 | NumericType::Float64)
    }

    /// The type of a ROS `PointField.datatype` (INT8 = 1 ... FLOAT64 = 8).
    pub const fn from_ros2(datatype: u8) -> Option<Self> {
        Some(match datatype {
            1 => NumericType::Int8,
            2 => NumericType::Uint8,
            3 => NumericType::Int16,
            4 => NumericType::Uint16,
            5 => NumericType::Int32,
            6 => NumericType::Uint32,
            7 => NumericType::Float32,
            8 => NumericType::Float64,
            _ => return None,
        })
    }

    /// The type of a Foxglove `PackedElementField.type` (UINT8 = 1, INT8 = 2, ...,
    /// FLOAT64 = 8; 0 is UNKNOWN).
    pub const fn from_foxglove(numeric_type: i32) -> Option<Self> {
        Some(match numeric_type {
            1 => NumericType::Uint8,
            2 => NumericType::Int8,
            3 => NumericType::Uint16,
            4 => NumericType::Int16,
            5 => NumericType::Uint32,
            6 => NumericType::Int32,
            7 => NumericType::Float32,
            8 => NumericType::Float64,
            _ => return None,
        })
    }
}

/// Byte order of multi-byte values.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Hash)]
pub enum Endianness {
    /// Least significant byte first (Foxglove; ROS `is_bigendian = false`).
    Little,
    /// Most significant byte first (ROS `is_bigendian = true`).
    Big,
}

/// Where and how one field is read in a point.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Hash)]
pub struct FieldPlan {
    /// Byte offset in the point.
    pub offset: usize,
    /// Element type.
    pub numeric: NumericType,
    /// Byte order.
    pub endianness: Endianness,
}

impl FieldPlan {
    /// The field's value in `point` (the bytes of one point), widened to `f64` (exact for
    /// every type). Reads 0 if the field does not fit, which a validated
    /// [`PointLayout`] rules out.
    #[inline(always)]
    pub fn read(self, point: &[u8]) -> f64 {
        macro_rules! get {
            ($t:ty) => {{
                let bytes = array::<{ size_of::<$t>() }>(point, self.offset);
                match self.endianness {
                    Endianness::Little => <$t>::from_le_bytes(bytes),
                    Endianness::Big => <$t>::from_be_bytes(bytes),
                }
            }};
        }
        match self.numeric {
            NumericType::Int8 => f64::from(get!(i8)),
            NumericType::Uint8 => f64::from(get!(u8)),
            NumericType::Int16 => f64::from(get!(i16)),
            NumericType::Uint16 => f64::from(get!(u16)),
            NumericType::Int32 => f64::from(get!(i32)),
            NumericType::Uint32 => f64::from(get!(u32)),
            NumericType::Float32 => f64::from(get!(f32)),
            NumericType::Float64 => get!(f64),
        }
    }
}

/// `N` bytes of `point` at `offset`, zeros if they are not all there.
#[inline(always)]
fn array<const N: usize>(point: &[u8], offset: usize) -> [u8; N] {
    point
        .get(offset..)
        .and_then(<[u8]>::first_chunk::<N>)
        .copied()
        .unwrap_or([0; N])
}

/// A used field: its name and how to read it.
#[derive(Debug, Clone, PartialEq, Eq, Hash)]
pub struct NamedField {
    /// The field's name in the message.
    pub name: String,
    /// Where and how to read it.
    pub plan: FieldPlan,
}

/// How the time field's unit and reference are decided.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Hash)]
enum TimeRule {
    /// Given (by a [`TimeFieldSpec`], or by the inference for integer fields).
    Fixed(TimeUnit, TimeReference),
    /// A float field: relative seconds or absolute, by the magnitude of its values.
    ByMagnitude,
}

/// The per-point time field and how to interpret it.
#[derive(Debug, Clone, PartialEq, Eq, Hash)]
struct TimePlan {
    field: NamedField,
    rule: TimeRule,
}

/// The decoding plan of one message's point layout: for each used field its offset,
/// element type and byte order, checked against the point size.
///
/// Built by [`PointLayout::from_ros2`] or [`PointLayout::from_foxglove`]; the decoders
/// build it once per message and apply it to every point.
#[derive(Debug, Clone, PartialEq, Eq, Hash)]
pub struct PointLayout {
    point_step: usize,
    xyz: [FieldPlan; 3],
    intensity: Option<NamedField>,
    ring: Option<NamedField>,
    time: Option<TimePlan>,
}

/// The result of decoding one message.
#[derive(Debug, Clone, PartialEq)]
pub struct DecodedCloud {
    /// The finite points, in message order, with their attributes.
    pub cloud: PointCloud,
    /// Points left out because `x`, `y` or `z` was not finite (no-return points of
    /// organized clouds, corrupt points).
    pub dropped_non_finite: usize,
    /// Whether the message has an intensity field (`intensity`, `i` or `reflectivity`);
    /// when `false`, every intensity is 0.
    pub has_intensity: bool,
    /// How the per-point time was read (inferred or as configured); `None` when the
    /// message has no time field.
    pub time_field: Option<TimeFieldSpec>,
}

// ---------------------------------------------------------------------------------------
// Entry points
// ---------------------------------------------------------------------------------------

/// Decodes a ROS 2 `sensor_msgs/msg/PointCloud2` (see the module documentation for the
/// fields read and the time inference that `time` overrides).
pub fn decode_ros2(
    msg: &PointCloud2,
    time: Option<&TimeFieldSpec>,
) -> Result<DecodedCloud, PointsError> {
    let ctx = Ctx {
        frame_id: &msg.header.frame_id,
        stamp: msg.header.stamp.stamp(),
    };
    let layout = PointLayout::from_ros2(msg, time)?;
    let grid = ros2_grid(&ctx, msg)?;
    decode_core(&ctx, &layout, &msg.data, grid)
}

/// Decodes a `foxglove.PointCloud` (little-endian; see the module documentation for the
/// fields read, the time inference that `time` overrides and how `pose` is applied).
pub fn decode_foxglove(
    msg: &fox::PointCloud,
    time: Option<&TimeFieldSpec>,
) -> Result<DecodedCloud, PointsError> {
    let stamp = foxglove_stamp(msg)?;
    let ctx = Ctx {
        frame_id: &msg.frame_id,
        stamp,
    };
    let layout = PointLayout::from_foxglove(msg, time)?;
    let data: &[u8] = &msg.data;
    let stride = msg.point_stride as usize;
    // The layout has a coordinate inside every point, so the stride is at least 1.
    if stride == 0 || !data.len().is_multiple_of(stride) {
        return Err(PointsError::NotMultipleOfStride {
            frame_id: ctx.frame_id.to_string(),
            stamp,
            got: data.len(),
            point_stride: msg.point_stride,
        });
    }
    let grid = Grid {
        rows: 1,
        width: data.len() / stride,
        row_step: data.len(),
    };
    let pose = foxglove_pose(&ctx, msg)?;
    let mut decoded = decode_core(&ctx, &layout, data, grid)?;
    if let Some(frame_from_cloud) = pose {
        for p in &mut decoded.cloud.xyz {
            let q = frame_from_cloud
                * nalgebra::Point3::new(f64::from(p[0]), f64::from(p[1]), f64::from(p[2]));
            *p = [q.x as f32, q.y as f32, q.z as f32];
        }
    }
    Ok(decoded)
}

/// Decodes an MCAP message of a point-cloud channel (`sensor_msgs/msg/PointCloud2` in
/// CDR, or `foxglove.PointCloud` in protobuf) with [`decode_ros2`] or
/// [`decode_foxglove`].
pub fn decode_message(
    msg: &MessageRef<'_>,
    time: Option<&TimeFieldSpec>,
) -> Result<DecodedCloud, PointsError> {
    let channel = msg.channel;
    let undecodable = |source: DecodeError| PointsError::Message {
        topic: channel.topic.clone(),
        source: Box::new(source),
    };
    match schema_kind(channel) {
        Some((SchemaKind::PointCloud, Dialect::Ros2)) => {
            let cloud: PointCloud2 =
                ros2::decode(msg.data).map_err(|e| undecodable(DecodeError::from(e)))?;
            decode_ros2(&cloud, time)
        }
        Some((SchemaKind::PointCloud, Dialect::FoxgloveProtobuf)) => {
            let cloud: fox::PointCloud =
                fox::decode(FOXGLOVE_SCHEMA, msg.data).map_err(undecodable)?;
            decode_foxglove(&cloud, time)
        }
        _ => Err(PointsError::NotAPointCloud {
            topic: channel.topic.clone(),
            schema: channel.schema_name().to_string(),
            encoding: channel.message_encoding.clone(),
        }),
    }
}

// ---------------------------------------------------------------------------------------
// Layout
// ---------------------------------------------------------------------------------------

/// Frame and stamp of the message, for errors.
#[derive(Debug, Clone, Copy)]
struct Ctx<'a> {
    frame_id: &'a str,
    stamp: Stamp,
}

/// A field of either dialect, before checking.
#[derive(Debug, Clone, Copy)]
struct RawField<'a> {
    name: &'a str,
    offset: u32,
    numeric: Result<NumericType, i64>,
    count: u32,
}

impl PointLayout {
    /// The plan for a ROS 2 `PointCloud2`'s `fields`, `point_step` and `is_bigendian`.
    pub fn from_ros2(msg: &PointCloud2, time: Option<&TimeFieldSpec>) -> Result<Self, PointsError> {
        let ctx = Ctx {
            frame_id: &msg.header.frame_id,
            stamp: msg.header.stamp.stamp(),
        };
        let fields: Vec<RawField<'_>> = msg
            .fields
            .iter()
            .map(|f| RawField {
                name: &f.name,
                offset: f.offset,
                numeric: NumericType::from_ros2(f.datatype).ok_or(i64::from(f.datatype)),
                count: f.count,
            })
            .collect();
        let endianness = if msg.is_bigendian {
            Endianness::Big
        } else {
            Endianness::Little
        };
        Self::build(
            &ctx,
            &fields,
            msg.point_step,
            endianness,
            "ROS PointField",
            time,
        )
    }

    /// The plan for a `foxglove.PointCloud`'s `fields` and `point_stride`
    /// (little-endian).
    pub fn from_foxglove(
        msg: &fox::PointCloud,
        time: Option<&TimeFieldSpec>,
    ) -> Result<Self, PointsError> {
        let ctx = Ctx {
            frame_id: &msg.frame_id,
            stamp: foxglove_stamp(msg)?,
        };
        let fields: Vec<RawField<'_>> = msg
            .fields
            .iter()
            .map(|f| RawField {
                name: &f.name,
                offset: f.offset,
                numeric: NumericType::from_foxglove(f.r#type).ok_or(i64::from(f.r#type)),
                count: 1,
            })
            .collect();
        Self::build(
            &ctx,
            &fields,
            msg.point_stride,
            Endianness::Little,
            "Foxglove NumericType",
            time,
        )
    }

    /// Bytes per point.
    pub fn point_step(&self) -> usize {
        self.point_step
    }

    /// The plans of `x`, `y` and `z`.
    pub fn xyz(&self) -> [FieldPlan; 3] {
        self.xyz
    }

    /// The intensity field, if any.
    pub fn intensity(&self) -> Option<&NamedField> {
        self.intensity.as_ref()
    }

    /// The ring field, if any.
    pub fn ring(&self) -> Option<&NamedField> {
        self.ring.as_ref()
    }

    /// The per-point time field, if any.
    pub fn time(&self) -> Option<&NamedField> {
        self.time.as_ref().map(|t| &t.field)
    }

    fn build(
        ctx: &Ctx<'_>,
        fields: &[RawField<'_>],
        point_step: u32,
        endianness: Endianness,
        dialect: &'static str,
        time: Option<&TimeFieldSpec>,
    ) -> Result<Self, PointsError> {
        let names = || fields.iter().map(|f| f.name).collect::<Vec<_>>().join(", ");
        let find = |wanted: &[&str]| {
            wanted
                .iter()
                .find_map(|name| fields.iter().find(|f| f.name == *name))
        };
        let plan = |f: &RawField<'_>| -> Result<FieldPlan, PointsError> {
            if f.count != 1 {
                return Err(PointsError::FieldCount {
                    frame_id: ctx.frame_id.to_string(),
                    stamp: ctx.stamp,
                    field: f.name.to_string(),
                    count: f.count,
                });
            }
            let numeric = f.numeric.map_err(|datatype| PointsError::UnknownDatatype {
                frame_id: ctx.frame_id.to_string(),
                stamp: ctx.stamp,
                field: f.name.to_string(),
                dialect,
                datatype,
            })?;
            if u64::from(f.offset) + numeric.size() as u64 > u64::from(point_step) {
                return Err(PointsError::FieldPastPointStep {
                    frame_id: ctx.frame_id.to_string(),
                    stamp: ctx.stamp,
                    field: f.name.to_string(),
                    offset: f.offset,
                    size: numeric.size(),
                    point_step,
                });
            }
            Ok(FieldPlan {
                offset: f.offset as usize,
                numeric,
                endianness,
            })
        };
        let named = |f: &RawField<'_>| -> Result<NamedField, PointsError> {
            Ok(NamedField {
                name: f.name.to_string(),
                plan: plan(f)?,
            })
        };

        let coordinate = |axis: &'static str| -> Result<FieldPlan, PointsError> {
            let field = find(&[axis]).ok_or_else(|| PointsError::MissingCoordinate {
                frame_id: ctx.frame_id.to_string(),
                stamp: ctx.stamp,
                axis,
                fields: names(),
            })?;
            plan(field)
        };
        let xyz = [coordinate("x")?, coordinate("y")?, coordinate("z")?];

        let intensity = find(&INTENSITY_NAMES)
            .or_else(|| find(&[INTENSITY_FALLBACK]))
            .map(named)
            .transpose()?;
        let ring = find(&RING_NAMES).map(named).transpose()?;
        let time = match time {
            Some(spec) => {
                let field =
                    find(&[spec.name.as_str()]).ok_or_else(|| PointsError::MissingTimeField {
                        frame_id: ctx.frame_id.to_string(),
                        stamp: ctx.stamp,
                        name: spec.name.clone(),
                        fields: names(),
                    })?;
                Some(TimePlan {
                    field: named(field)?,
                    rule: TimeRule::Fixed(spec.unit, spec.reference),
                })
            }
            None => find(&TIME_NAMES)
                .map(|f| -> Result<TimePlan, PointsError> {
                    let field = named(f)?;
                    let rule = if field.plan.numeric.is_float() {
                        TimeRule::ByMagnitude
                    } else {
                        TimeRule::Fixed(TimeUnit::Nanoseconds, TimeReference::RelativeToStamp)
                    };
                    Ok(TimePlan { field, rule })
                })
                .transpose()?,
        };
        Ok(Self {
            point_step: point_step as usize,
            xyz,
            intensity,
            ring,
            time,
        })
    }
}

// ---------------------------------------------------------------------------------------
// Geometry of the data
// ---------------------------------------------------------------------------------------

/// Where the points lie in `data`: `rows` rows `row_step` bytes apart, each starting
/// with `width` points. Checked against the data's length before use.
#[derive(Debug, Clone, Copy)]
struct Grid {
    rows: usize,
    width: usize,
    row_step: usize,
}

/// The grid of a ROS cloud, checked against its data.
fn ros2_grid(ctx: &Ctx<'_>, msg: &PointCloud2) -> Result<Grid, PointsError> {
    let row_len = u64::from(msg.width) * u64::from(msg.point_step);
    let row_step = if msg.row_step == 0 {
        row_len
    } else {
        u64::from(msg.row_step)
    };
    if row_step < row_len {
        return Err(PointsError::RowStepTooShort {
            frame_id: ctx.frame_id.to_string(),
            stamp: ctx.stamp,
            row_step: msg.row_step,
            width: msg.width,
            point_step: msg.point_step,
        });
    }
    let height = u64::from(msg.height);
    let full = row_step * height;
    // The last row's padding may be left out.
    let trimmed = full - if height > 0 { row_step - row_len } else { 0 };
    let got = msg.data.len() as u64;
    if got != full && got != trimmed {
        return Err(PointsError::DataLength {
            frame_id: ctx.frame_id.to_string(),
            stamp: ctx.stamp,
            got: msg.data.len(),
            expected: full,
            width: msg.width,
            height: msg.height,
            point_step: msg.point_step,
            row_step: msg.row_step,
        });
    }
    // Every product is now at most `data.len()`, so it fits; a zero-width grid has no
    // rows to visit.
    Ok(Grid {
        rows: if msg.width == 0 {
            0
        } else {
            msg.height as usize
        },
        width: msg.width as usize,
        row_step: row_step as usize,
    })
}

/// The stamp of a Foxglove cloud.
fn foxglove_stamp(msg: &fox::PointCloud) -> Result<Stamp, PointsError> {
    fox::stamp(FOXGLOVE_SCHEMA, msg.timestamp.as_ref()).map_err(|_| PointsError::MissingTimestamp {
        frame_id: msg.frame_id.clone(),
    })
}

/// `frame_id_from_cloud` of a Foxglove cloud; `None` when absent or the identity.
fn foxglove_pose(
    ctx: &Ctx<'_>,
    msg: &fox::PointCloud,
) -> Result<Option<nalgebra::Isometry3<f64>>, PointsError> {
    let Some(pose) = msg.pose else {
        return Ok(None);
    };
    let t = pose.position.unwrap_or_default();
    let q = pose
        .orientation
        .map_or([0.0, 0.0, 0.0, 1.0], |q| [q.x, q.y, q.z, q.w]);
    let iso = super::isometry(ctx.stamp, ctx.frame_id, "cloud origin", [t.x, t.y, t.z], q)
        .map_err(|e| PointsError::BadPose {
            frame_id: ctx.frame_id.to_string(),
            stamp: ctx.stamp,
            reason: e.to_string(),
        })?;
    let identity =
        iso.translation.vector == nalgebra::Vector3::zeros() && iso.rotation.angle() == 0.0;
    Ok((!identity).then_some(iso))
}

// ---------------------------------------------------------------------------------------
// The per-point loop
// ---------------------------------------------------------------------------------------

/// Converts a time field's value into the offset from the stamp in seconds:
/// `(value - whole) / per_second - frac_secs`, where `whole + frac` is the stamp for an
/// absolute field (split so that the large part cancels exactly) and 0 for a relative one.
#[derive(Debug, Clone, Copy)]
struct TimeConversion {
    field: FieldPlan,
    per_second: f64,
    whole: f64,
    frac_secs: f64,
}

impl TimeConversion {
    fn new(field: FieldPlan, unit: TimeUnit, reference: TimeReference, stamp: Stamp) -> Self {
        let (whole, frac_secs) = match reference {
            TimeReference::RelativeToStamp => (0.0, 0.0),
            TimeReference::Absolute => {
                let per_unit = unit.nanos();
                let nanos = stamp.nanos();
                (
                    nanos.div_euclid(per_unit) as f64,
                    nanos.rem_euclid(per_unit) as f64 / 1e9,
                )
            }
        };
        Self {
            field,
            per_second: unit.per_second(),
            whole,
            frac_secs,
        }
    }

    #[inline]
    fn offset_secs(self, value: f64) -> f64 {
        (value - self.whole) / self.per_second - self.frac_secs
    }
}

/// The bytes of each row's points.
fn rows(data: &[u8], grid: Grid, point_step: usize) -> impl Iterator<Item = &[u8]> {
    let row_len = grid.width * point_step;
    (0..grid.rows).map(move |r| {
        let start = r * grid.row_step;
        data.get(start..start + row_len).unwrap_or(&[])
    })
}

/// The unit and reference of a float time field whose largest magnitude over the kept
/// points is `max_abs` (see the module documentation).
fn magnitude_rule(max_abs: f64) -> (TimeUnit, TimeReference) {
    if max_abs > NANOSECONDS_THRESHOLD {
        (TimeUnit::Nanoseconds, TimeReference::Absolute)
    } else if max_abs > MICROSECONDS_THRESHOLD {
        (TimeUnit::Microseconds, TimeReference::Absolute)
    } else if max_abs > ABSOLUTE_THRESHOLD {
        (TimeUnit::Seconds, TimeReference::Absolute)
    } else {
        (TimeUnit::Seconds, TimeReference::RelativeToStamp)
    }
}

/// Reads the position of a point. Implemented once for any layout ([`AnyXyz`]) and once,
/// without a type dispatch per point, for the usual FLOAT32 coordinates ([`Float32Xyz`]).
trait XyzReader: Copy {
    fn xyz(self, point: &[u8]) -> [f32; 3];
}

/// FLOAT32 `x`, `y`, `z` at these offsets, big-endian when `BIG`.
#[derive(Debug, Clone, Copy)]
struct Float32Xyz<const BIG: bool>([usize; 3]);

impl<const BIG: bool> XyzReader for Float32Xyz<BIG> {
    #[inline(always)]
    fn xyz(self, point: &[u8]) -> [f32; 3] {
        self.0.map(|offset| {
            let bytes = array::<4>(point, offset);
            if BIG {
                f32::from_be_bytes(bytes)
            } else {
                f32::from_le_bytes(bytes)
            }
        })
    }
}

/// Coordinates of any type.
#[derive(Debug, Clone, Copy)]
struct AnyXyz([FieldPlan; 3]);

impl XyzReader for AnyXyz {
    #[inline(always)]
    fn xyz(self, point: &[u8]) -> [f32; 3] {
        self.0.map(|f| f.read(point) as f32)
    }
}

/// The optional attributes to read from each kept point.
#[derive(Debug, Clone, Copy)]
struct Attributes {
    intensity: Option<FieldPlan>,
    ring: Option<FieldPlan>,
    time: Option<TimeConversion>,
}

/// The columns of the kept points.
#[derive(Debug)]
struct Points {
    xyz: Vec<[f32; 3]>,
    intensity: Vec<f32>,
    ring: Option<Vec<u16>>,
    time_offset: Option<Vec<f32>>,
    dropped: usize,
    /// The largest `|value|` of the time field over the kept points (0 without one).
    max_abs_time: f64,
}

/// The per-point loop: reads every point of `data` (laid out as `grid`), drops the
/// non-finite ones and converts the attributes of the others.
#[inline(always)]
fn fill<X: XyzReader>(
    ctx: &Ctx<'_>,
    layout: &PointLayout,
    data: &[u8],
    grid: Grid,
    capacity: usize,
    position: X,
    attributes: Attributes,
) -> Result<Points, PointsError> {
    let step = layout.point_step.max(1);
    let Attributes {
        intensity: intensity_plan,
        ring: ring_plan,
        time,
    } = attributes;
    // Columns of `capacity` (the number of points) zeros, written in place and cut to the
    // kept points at the end: no capacity checks or growth calls in the loop.
    let sized = |wanted: bool| if wanted { capacity } else { 0 };
    let mut xyz = vec![[0f32; 3]; capacity];
    let mut intensity = vec![0f32; capacity];
    let mut ring = vec![0u16; sized(ring_plan.is_some())];
    let mut time_offset = vec![0f32; sized(time.is_some())];
    let mut kept = 0usize;
    let mut index = 0usize;
    let mut max_abs_time = 0.0f64;

    for row in rows(data, grid, step) {
        for p in row.chunks_exact(step) {
            let i = index;
            index += 1;
            let [x, y, z] = position.xyz(p);
            if !(x.is_finite() && y.is_finite() && z.is_finite()) {
                continue;
            }
            if let Some(slot) = xyz.get_mut(kept) {
                *slot = [x, y, z];
            }
            if let (Some(plan), Some(slot)) = (intensity_plan, intensity.get_mut(kept)) {
                *slot = plan.read(p) as f32;
            }
            if let (Some(plan), Some(slot)) = (ring_plan, ring.get_mut(kept)) {
                let value = plan.read(p);
                // The cast saturates (NaN gives 0): the value is a ring index exactly when
                // it survives the round trip.
                let ring_index = value as u16;
                if f64::from(ring_index) != value {
                    return Err(bad_value(ctx, layout.ring.as_ref(), i, value, true));
                }
                *slot = ring_index;
            }
            if let (Some(conv), Some(slot)) = (time, time_offset.get_mut(kept)) {
                let value = conv.field.read(p);
                max_abs_time = max_abs_time.max(value.abs());
                let offset = conv.offset_secs(value) as f32;
                if !offset.is_finite() {
                    return Err(bad_value(ctx, layout.time(), i, value, false));
                }
                *slot = offset;
            }
            kept += 1;
        }
    }

    xyz.truncate(kept);
    intensity.truncate(kept);
    ring.truncate(kept);
    time_offset.truncate(kept);
    Ok(Points {
        xyz,
        intensity,
        ring: ring_plan.map(|_| ring),
        time_offset: time.map(|_| time_offset),
        dropped: index - kept,
        max_abs_time,
    })
}

/// The error for a ring (`ring` true) or time value that cannot be converted.
#[cold]
fn bad_value(
    ctx: &Ctx<'_>,
    field: Option<&NamedField>,
    index: usize,
    value: f64,
    ring: bool,
) -> PointsError {
    let frame_id = ctx.frame_id.to_string();
    let stamp = ctx.stamp;
    let field = field.map_or_else(String::new, |f| f.name.clone());
    if ring {
        PointsError::BadRing {
            frame_id,
            stamp,
            field,
            index,
            value,
        }
    } else {
        PointsError::BadTime {
            frame_id,
            stamp,
            field,
            index,
            value,
        }
    }
}

/// Applies `layout` to every point of `data` (laid out as `grid`, already checked).
///
/// A float time field under inference is first read as relative seconds (velodyne, the
/// common case) while its largest magnitude is tracked; only when that shows absolute
/// values is the time column read again, with the inferred unit and the stamp
/// subtracted. The decision thus rests on the kept points only, and costs no extra pass
/// over relative clouds.
fn decode_core(
    ctx: &Ctx<'_>,
    layout: &PointLayout,
    data: &[u8],
    grid: Grid,
) -> Result<DecodedCloud, PointsError> {
    // A validated layout has a field inside every point, so this is at least 1.
    let step = layout.point_step.max(1);
    let capacity = grid.rows.saturating_mul(grid.width).min(data.len() / step);
    let [px, py, pz] = layout.xyz;
    let float32 = [px, py, pz]
        .iter()
        .all(|f| f.numeric == NumericType::Float32);
    let offsets = [px.offset, py.offset, pz.offset];
    let run = |attributes: Attributes| match (float32, px.endianness) {
        (true, Endianness::Little) => {
            let position = Float32Xyz::<false>(offsets);
            fill(ctx, layout, data, grid, capacity, position, attributes)
        }
        (true, Endianness::Big) => {
            let position = Float32Xyz::<true>(offsets);
            fill(ctx, layout, data, grid, capacity, position, attributes)
        }
        (false, _) => fill(
            ctx,
            layout,
            data,
            grid,
            capacity,
            AnyXyz(layout.xyz),
            attributes,
        ),
    };

    let (first_unit, first_reference) = match layout.time.as_ref().map(|t| t.rule) {
        Some(TimeRule::Fixed(unit, reference)) => (unit, reference),
        _ => (TimeUnit::Seconds, TimeReference::RelativeToStamp),
    };
    let time_conversion = |unit, reference| {
        layout
            .time
            .as_ref()
            .map(|t| TimeConversion::new(t.field.plan, unit, reference, ctx.stamp))
    };
    let mut points = run(Attributes {
        intensity: layout.intensity.as_ref().map(|f| f.plan),
        ring: layout.ring.as_ref().map(|f| f.plan),
        time: time_conversion(first_unit, first_reference),
    })?;

    let time_field = match &layout.time {
        None => None,
        Some(plan) => {
            let (unit, reference) = match plan.rule {
                TimeRule::Fixed(unit, reference) => (unit, reference),
                TimeRule::ByMagnitude => magnitude_rule(points.max_abs_time),
            };
            if (unit, reference) != (first_unit, first_reference) {
                points.time_offset = run(Attributes {
                    intensity: None,
                    ring: None,
                    time: time_conversion(unit, reference),
                })?
                .time_offset;
            }
            Some(TimeFieldSpec {
                name: plan.field.name.clone(),
                unit,
                reference,
            })
        }
    };

    Ok(DecodedCloud {
        cloud: PointCloud {
            stamp: ctx.stamp,
            frame_id: ctx.frame_id.to_string(),
            xyz: points.xyz,
            intensity: points.intensity,
            ring: points.ring,
            time_offset_secs: points.time_offset,
        },
        dropped_non_finite: points.dropped,
        has_intensity: layout.intensity.is_some(),
        time_field,
    })
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::decode::ros2::{Header, PointField, Ros2Time};
    use crate::source::{ChannelInfo, MessageLoc, SchemaInfo};
    use ::foxglove::messages::packed_element_field::NumericType as FoxType;
    use ::foxglove::messages::{PackedElementField, Pose, Quaternion, Timestamp, Vector3};
    use prost::Message as _;
    use std::collections::BTreeMap;
    use std::sync::Arc;

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
    fn points(
        n: usize,
        step: usize,
        big: bool,
        mut write: impl FnMut(usize, &mut Pt<'_>),
    ) -> Vec<u8> {
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

    // ----- Hesai / Livox (absolute time) -----

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

    // ----- Autoware -----

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

    // ----- explicit time specification -----

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

    // ----- errors -----

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

    // ----- decode_message -----

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

    // ----- never panics -----

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

    use crate::test_rng::TestRng as Rng;

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
                    [TimeReference::Absolute, TimeReference::RelativeToStamp]
                        [rng.below(2) as usize],
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
}
