//! [`DecodeError`]: why a message that decoded cannot be turned into the sensor model.

use superflow_schemas::Stamp;
use superflow_schemas::ros2::CdrError;
use superflow_schemas::sensor::SensorError;

/// A message that decoded but cannot be turned into the sensor model.
#[derive(Debug, thiserror::Error)]
pub enum DecodeError {
    /// The payload is not a valid protobuf message of the schema.
    #[error("invalid {schema} protobuf message: {source}")]
    Protobuf {
        /// Schema name.
        schema: &'static str,
        /// What prost reported.
        #[source]
        source: prost::DecodeError,
    },
    /// The payload is not a valid CDR message of the schema.
    #[error(transparent)]
    Cdr(#[from] CdrError),
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
