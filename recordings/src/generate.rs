//! Simulating and writing a drive in one go.

use crate::dialect::Dialect;
use crate::drive::GeneratedDrive;
use crate::options::DriveOptions;
use crate::simulation::simulate_with;
use crate::{error, foxglove, ros2};

/// Simulates and writes the sample drive in `dialect`.
pub fn generate(dialect: Dialect) -> error::Result<GeneratedDrive> {
    generate_with(dialect, &DriveOptions::default())
}

/// Simulates and writes a drive of `options` in `dialect`.
pub fn generate_with(dialect: Dialect, options: &DriveOptions) -> error::Result<GeneratedDrive> {
    let simulation = simulate_with(dialect, options);
    match dialect {
        Dialect::Foxglove => foxglove::write(&simulation),
        Dialect::Ros2 => ros2::write(&simulation),
    }
}
