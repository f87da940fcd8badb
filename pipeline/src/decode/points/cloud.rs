//! [`DecodedCloud`]: what decoding one message gives, the sensor model's cloud and what
//! the decoder saw on the way (dropped points, the intensity and time fields it used,
//! the message index of each kept point).

use superflow_schemas::sensor::PointCloud;

use super::time::TimeFieldSpec;

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
    /// The index in the message (row by row, dropped points counted) of each kept
    /// point, when [`CloudOptions::kept_indices`] asked for it: what carries anything
    /// parallel to the message's points (a sidecar's labels) through the dropping.
    ///
    /// [`CloudOptions::kept_indices`]: super::dialect::CloudOptions::kept_indices
    pub kept_indices: Option<Vec<u32>>,
}
