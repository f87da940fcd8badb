//! The per-message decoding plan ([`PointLayout`]) built from a ROS 2 or Foxglove field
//! list and checked against the point size (the fields' own types are in
//! [`super::field`]).

use super::error::PointsError;
use super::field::{Endianness, FieldPlan, NamedField, NumericType};
use super::label::{LabelFieldSpec, LabelPlan};
use super::time::{TIME_NAMES, TimeFieldSpec, TimePlan, TimeReference, TimeRule, TimeUnit};
use crate::decode::context::Ctx;
use crate::decode::foxglove as fox;
use crate::decode::ros2::PointCloud2;

/// Names of the intensity field, in order of preference.
const INTENSITY_NAMES: [&str; 2] = ["intensity", "i"];
/// Name of the intensity fallback, used only when no [`INTENSITY_NAMES`] field exists.
const INTENSITY_FALLBACK: &str = "reflectivity";
/// Names of the ring (beam index) field, in order of preference.
const RING_NAMES: [&str; 4] = ["ring", "channel", "laser_id", "line"];

/// The decoding plan of one message's point layout: for each used field its offset,
/// element type and byte order, checked against the point size.
///
/// Built by [`PointLayout::from_ros2`] or [`PointLayout::from_foxglove`]; the decoders
/// build it once per message and apply it to every point.
#[derive(Debug, Clone, PartialEq, Eq, Hash)]
pub struct PointLayout {
    pub(super) point_step: usize,
    pub(super) xyz: [FieldPlan; 3],
    pub(super) intensity: Option<NamedField>,
    pub(super) ring: Option<NamedField>,
    pub(super) time: Option<TimePlan>,
    /// The label field, only when the caller asked for labels.
    pub(super) label: Option<LabelPlan>,
}

/// A field of either dialect, before checking.
#[derive(Debug, Clone, Copy)]
pub(super) struct RawField<'a> {
    name: &'a str,
    offset: u32,
    numeric: Result<NumericType, i64>,
    count: u32,
}

/// The field list of one message with what checking its fields needs: the message's
/// context, the point size, the byte order and the dialect's name of its datatypes.
#[derive(Debug)]
pub(super) struct FieldList<'a> {
    pub(super) ctx: Ctx<'a>,
    fields: Vec<RawField<'a>>,
    point_step: u32,
    endianness: Endianness,
    /// `"ROS PointField"` or `"Foxglove NumericType"`, for errors.
    dialect: &'static str,
}

impl<'a> FieldList<'a> {
    /// The field list of a ROS 2 `PointCloud2` (`fields`, `point_step`, `is_bigendian`).
    pub(super) fn ros2(msg: &'a PointCloud2) -> Self {
        let fields = msg
            .fields
            .iter()
            .map(|f| RawField {
                name: &f.name,
                offset: f.offset,
                numeric: NumericType::from_ros2(f.datatype).ok_or(i64::from(f.datatype)),
                count: f.count,
            })
            .collect();
        FieldList {
            ctx: Ctx::ros2(&msg.header),
            fields,
            point_step: msg.point_step,
            endianness: if msg.is_bigendian {
                Endianness::Big
            } else {
                Endianness::Little
            },
            dialect: "ROS PointField",
        }
    }

    /// The field list of a `foxglove.PointCloud` (`fields`, `point_stride`,
    /// little-endian); an error without a timestamp.
    pub(super) fn foxglove(msg: &'a fox::PointCloud) -> Result<Self, PointsError> {
        let fields = msg
            .fields
            .iter()
            .map(|f| RawField {
                name: &f.name,
                offset: f.offset,
                numeric: NumericType::from_foxglove(f.r#type).ok_or(i64::from(f.r#type)),
                count: 1,
            })
            .collect();
        Ok(FieldList {
            ctx: foxglove_ctx(msg)?,
            fields,
            point_step: msg.point_stride,
            endianness: Endianness::Little,
            dialect: "Foxglove NumericType",
        })
    }
}

impl PointLayout {
    /// The plan for a ROS 2 `PointCloud2`'s `fields`, `point_step` and `is_bigendian`.
    pub fn from_ros2(msg: &PointCloud2, time: Option<&TimeFieldSpec>) -> Result<Self, PointsError> {
        FieldList::ros2(msg).layout(time, None)
    }

    /// The plan for a `foxglove.PointCloud`'s `fields` and `point_stride`
    /// (little-endian).
    pub fn from_foxglove(
        msg: &fox::PointCloud,
        time: Option<&TimeFieldSpec>,
    ) -> Result<Self, PointsError> {
        FieldList::foxglove(msg)?.layout(time, None)
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

    /// The label field, if labels were asked for.
    pub fn label(&self) -> Option<&NamedField> {
        self.label.as_ref().map(|l| &l.field)
    }
}

impl FieldList<'_> {
    /// The layout: coordinates, then intensity, ring and time, each checked when used,
    /// and with `label` the label field (required then).
    pub(super) fn layout(
        &self,
        time: Option<&TimeFieldSpec>,
        label: Option<&LabelFieldSpec>,
    ) -> Result<PointLayout, PointsError> {
        let xyz = [
            self.coordinate("x")?,
            self.coordinate("y")?,
            self.coordinate("z")?,
        ];
        let intensity = self
            .find(&INTENSITY_NAMES)
            .or_else(|| self.find(&[INTENSITY_FALLBACK]))
            .map(|f| self.named(f))
            .transpose()?;
        let ring = self.find(&RING_NAMES).map(|f| self.named(f)).transpose()?;
        let time = self.time(time)?;
        let label = label.map(|spec| self.label(spec, false)).transpose()?;
        Ok(PointLayout {
            point_step: self.point_step as usize,
            xyz,
            intensity,
            ring,
            time,
            label,
        })
    }

    /// Bytes per point.
    pub(super) fn point_step(&self) -> u32 {
        self.point_step
    }

    /// The label field of `spec`: the configured name, else the first of
    /// [`super::LABEL_NAMES`] present (both case-insensitive); failing that, with
    /// `sole_field`, the only field of a one-field list (a sidecar label cloud). Absent:
    /// [`PointsError::MissingLabelField`].
    pub(super) fn label(
        &self,
        spec: &LabelFieldSpec,
        sole_field: bool,
    ) -> Result<LabelPlan, PointsError> {
        let sole = match self.fields.as_slice() {
            [only] if sole_field => Some(only),
            _ => None,
        };
        let found = self.find_ignoring_case(&spec.names()).or(sole);
        let field = found.ok_or_else(|| PointsError::MissingLabelField {
            frame_id: self.ctx.id(),
            stamp: self.ctx.stamp,
            wanted: spec.wanted(),
            fields: self.names(),
        })?;
        Ok(LabelPlan {
            field: self.named(field)?,
            mask: spec.mask,
        })
    }

    /// The first field named as one of `wanted` regardless of case, in the order of
    /// `wanted`.
    fn find_ignoring_case(&self, wanted: &[&str]) -> Option<&RawField<'_>> {
        wanted.iter().find_map(|name| {
            self.fields
                .iter()
                .find(|f| f.name.eq_ignore_ascii_case(name))
        })
    }

    /// The field names present, comma-separated (for errors).
    fn names(&self) -> String {
        let names: Vec<&str> = self.fields.iter().map(|f| f.name).collect();
        names.join(", ")
    }

    /// The first field named as one of `wanted`, in the order of `wanted`.
    fn find(&self, wanted: &[&str]) -> Option<&RawField<'_>> {
        wanted
            .iter()
            .find_map(|name| self.fields.iter().find(|f| f.name == *name))
    }

    /// How to read a used field: `count` 1, a known datatype, inside the point.
    fn plan(&self, f: &RawField<'_>) -> Result<FieldPlan, PointsError> {
        let ctx = &self.ctx;
        if f.count != 1 {
            return Err(PointsError::FieldCount {
                frame_id: ctx.id(),
                stamp: ctx.stamp,
                field: f.name.to_string(),
                count: f.count,
            });
        }
        let numeric = f.numeric.map_err(|datatype| PointsError::UnknownDatatype {
            frame_id: ctx.id(),
            stamp: ctx.stamp,
            field: f.name.to_string(),
            dialect: self.dialect,
            datatype,
        })?;
        if u64::from(f.offset) + numeric.size() as u64 > u64::from(self.point_step) {
            return Err(PointsError::FieldPastPointStep {
                frame_id: ctx.id(),
                stamp: ctx.stamp,
                field: f.name.to_string(),
                offset: f.offset,
                size: numeric.size(),
                point_step: self.point_step,
            });
        }
        Ok(FieldPlan {
            offset: f.offset as usize,
            numeric,
            endianness: self.endianness,
        })
    }

    /// [`Self::plan`] with the field's name.
    fn named(&self, f: &RawField<'_>) -> Result<NamedField, PointsError> {
        Ok(NamedField {
            name: f.name.to_string(),
            plan: self.plan(f)?,
        })
    }

    /// The plan of a required coordinate.
    fn coordinate(&self, axis: &'static str) -> Result<FieldPlan, PointsError> {
        let field = self
            .find(&[axis])
            .ok_or_else(|| PointsError::MissingCoordinate {
                frame_id: self.ctx.id(),
                stamp: self.ctx.stamp,
                axis,
                fields: self.names(),
            })?;
        self.plan(field)
    }

    /// The time plan: the configured field (required), or the first of [`TIME_NAMES`]
    /// with the rule its type implies.
    fn time(&self, spec: Option<&TimeFieldSpec>) -> Result<Option<TimePlan>, PointsError> {
        let Some(spec) = spec else {
            return self
                .find(&TIME_NAMES)
                .map(|f| {
                    let field = self.named(f)?;
                    let rule = if field.plan.numeric.is_float() {
                        TimeRule::ByMagnitude
                    } else {
                        TimeRule::Fixed(TimeUnit::Nanoseconds, TimeReference::RelativeToStamp)
                    };
                    Ok(TimePlan { field, rule })
                })
                .transpose();
        };
        let field =
            self.find(&[spec.name.as_str()])
                .ok_or_else(|| PointsError::MissingTimeField {
                    frame_id: self.ctx.id(),
                    stamp: self.ctx.stamp,
                    name: spec.name.clone(),
                    fields: self.names(),
                })?;
        Ok(Some(TimePlan {
            field: self.named(field)?,
            rule: TimeRule::Fixed(spec.unit, spec.reference),
        }))
    }
}

/// The context of a Foxglove cloud: its frame and stamp (an error without a timestamp).
pub(super) fn foxglove_ctx(msg: &fox::PointCloud) -> Result<Ctx<'_>, PointsError> {
    Ctx::foxglove(msg).map_err(|_| PointsError::MissingTimestamp {
        frame_id: msg.frame_id.clone(),
    })
}
