//! A dataset: many drives, each one or more MCAP files (a recording split in parts),
//! grouped by [`super::files`] and each indexed by [`Drive::open`](super::Drive::open).

use super::discover::IngestConfig;
use super::error::IngestError;
use super::files::drive_groups;
use super::index::Drive;
use crate::source::McapFile;
use std::path::PathBuf;

/// Every drive of a dataset.
#[derive(Debug)]
pub struct Dataset {
    /// The drives, in input order.
    pub drives: Vec<Drive>,
}

impl Dataset {
    /// Indexes every drive of `inputs` (files, directories, rosbag2 directories).
    pub fn open(inputs: &[PathBuf], config: &IngestConfig) -> Result<Dataset, IngestError> {
        Self::open_with_progress(inputs, config, |_, _| {})
    }

    /// [`Dataset::open`], reporting `(bytes indexed, total bytes)` as it goes.
    pub fn open_with_progress(
        inputs: &[PathBuf],
        config: &IngestConfig,
        mut progress: impl FnMut(u64, u64),
    ) -> Result<Dataset, IngestError> {
        let groups = drive_groups(inputs)?;
        let total: u64 = groups
            .iter()
            .flatten()
            .map(|f| std::fs::metadata(f).map_or(0, |m| m.len()))
            .sum();
        let mut done = 0u64;
        let mut drives = Vec::with_capacity(groups.len());
        for files in &groups {
            let drive = Drive::open_with_progress(files, config, |d, _| progress(done + d, total))?;
            done += drive.files.iter().map(McapFile::len).sum::<u64>();
            drives.push(drive);
        }
        Ok(Dataset { drives })
    }

    /// Checks every drive ([`Drive::check_sensors`]).
    pub fn check_sensors(&self) -> Result<(), IngestError> {
        self.drives.iter().try_for_each(Drive::check_sensors)
    }
}
