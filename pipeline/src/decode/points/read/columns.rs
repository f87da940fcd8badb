//! What the per-point loops read of each kept point ([`Attributes`]) and the columns
//! they fill ([`Points`]).

use crate::decode::points::field::FieldPlan;
use crate::decode::points::label::LabelPlan;
use crate::decode::points::time::TimeConversion;

/// The optional attributes to read from each kept point.
#[derive(Debug, Clone, Copy)]
pub(super) struct Attributes<'a> {
    pub(super) intensity: Option<FieldPlan>,
    pub(super) ring: Option<FieldPlan>,
    pub(super) time: Option<TimeConversion>,
    pub(super) label: Option<&'a LabelPlan>,
    /// Record the message index of each kept point.
    pub(super) kept_indices: bool,
}

/// The columns of the kept points.
#[derive(Debug)]
pub(super) struct Points {
    pub(super) xyz: Vec<[f32; 3]>,
    pub(super) intensity: Vec<f32>,
    pub(super) ring: Option<Vec<u16>>,
    pub(super) time_offset: Option<Vec<f32>>,
    pub(super) label: Option<Vec<u32>>,
    pub(super) kept_indices: Option<Vec<u32>>,
    pub(super) dropped: usize,
    /// The largest `|value|` of the time field over the kept points (0 without one).
    pub(super) max_abs_time: f64,
}
