//! A camera calibration from its recorded parts, validated: the one conversion behind
//! `sensor_msgs/msg/CameraInfo` and `foxglove.CameraCalibration`.

use superflow_schemas::Stamp;

use super::error::DecodeError;

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
