//! Per-point semantic labels: which field holds them ([`LabelFieldSpec`]), how a stored
//! value becomes a raw class id (integral, non-negative, masked), and the decoding of a
//! label-only cloud ([`LabelCloud`], the parallel cloud of a `<drive>.labels.mcap`
//! sidecar).
//!
//! | form | field | types |
//! |---|---|---|
//! | in the LiDAR cloud | the configured name, else the first of [`LABEL_NAMES`] present (case-insensitive) | any integer type; FLOAT32 / FLOAT64 holding integers |
//! | a parallel label cloud | as above, else its only field | as above |
//!
//! A value is a raw id when it is an integer in `0..=u32::MAX` (a float with a fraction,
//! NaN or a negative value is [`PointsError::BadLabel`]). With a mask (SemanticKITTI packs
//! the instance in the upper 16 bits of a UINT32 `label`: mask `0xFFFF`) the id is
//! `value & mask`; a negative value of a signed integer field is then taken as its
//! two's-complement bits, so an INT32 field with instance bits set still masks right.

use super::PointsError;
use super::dialect::{AnyCloud, foxglove_grid, ros2_grid};
use super::layout::{FieldList, FieldPlan, NamedField};
use super::read::{Grid, rows};
use crate::decode::foxglove as fox;
use crate::decode::ros2::PointCloud2;
use crate::source::MessageRef;
use superflow_schemas::Stamp;

/// Names of the label field tried, in this order and regardless of case, when none is
/// configured.
pub const LABEL_NAMES: [&str; 5] = ["label", "class", "semantic", "semantic_label", "lidarseg"];

/// Which per-point field holds the semantic class and which of its bits are the class.
#[derive(Debug, Clone, Default, PartialEq, Eq, Hash)]
pub struct LabelFieldSpec {
    /// Field name, matched regardless of case; `None`: the first of [`LABEL_NAMES`]
    /// present.
    pub name: Option<String>,
    /// Bits of the stored value that are the class (`0xFFFF` for SemanticKITTI); `None`
    /// keeps the whole value.
    pub mask: Option<u32>,
}

impl LabelFieldSpec {
    /// The names looked for, in order: the configured one, else [`LABEL_NAMES`].
    pub(super) fn names(&self) -> Vec<&str> {
        match &self.name {
            Some(name) => vec![name.as_str()],
            None => LABEL_NAMES.to_vec(),
        }
    }

    /// The names looked for, for errors (`label` or `one of label, class, ...`).
    pub(super) fn wanted(&self) -> String {
        match &self.name {
            Some(name) => format!("`{name}`"),
            None => format!("one of {}", LABEL_NAMES.join(", ")),
        }
    }
}

/// The label field of a layout and its mask.
#[derive(Debug, Clone, PartialEq, Eq, Hash)]
pub(super) struct LabelPlan {
    /// The field.
    pub(super) field: NamedField,
    /// Bits kept.
    pub(super) mask: Option<u32>,
}

impl LabelPlan {
    /// The raw id of `point`, or the stored value when it is not one.
    #[inline(always)]
    pub(super) fn read(&self, point: &[u8]) -> Result<u32, f64> {
        raw_id(self.field.plan, point, self.mask)
    }
}

/// The raw id of the label `field` of `point` (see the module documentation), or the
/// stored value when it is not one.
#[inline(always)]
fn raw_id(field: FieldPlan, point: &[u8], mask: Option<u32>) -> Result<u32, f64> {
    let value = field.read(point);
    // NaN has a NaN fraction and fails the comparison like any fraction.
    if value.fract() != 0.0 {
        return Err(value);
    }
    let bits = if (0.0..=f64::from(u32::MAX)).contains(&value) {
        value as u32
    } else if value < 0.0 && mask.is_some() && !field.numeric.is_float() {
        // Integer fields are at most 32 bits: the low 32 bits of the sign extension
        // are the stored bits.
        value as i64 as u32
    } else {
        return Err(value);
    };
    Ok(mask.map_or(bits, |m| bits & m))
}

/// The error for a label value that is not a raw id.
#[cold]
pub(super) fn bad_label(
    frame_id: &str,
    stamp: Stamp,
    field: &str,
    index: usize,
    value: f64,
) -> PointsError {
    PointsError::BadLabel {
        frame_id: frame_id.to_string(),
        stamp,
        field: field.to_string(),
        index,
        value,
    }
}

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

/// The label field `spec` picks among `names` (as [`LABEL_NAMES`] and the configured
/// name are matched: regardless of case), if any.
pub fn find_label_field<'n>(names: &'n [String], spec: &LabelFieldSpec) -> Option<&'n str> {
    spec.names().iter().find_map(|wanted| {
        names
            .iter()
            .find(|n| n.eq_ignore_ascii_case(wanted))
            .map(String::as_str)
    })
}
