//! Per-point semantic labels: which field holds them ([`LabelFieldSpec`]) and how a
//! stored value becomes a raw class id (integral, non-negative, masked). The decoding of
//! a label-only cloud ([`LabelCloud`](super::LabelCloud), the parallel cloud of a
//! `<drive>.labels.mcap` sidecar) is in [`super::label_cloud`].
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

use super::error::PointsError;
use super::field::{FieldPlan, NamedField};
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
