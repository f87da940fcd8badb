//! `--ddp`: joining the MPI job, or saying why this build cannot.

use super::error::RunError;
use super::options::RunOptions;

#[cfg(feature = "mpi")]
pub use crate::ddp::Ddp;

/// `--ddp`: this rank's place in the MPI job.
pub fn join_job(options: &RunOptions) -> Result<Option<Ddp>, RunError> {
    if !options.ddp {
        return Ok(None);
    }
    #[cfg(feature = "mpi")]
    {
        let timeout = std::time::Duration::from_secs(options.collective_timeout_secs);
        if options.collective_timeout_secs <= options.timeout_secs {
            tracing::warn!(
                collective_timeout_secs = options.collective_timeout_secs,
                timeout_secs = options.timeout_secs,
                "the collective timeout is not above the batch timeout: a rank waiting for its batch may abort the job first"
            );
        }
        Ok(Some(Ddp::init(timeout)?))
    }
    #[cfg(not(feature = "mpi"))]
    Err(RunError::NoMpi)
}

/// Without the `mpi` feature there is no job to be part of: an uninhabited stand-in,
/// so the session code is the same in both builds.
#[cfg(not(feature = "mpi"))]
#[derive(Debug)]
pub enum Ddp {}

#[cfg(not(feature = "mpi"))]
impl Ddp {
    pub fn rank(&self) -> usize {
        match *self {}
    }
    pub fn size(&self) -> usize {
        match *self {}
    }
    pub fn local_rank(&self) -> usize {
        match *self {}
    }
    pub fn all_reduce_sum(&self, _: &mut [f32], _: &str) {
        match *self {}
    }
    pub fn broadcast_bytes(&self, _: Vec<u8>, _: &str) -> Vec<u8> {
        match *self {}
    }
    pub fn all_gather(&self, _: &[u64], _: &str) -> Vec<u64> {
        match *self {}
    }
}
