//! A transform from its recorded parts (translation and quaternion), checked: the one
//! conversion behind `/tf`, `foxglove.FrameTransform` and a Foxglove cloud's pose.

use nalgebra::{Isometry3, Quaternion, Translation3, UnitQuaternion};
use superflow_schemas::Stamp;

use super::error::DecodeError;

/// Builds `parent_from_child` from a translation and an `(x, y, z, w)` quaternion,
/// normalizing the quaternion; rejects non-finite values and zero quaternions.
pub(crate) fn isometry(
    stamp: Stamp,
    parent: &str,
    child: &str,
    translation: [f64; 3],
    rotation_xyzw: [f64; 4],
) -> Result<Isometry3<f64>, DecodeError> {
    let bad = |reason| DecodeError::BadTransform {
        parent: parent.to_string(),
        child: child.to_string(),
        stamp,
        reason,
    };
    if !translation
        .iter()
        .chain(&rotation_xyzw)
        .all(|v| v.is_finite())
    {
        return Err(bad("non-finite translation or rotation"));
    }
    let [x, y, z, w] = rotation_xyzw;
    let q = Quaternion::new(w, x, y, z);
    if q.norm() < 1e-6 {
        return Err(bad("zero quaternion"));
    }
    let [tx, ty, tz] = translation;
    Ok(Isometry3::from_parts(
        Translation3::new(tx, ty, tz),
        UnitQuaternion::from_quaternion(q),
    ))
}
