//! Per-point time: the [`TimeFieldSpec`] a caller may pass (field, [`TimeUnit`],
//! [`TimeReference`]), the inference by magnitude of float fields, and the conversion of
//! a stored value into the offset from the message stamp (see the module documentation
//! of [`super`] for the rules).

use super::field::{FieldPlan, NamedField};
use superflow_schemas::Stamp;

/// Names of the per-point time field, in order of preference.
pub(super) const TIME_NAMES: [&str; 5] = ["time", "t", "time_offset", "offset_time", "timestamp"];

/// Float time values above this magnitude are absolute (seconds since the epoch or finer).
const ABSOLUTE_THRESHOLD: f64 = 1e8;
/// Absolute float times above this magnitude are microseconds.
const MICROSECONDS_THRESHOLD: f64 = 1e14;
/// Absolute float times above this magnitude are nanoseconds.
const NANOSECONDS_THRESHOLD: f64 = 1e17;

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
/// decoders also return the interpretation they used in [`DecodedCloud::time_field`](super::DecodedCloud::time_field).
#[derive(Debug, Clone, PartialEq, Eq, Hash)]
pub struct TimeFieldSpec {
    /// Field name (exact).
    pub name: String,
    /// Unit of the stored values.
    pub unit: TimeUnit,
    /// What the values are measured from.
    pub reference: TimeReference,
}

/// How the time field's unit and reference are decided.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Hash)]
pub(super) enum TimeRule {
    /// Given (by a [`TimeFieldSpec`], or by the inference for integer fields).
    Fixed(TimeUnit, TimeReference),
    /// A float field: relative seconds or absolute, by the magnitude of its values.
    ByMagnitude,
}

/// The per-point time field and how to interpret it.
#[derive(Debug, Clone, PartialEq, Eq, Hash)]
pub(super) struct TimePlan {
    /// The field.
    pub(super) field: NamedField,
    /// How its unit and reference are decided.
    pub(super) rule: TimeRule,
}

/// Converts a time field's value into the offset from the stamp in seconds:
/// `(value - whole) / per_second - frac_secs`, where `whole + frac` is the stamp for an
/// absolute field (split so that the large part cancels exactly) and 0 for a relative one.
#[derive(Debug, Clone, Copy)]
pub(super) struct TimeConversion {
    /// The time field.
    pub(super) field: FieldPlan,
    per_second: f64,
    whole: f64,
    frac_secs: f64,
}

impl TimeConversion {
    /// The conversion of `field`'s values in `unit` from `reference` for a message at
    /// `stamp`.
    pub(super) fn new(
        field: FieldPlan,
        unit: TimeUnit,
        reference: TimeReference,
        stamp: Stamp,
    ) -> Self {
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

    /// The offset from the stamp, in seconds, of a stored `value`.
    #[inline]
    pub(super) fn offset_secs(self, value: f64) -> f64 {
        (value - self.whole) / self.per_second - self.frac_secs
    }
}

/// The unit and reference of a float time field whose largest magnitude over the kept
/// points is `max_abs` (see the module documentation).
pub(super) fn magnitude_rule(max_abs: f64) -> (TimeUnit, TimeReference) {
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
