//! Nanosecond timestamps.

use serde::{Deserialize, Serialize};
use std::fmt;

/// Keyframe spacing of SuperFlow's recipe and the official code (nuScenes' 2 Hz
/// keyframes): the pipeline's default `keyframe_interval_secs`, the spacing `inspect`
/// counts keyframes by, the probe's labelled sweeps and the unit of the generator's
/// `--keyframes`.
pub const KEYFRAME_INTERVAL_NANOS: i64 = 500_000_000;

/// [`KEYFRAME_INTERVAL_NANOS`] in seconds.
pub const KEYFRAME_INTERVAL_SECS: f64 = KEYFRAME_INTERVAL_NANOS as f64 / 1e9;

/// A sensor timestamp in nanoseconds since the Unix epoch (or since whatever epoch the
/// recording uses; only differences matter inside the pipeline).
///
/// Sensor stamps (`header.stamp`, `timestamp`) are kept at full nanosecond precision;
/// conversions to seconds happen only for geometry (interpolation weights, per-point time).
#[derive(
    Clone, Copy, Debug, Default, PartialEq, Eq, PartialOrd, Ord, Hash, Serialize, Deserialize,
)]
#[serde(transparent)]
pub struct Stamp(i64);

impl Stamp {
    /// The stamp `nanos` nanoseconds after the epoch.
    pub const fn from_nanos(nanos: i64) -> Self {
        Self(nanos)
    }

    /// A stamp from a ROS-style `(sec, nanosec)` pair.
    pub const fn from_sec_nanosec(sec: i64, nanosec: u32) -> Self {
        Self(sec * 1_000_000_000 + nanosec as i64)
    }

    /// Nanoseconds since the epoch.
    pub const fn nanos(self) -> i64 {
        self.0
    }

    /// The ROS-style `(sec, nanosec)` split; `nanosec` is always in `0..1e9`.
    pub const fn to_sec_nanosec(self) -> (i64, u32) {
        (
            self.0.div_euclid(1_000_000_000),
            self.0.rem_euclid(1_000_000_000) as u32,
        )
    }

    /// Seconds since the epoch (loses precision below ~0.1 µs for current dates).
    pub fn as_secs_f64(self) -> f64 {
        self.0 as f64 * 1e-9
    }

    /// `self - earlier` in seconds, exact to the nanosecond before the conversion.
    pub fn secs_since(self, earlier: Stamp) -> f64 {
        (self.0 - earlier.0) as f64 * 1e-9
    }

    /// `self - earlier` in nanoseconds.
    pub const fn nanos_since(self, earlier: Stamp) -> i64 {
        self.0 - earlier.0
    }

    /// The stamp `nanos` nanoseconds later (earlier for negative values).
    pub const fn add_nanos(self, nanos: i64) -> Stamp {
        Stamp(self.0 + nanos)
    }
}

impl fmt::Display for Stamp {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        let (sec, nanosec) = self.to_sec_nanosec();
        write!(f, "{sec}.{nanosec:09}")
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn sec_nanosec_round_trip_and_display() {
        let stamp = Stamp::from_sec_nanosec(1_700_000_000, 50_000_001);
        assert_eq!(stamp.nanos(), 1_700_000_000_050_000_001);
        assert_eq!(stamp.to_sec_nanosec(), (1_700_000_000, 50_000_001));
        assert_eq!(stamp.to_string(), "1700000000.050000001");
        let negative = Stamp::from_nanos(-1);
        assert_eq!(negative.to_sec_nanosec(), (-1, 999_999_999));
    }

    #[test]
    fn differences_are_exact() {
        let a = Stamp::from_nanos(1_700_000_000_000_000_000);
        let b = a.add_nanos(12_345);
        assert_eq!(b.nanos_since(a), 12_345);
        assert!((b.secs_since(a) - 12.345e-6).abs() < 1e-15);
    }
}
