//! Label-only clouds ([`LabelCloud`]): the parallel cloud of a `<drive>.labels.mcap`
//! sidecar, one raw id per point, read by the rules of [`super::label`]; and the field
//! names of a cloud, to tell whether it carries labels.

use super::dialect::{AnyCloud, foxglove_grid, ros2_grid};
use super::error::PointsError;
use super::grid::{Grid, rows};
use super::label::{LabelFieldSpec, LabelPlan, bad_label};
use super::layout::FieldList;
use crate::decode::foxglove as fox;
use crate::decode::ros2::PointCloud2;
use crate::source::MessageRef;
use superflow_schemas::Stamp;

/// A label-only cloud: one raw id per point, in message order (invalid points of the
/// LiDAR cloud it parallels included: nothing is dropped).
#[derive(Debug, Clone, PartialEq, Eq)]
pub struct LabelCloud {
    /// The message's stamp.
    pub stamp: Stamp,
    /// The message's frame.
    pub frame_id: String,
    /// The field the ids were read from.
    pub field: String,
    /// Raw ids (masked), one per point.
    pub labels: Vec<u32>,
}

/// Reads the label of every point of `data` laid out as `grid`.
fn read_labels(
    list: &FieldList<'_>,
    plan: &LabelPlan,
    data: &[u8],
    grid: Grid,
) -> Result<LabelCloud, PointsError> {
    let step = (list.point_step() as usize).max(1);
    let capacity = grid.rows.saturating_mul(grid.width).min(data.len() / step);
    let mut labels = Vec::with_capacity(capacity);
    for row in rows(data, grid, step) {
        for point in row.chunks_exact(step) {
            let id = plan.read(point).map_err(|value| {
                let ctx = &list.ctx;
                bad_label(
                    ctx.frame_id,
                    ctx.stamp,
                    &plan.field.name,
                    labels.len(),
                    value,
                )
            })?;
            labels.push(id);
        }
    }
    Ok(LabelCloud {
        stamp: list.ctx.stamp,
        frame_id: list.ctx.id(),
        field: plan.field.name.clone(),
        labels,
    })
}

/// The labels of a ROS 2 `PointCloud2` that carries only them (or anything else as well):
/// the field of `spec`, else its only field.
pub fn decode_labels_ros2(
    msg: &PointCloud2,
    spec: &LabelFieldSpec,
) -> Result<LabelCloud, PointsError> {
    let list = FieldList::ros2(msg);
    let plan = list.label(spec, true)?;
    let grid = ros2_grid(&list.ctx, msg)?;
    read_labels(&list, &plan, &msg.data, grid)
}

/// The labels of a `foxglove.PointCloud` that carries only them (or anything else as
/// well): the field of `spec`, else its only field.
pub fn decode_labels_foxglove(
    msg: &fox::PointCloud,
    spec: &LabelFieldSpec,
) -> Result<LabelCloud, PointsError> {
    let list = FieldList::foxglove(msg)?;
    let plan = list.label(spec, true)?;
    let grid = foxglove_grid(&list.ctx, msg)?;
    read_labels(&list, &plan, &msg.data, grid)
}

/// [`decode_labels_ros2`] or [`decode_labels_foxglove`] of an MCAP message, by its
/// channel's schema.
pub fn decode_labels_message(
    msg: &MessageRef<'_>,
    spec: &LabelFieldSpec,
) -> Result<LabelCloud, PointsError> {
    match AnyCloud::decode(msg)? {
        AnyCloud::Ros2(cloud) => decode_labels_ros2(&cloud, spec),
        AnyCloud::Foxglove(cloud) => decode_labels_foxglove(&cloud, spec),
    }
}

/// The field names of a point-cloud message (to tell whether it carries labels).
pub fn field_names(msg: &MessageRef<'_>) -> Result<Vec<String>, PointsError> {
    Ok(match AnyCloud::decode(msg)? {
        AnyCloud::Ros2(cloud) => cloud.fields.into_iter().map(|f| f.name).collect(),
        AnyCloud::Foxglove(cloud) => cloud.fields.into_iter().map(|f| f.name).collect(),
    })
}

/// The label field `spec` picks among `names` (as [`LABEL_NAMES`](super::LABEL_NAMES) and the configured
/// name are matched: regardless of case), if any.
pub fn find_label_field<'n>(names: &'n [String], spec: &LabelFieldSpec) -> Option<&'n str> {
    spec.names().iter().find_map(|wanted| {
        names
            .iter()
            .find(|n| n.eq_ignore_ascii_case(wanted))
            .map(String::as_str)
    })
}
