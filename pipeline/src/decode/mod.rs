//! Wire formats of recorded drives: the message types of each dialect, and their
//! conversion into the sensor model of `superflow-schemas`.
//!
//! * [`ros2`]: ROS 2 messages (`ros2msg` schemas, CDR payloads), as rosbag2 writes them.
//! * [`foxglove`]: Foxglove protobuf messages (`foxglove.PointCloud`, ...), as the
//!   nuScenes converter writes them.
//! * [`schema`]: which sensor a channel carries in which dialect ([`schema_kind`]), from
//!   its schema name and message encoding.
//! * [`points`] and [`image`]: point clouds and camera images of either dialect, decoded
//!   into the sensor model.
//!
//! Conversions check what the sensor model needs (finite numbers, unit quaternions,
//! a usable calibration) and report a [`DecodeError`] naming the frame and stamp.

mod context;
pub mod foxglove;
pub mod image;
pub mod points;
pub mod ros2;
pub mod schema;

pub use schema::{Dialect, SchemaKind, schema_kind};

use nalgebra::{Isometry3, Quaternion, Translation3, UnitQuaternion};
use superflow_schemas::Stamp;
use superflow_schemas::sensor::SensorError;

/// A message that decoded but cannot be turned into the sensor model.
#[derive(Debug, thiserror::Error)]
pub enum DecodeError {
    /// The payload is not a valid protobuf message of the schema.
    #[error("invalid {schema} protobuf message: {reason}")]
    Protobuf {
        /// Schema name.
        schema: &'static str,
        /// What prost reported.
        reason: String,
    },
    /// The payload is not a valid CDR message of the schema.
    #[error(transparent)]
    Cdr(#[from] ros2::CdrError),
    /// A required field is absent.
    #[error("{schema} message has no `{field}`")]
    MissingField {
        /// Schema name.
        schema: &'static str,
        /// Field name.
        field: &'static str,
    },
    /// A transform with non-finite values or a zero quaternion.
    #[error("transform {parent} -> {child} at {stamp}: {reason}")]
    BadTransform {
        /// Parent frame.
        parent: String,
        /// Child frame.
        child: String,
        /// Its stamp.
        stamp: Stamp,
        /// What is wrong.
        reason: &'static str,
    },
    /// A calibration or image the sensor model rejects.
    #[error("{frame_id} at {stamp}: {source}")]
    Sensor {
        /// Frame of the record.
        frame_id: String,
        /// Its stamp.
        stamp: Stamp,
        /// The sensor model's complaint.
        source: SensorError,
    },
    /// A calibration matrix with the wrong number of entries.
    #[error("calibration of {frame_id} at {stamp}: K has {len} entries, 9 expected")]
    BadIntrinsics {
        /// Optical frame.
        frame_id: String,
        /// Its stamp.
        stamp: Stamp,
        /// Entries found.
        len: usize,
    },
}

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

/// A calibration from the recorded parts (row-major `K`, distortion name and
/// coefficients), validated; errors name the frame and stamp.
pub(crate) fn calibration(
    stamp: Stamp,
    frame_id: &str,
    (width, height): (u32, u32),
    k_row_major: &[f64],
    distortion_model: &str,
    d: &[f64],
) -> Result<superflow_schemas::sensor::CameraCalibration, DecodeError> {
    use superflow_schemas::sensor::{CameraCalibration, Distortion};
    if k_row_major.len() != 9 {
        return Err(DecodeError::BadIntrinsics {
            frame_id: frame_id.to_string(),
            stamp,
            len: k_row_major.len(),
        });
    }
    let sensor_error = |source| DecodeError::Sensor {
        frame_id: frame_id.to_string(),
        stamp,
        source,
    };
    let calibration = CameraCalibration {
        stamp,
        frame_id: frame_id.to_string(),
        width,
        height,
        k: nalgebra::Matrix3::from_row_slice(k_row_major),
        distortion: Distortion::from_recorded(distortion_model, d).map_err(sensor_error)?,
    };
    calibration.validate().map_err(sensor_error)?;
    Ok(calibration)
}
