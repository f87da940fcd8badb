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
//! | Hesai `PointXYZIT` | x0 y4 z8, intensity16 (FLOAT32), timestamp24 (FLOAT64 absolute s), ring32 (UINT16) | 48 |
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
//! `max |v|` is taken over the finite values of the whole cloud (one extra pass over the
//! time field, only for float time fields), so that a few zero times on invalid points do
//! not flip the decision. A relative field cannot reach 1e8 s (three years); an absolute
//! one is at least 1e8 s past the epoch for any date after 1973. A float field that holds
//! time since boot (< 1e8 s) is indistinguishable from a relative one: pass a
//! [`TimeFieldSpec`] for such a recorder.
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
    #[inline]
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
    if stride == 0 || data.len() % stride != 0 {
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
fn rows<'a>(data: &'a [u8], grid: Grid, point_step: usize) -> impl Iterator<Item = &'a [u8]> {
    let row_len = grid.width * point_step;
    (0..grid.rows).map(move |r| {
        let start = r * grid.row_step;
        data.get(start..start + row_len).unwrap_or(&[])
    })
}

/// The interpretation of the time field for this cloud: fixed, or decided by the
/// largest finite magnitude of its values (see the module documentation).
fn resolve_time(plan: &TimePlan, data: &[u8], grid: Grid, point_step: usize) -> TimeFieldSpec {
    let (unit, reference) = match plan.rule {
        TimeRule::Fixed(unit, reference) => (unit, reference),
        TimeRule::ByMagnitude => {
            let field = plan.field.plan;
            let max = rows(data, grid, point_step)
                .flat_map(|row| row.chunks_exact(point_step))
                .map(|p| field.read(p).abs())
                .filter(|v| v.is_finite())
                .fold(0.0, f64::max);
            if max > NANOSECONDS_THRESHOLD {
                (TimeUnit::Nanoseconds, TimeReference::Absolute)
            } else if max > MICROSECONDS_THRESHOLD {
                (TimeUnit::Microseconds, TimeReference::Absolute)
            } else if max > ABSOLUTE_THRESHOLD {
                (TimeUnit::Seconds, TimeReference::Absolute)
            } else {
                (TimeUnit::Seconds, TimeReference::RelativeToStamp)
            }
        }
    };
    TimeFieldSpec {
        name: plan.field.name.clone(),
        unit,
        reference,
    }
}

/// Applies `layout` to every point of `data` (laid out as `grid`, already checked).
fn decode_core(
    ctx: &Ctx<'_>,
    layout: &PointLayout,
    data: &[u8],
    grid: Grid,
) -> Result<DecodedCloud, PointsError> {
    // A validated layout has a field inside every point, so this is at least 1.
    let step = layout.point_step.max(1);
    let capacity = grid.rows.saturating_mul(grid.width).min(data.len() / step);
    let time_field = layout
        .time
        .as_ref()
        .map(|plan| resolve_time(plan, data, grid, step));
    let time = layout
        .time
        .as_ref()
        .zip(time_field.as_ref())
        .map(|(plan, spec)| {
            TimeConversion::new(plan.field.plan, spec.unit, spec.reference, ctx.stamp)
        });
    let [px, py, pz] = layout.xyz;
    let intensity_plan = layout.intensity.as_ref().map(|f| f.plan);
    let ring_plan = layout.ring.as_ref().map(|f| f.plan);

    let mut xyz = Vec::with_capacity(capacity);
    let mut intensity = Vec::with_capacity(capacity);
    let mut ring = ring_plan.map(|_| Vec::with_capacity(capacity));
    let mut time_offset = time.map(|_| Vec::with_capacity(capacity));
    let mut dropped = 0usize;
    let mut index = 0usize;

    for row in rows(data, grid, step) {
        for p in row.chunks_exact(step) {
            let i = index;
            index += 1;
            let (x, y, z) = (px.read(p) as f32, py.read(p) as f32, pz.read(p) as f32);
            if !(x.is_finite() && y.is_finite() && z.is_finite()) {
                dropped += 1;
                continue;
            }
            xyz.push([x, y, z]);
            intensity.push(intensity_plan.map_or(0.0, |f| f.read(p) as f32));
            if let (Some(plan), Some(out)) = (ring_plan, ring.as_mut()) {
                let value = plan.read(p);
                if !(value.fract() == 0.0 && (0.0..=f64::from(u16::MAX)).contains(&value)) {
                    return Err(PointsError::BadRing {
                        frame_id: ctx.frame_id.to_string(),
                        stamp: ctx.stamp,
                        field: layout.ring.as_ref().map_or("", |f| &f.name).to_string(),
                        index: i,
                        value,
                    });
                }
                out.push(value as u16);
            }
            if let (Some(conv), Some(out)) = (time, time_offset.as_mut()) {
                let value = conv.field.read(p);
                let offset = conv.offset_secs(value) as f32;
                if !offset.is_finite() {
                    return Err(PointsError::BadTime {
                        frame_id: ctx.frame_id.to_string(),
                        stamp: ctx.stamp,
                        field: layout.time().map_or("", |f| &f.name).to_string(),
                        index: i,
                        value,
                    });
                }
                out.push(offset);
            }
        }
    }

    Ok(DecodedCloud {
        cloud: PointCloud {
            stamp: ctx.stamp,
            frame_id: ctx.frame_id.to_string(),
            xyz,
            intensity,
            ring,
            time_offset_secs: time_offset,
        },
        dropped_non_finite: dropped,
        has_intensity: intensity_plan.is_some(),
        time_field,
    })
}
