//! [`Dialect`]: the MCAP layouts the generator writes, and what each records.

use crate::sample_drive::DURATION_NANOS;
use crate::sim::DriveTiming;
use superflow_schemas::Stamp;
use superflow_schemas::sensor::Distortion;

/// The MCAP layouts the generator writes (`--dialect foxglove|ros2`).
#[derive(Debug, Clone, Copy, PartialEq, Eq, clap::ValueEnum)]
pub enum Dialect {
    /// nuScenes converted to MCAP with Foxglove protobuf schemas (2024 upper-case topics,
    /// lz4 chunks, microsecond stamps, motion-compensated sweeps stamped at their end,
    /// undistorted images, extrinsics re-published on `/tf`).
    Foxglove,
    /// A ROS 2 rosbag2 recording (`ros2msg` + CDR, zstd chunks, raw velodyne-layout sweeps
    /// with per-point time stamped at their start, distorted JPEG images,
    /// `map → odom → base_link` on `/tf`, extrinsics on `/tf_static`).
    Ros2,
}

impl Dialect {
    /// Both dialects.
    pub const ALL: [Dialect; 2] = [Dialect::Foxglove, Dialect::Ros2];

    /// Lower-case name, used in file names and the ground truth.
    pub fn name(self) -> &'static str {
        match self {
            Dialect::Foxglove => "foxglove",
            Dialect::Ros2 => "ros2",
        }
    }

    /// File stem of the drive in `recordings/`.
    pub fn drive_name(self) -> String {
        format!("street_{}", self.name())
    }

    /// The timing of the sample drive in this dialect.
    pub fn timing(self) -> DriveTiming {
        DriveTiming {
            start: Stamp::from_nanos(1_700_000_000_123_456_000),
            duration_nanos: DURATION_NANOS,
            sweep_nanos: 50_000_000,
            camera_period_nanos: 83_333_333,
            quantum_nanos: match self {
                Dialect::Foxglove => 1_000,
                Dialect::Ros2 => 1,
            },
        }
    }

    /// The lens distortion of the cameras in this dialect.
    pub fn distortion(self) -> Distortion {
        match self {
            Dialect::Foxglove => Distortion::None,
            Dialect::Ros2 => Distortion::PlumbBob {
                coeffs: [-0.08, 0.012, 0.0004, -0.0003, 0.0],
            },
        }
    }
}
