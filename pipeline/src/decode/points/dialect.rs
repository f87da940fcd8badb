//! The per-dialect entry points: ROS 2 `PointCloud2` (row geometry, endianness),
//! `foxglove.PointCloud` (stride, pose) and MCAP messages dispatched on their schema.

use super::cloud::DecodedCloud;
use super::error::PointsError;
use super::grid::Grid;
use super::label::LabelFieldSpec;
use super::layout::{FieldList, foxglove_ctx};
use super::read::decode_core;
use super::time::TimeFieldSpec;
use crate::decode::context::Ctx;
use crate::decode::error::DecodeError;
use crate::decode::foxglove as fox;
use crate::decode::ros2::{self, PointCloud2};
use crate::decode::schema::{Dialect, SchemaKind, schema_kind};
use crate::decode::transform;
use crate::source::MessageRef;

/// Schema name of `foxglove.PointCloud`.
const FOXGLOVE_SCHEMA: &str = "foxglove.PointCloud";

/// What to read of a cloud beyond positions, intensity and ring: the per-point time
/// (inferred unless given), the labels (not read unless given) and the message index of
/// each kept point (not recorded unless asked for).
#[derive(Debug, Clone, Copy, Default)]
pub struct CloudOptions<'a> {
    /// How to read the per-point time; `None` infers it (see the module documentation).
    pub time: Option<&'a TimeFieldSpec>,
    /// Which field holds the semantic labels; `None` reads none (and costs nothing).
    /// Given, the field is required and fills [`PointCloud::label`](superflow_schemas::sensor::PointCloud::label).
    pub label: Option<&'a LabelFieldSpec>,
    /// Record [`DecodedCloud::kept_indices`].
    pub kept_indices: bool,
}

/// Decodes a ROS 2 `sensor_msgs/msg/PointCloud2` (see the module documentation for the
/// fields read and the time inference that `time` overrides).
pub fn decode_ros2(
    msg: &PointCloud2,
    time: Option<&TimeFieldSpec>,
) -> Result<DecodedCloud, PointsError> {
    decode_ros2_with(
        msg,
        &CloudOptions {
            time,
            ..CloudOptions::default()
        },
    )
}

/// [`decode_ros2`] reading what `options` asks for.
pub fn decode_ros2_with(
    msg: &PointCloud2,
    options: &CloudOptions<'_>,
) -> Result<DecodedCloud, PointsError> {
    let ctx = Ctx::ros2(&msg.header);
    let layout = FieldList::ros2(msg).layout(options.time, options.label)?;
    let grid = ros2_grid(&ctx, msg)?;
    decode_core(&ctx, &layout, &msg.data, grid, options.kept_indices)
}

/// Decodes a `foxglove.PointCloud` (little-endian; see the module documentation for the
/// fields read, the time inference that `time` overrides and how `pose` is applied).
pub fn decode_foxglove(
    msg: &fox::PointCloud,
    time: Option<&TimeFieldSpec>,
) -> Result<DecodedCloud, PointsError> {
    decode_foxglove_with(
        msg,
        &CloudOptions {
            time,
            ..CloudOptions::default()
        },
    )
}

/// [`decode_foxglove`] reading what `options` asks for.
pub fn decode_foxglove_with(
    msg: &fox::PointCloud,
    options: &CloudOptions<'_>,
) -> Result<DecodedCloud, PointsError> {
    let ctx = foxglove_ctx(msg)?;
    let layout = FieldList::foxglove(msg)?.layout(options.time, options.label)?;
    let grid = foxglove_grid(&ctx, msg)?;
    let pose = foxglove_pose(&ctx, msg)?;
    let mut decoded = decode_core(&ctx, &layout, &msg.data, grid, options.kept_indices)?;
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
    decode_message_with(
        msg,
        &CloudOptions {
            time,
            ..CloudOptions::default()
        },
    )
}

/// [`decode_message`] reading what `options` asks for.
pub fn decode_message_with(
    msg: &MessageRef<'_>,
    options: &CloudOptions<'_>,
) -> Result<DecodedCloud, PointsError> {
    match AnyCloud::decode(msg)? {
        AnyCloud::Ros2(cloud) => decode_ros2_with(&cloud, options),
        AnyCloud::Foxglove(cloud) => decode_foxglove_with(&cloud, options),
    }
}

/// A point-cloud message of either dialect, decoded from its wire format.
#[derive(Debug)]
pub(super) enum AnyCloud {
    /// `sensor_msgs/msg/PointCloud2`.
    Ros2(PointCloud2),
    /// `foxglove.PointCloud`.
    Foxglove(fox::PointCloud),
}

impl AnyCloud {
    /// The message decoded by its channel's schema.
    pub(super) fn decode(msg: &MessageRef<'_>) -> Result<Self, PointsError> {
        let channel = msg.channel;
        let undecodable = |source: DecodeError| PointsError::Message {
            topic: channel.topic.clone(),
            source: Box::new(source),
        };
        match schema_kind(channel) {
            Some((SchemaKind::PointCloud, Dialect::Ros2)) => ros2::decode(msg.data)
                .map(AnyCloud::Ros2)
                .map_err(|e| undecodable(DecodeError::from(e))),
            Some((SchemaKind::PointCloud, Dialect::FoxgloveProtobuf)) => {
                fox::decode(FOXGLOVE_SCHEMA, msg.data)
                    .map(AnyCloud::Foxglove)
                    .map_err(undecodable)
            }
            _ => Err(PointsError::NotAPointCloud {
                topic: channel.topic.clone(),
                schema: channel.schema_name().to_string(),
                encoding: channel.message_encoding.clone(),
            }),
        }
    }
}

/// The grid of a Foxglove cloud: one row of `data.len() / point_stride` points.
pub(super) fn foxglove_grid(ctx: &Ctx<'_>, msg: &fox::PointCloud) -> Result<Grid, PointsError> {
    let data: &[u8] = &msg.data;
    let stride = msg.point_stride as usize;
    // The layout has a coordinate inside every point, so the stride is at least 1.
    if stride == 0 || !data.len().is_multiple_of(stride) {
        return Err(PointsError::NotMultipleOfStride {
            frame_id: ctx.id(),
            stamp: ctx.stamp,
            got: data.len(),
            point_stride: msg.point_stride,
        });
    }
    Ok(Grid {
        rows: 1,
        width: data.len() / stride,
        row_step: data.len(),
    })
}

/// The grid of a ROS cloud, checked against its data.
pub(super) fn ros2_grid(ctx: &Ctx<'_>, msg: &PointCloud2) -> Result<Grid, PointsError> {
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
    let iso = transform::isometry(ctx.stamp, ctx.frame_id, "cloud origin", [t.x, t.y, t.z], q)
        .map_err(|e| PointsError::BadPose {
            frame_id: ctx.frame_id.to_string(),
            stamp: ctx.stamp,
            reason: e.to_string(),
        })?;
    let identity =
        iso.translation.vector == nalgebra::Vector3::zeros() && iso.rotation.angle() == 0.0;
    Ok((!identity).then_some(iso))
}
