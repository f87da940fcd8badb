//! [`PointsError`]: why a point cloud cannot be decoded. Every variant about a message
//! names its frame id and stamp; the caller adds the file and topic.

use crate::decode::error::DecodeError;
use superflow_schemas::Stamp;

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
    /// The time field named by a [`TimeFieldSpec`](super::TimeFieldSpec) is absent.
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
    /// Labels were asked for and no field holds them.
    #[error(
        "point cloud `{frame_id}` at {stamp}: no label field ({wanted}, regardless of case; fields: {fields})"
    )]
    MissingLabelField {
        /// Frame of the cloud.
        frame_id: String,
        /// Its stamp.
        stamp: Stamp,
        /// The names looked for.
        wanted: String,
        /// The field names present, comma-separated.
        fields: String,
    },
    /// A label value that is not a class id (a non-negative integer below 2^32).
    #[error(
        "point cloud `{frame_id}` at {stamp}: point {index} has label field `{field}` = {value}, not a class id (a non-negative integer below 2^32)"
    )]
    BadLabel {
        /// Frame of the cloud.
        frame_id: String,
        /// Its stamp.
        stamp: Stamp,
        /// Name of the label field.
        field: String,
        /// Index of the point in the message (invalid points counted).
        index: usize,
        /// The recorded value.
        value: f64,
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
    /// [`decode_message`](super::decode_message) on a channel that does not carry point clouds.
    #[error("`{topic}`: schema `{schema}` with message encoding `{encoding}` is not a point cloud")]
    NotAPointCloud {
        /// Topic of the channel.
        topic: String,
        /// Schema name.
        schema: String,
        /// Message encoding.
        encoding: String,
    },
    /// [`decode_message`](super::decode_message) on a payload that does not decode as its schema.
    #[error("`{topic}`: {source}")]
    Message {
        /// Topic of the channel.
        topic: String,
        /// The payload's decoding error.
        source: Box<DecodeError>,
    },
}
