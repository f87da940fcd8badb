//! A drive once written: [`GeneratedDrive`] (its bytes and ground truth) and what a
//! dialect writer decided ([`WrittenDrive`]).

use crate::dialect::Dialect;
use crate::error;
use crate::truth::{self, GroundTruth};
use superflow_schemas::Stamp;

/// A generated drive: the MCAP bytes, its class-map sidecar and its ground truth.
#[derive(Debug, Clone)]
pub struct GeneratedDrive {
    /// The MCAP file.
    pub mcap: Vec<u8>,
    /// The class-map sidecar `<drive>.superpixels.mcap` with
    /// [`ClassMapStorage::PngSidecar`]; `None` when the class maps are in the drive.
    pub sidecar: Option<Vec<u8>>,
    /// The labels sidecar `<drive>.labels.mcap` when the labels go to one
    /// ([`LidarLabels::Sidecar`]).
    pub labels_sidecar: Option<Vec<u8>>,
    /// The facts about it.
    pub truth: GroundTruth,
}

impl GeneratedDrive {
    /// The ground truth as the pretty JSON written next to the drive.
    pub fn truth_json(&self) -> error::Result<Vec<u8>> {
        let mut json = serde_json::to_vec_pretty(&self.truth)?;
        json.push(b'\n');
        Ok(json)
    }
}

/// The facts a dialect writer decides: names, layout and what it wrote.
#[derive(Debug)]
pub(crate) struct WrittenDrive {
    pub(crate) dialect: Dialect,
    pub(crate) profile: &'static str,
    pub(crate) compression: &'static str,
    pub(crate) frames: truth::FramesTruth,
    pub(crate) lidar_topic: String,
    pub(crate) motion_compensated: bool,
    pub(crate) stamp_at: &'static str,
    pub(crate) channels: Vec<truth::ChannelTruth>,
    pub(crate) sweeps: Vec<truth::SweepTruth>,
    pub(crate) lidar_stamps: Vec<Stamp>,
    pub(crate) cameras: Vec<truth::CameraTruth>,
    pub(crate) sidecar_channels: Option<Vec<truth::ChannelTruth>>,
    /// Where the labels went ([`Simulation::labels_truth`](crate::simulation::Simulation::labels_truth)).
    pub(crate) labels: Option<truth::LabelsTruth>,
}
