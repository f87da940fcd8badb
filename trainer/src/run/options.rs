//! [`RunOptions`]: what the command line says about a run besides its configuration.

use super::error::RunError;
use std::path::PathBuf;

/// What the command line says about a run besides its configuration.
#[derive(Debug, Clone)]
pub struct RunOptions {
    /// Run name of the pipeline to subscribe to.
    pub run: String,
    /// Data-parallel rank (shard mode) ...
    pub rank: Option<u32>,
    /// ... out of this many ranks.
    pub world_size: Option<u32>,
    /// Output directory [default: `runs/<run>` or `runs/<run>-rank<r>`].
    pub out: Option<PathBuf>,
    /// Continue from the newest checkpoint in the output directory.
    pub resume: bool,
    /// Write `losses.svg` at the end.
    pub plot: bool,
    /// Give up when no batch arrives for this long, seconds.
    pub timeout_secs: u64,
    /// Synchronous data parallelism over MPI.
    pub ddp: bool,
    /// `--ddp`: abort when a collective waits longer than this, seconds.
    pub collective_timeout_secs: u64,
    /// Isolates a deployment's iceoryx2 resources.
    pub iox_prefix: Option<String>,
    /// Compute backend.
    pub backend: crate::device::Backend,
    /// GPU index for cuda.
    pub device_index: usize,
}

impl RunOptions {
    /// `--rank` must be below `--world-size`.
    pub fn check_rank(&self) -> Result<(), RunError> {
        if let (Some(rank), Some(world_size)) = (self.rank, self.world_size)
            && rank >= world_size
        {
            return Err(RunError::RankOutOfRange { rank, world_size });
        }
        Ok(())
    }

    /// The output directory: `--out`, or `runs/<run>` (`runs/<run>-rank<r>` for a shard).
    pub fn out_dir(&self) -> PathBuf {
        self.out.clone().unwrap_or_else(|| {
            let name = match self.rank {
                Some(r) => format!("{}-rank{r}", self.run),
                None => self.run.clone(),
            };
            PathBuf::from("runs").join(name)
        })
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    fn options(run: &str, rank: Option<u32>, world_size: Option<u32>) -> RunOptions {
        RunOptions {
            run: run.into(),
            rank,
            world_size,
            out: None,
            resume: false,
            plot: false,
            timeout_secs: 300,
            ddp: false,
            collective_timeout_secs: 900,
            iox_prefix: None,
            backend: crate::device::Backend::Flex,
            device_index: 0,
        }
    }

    #[test]
    fn the_output_directory_is_named_after_the_run_and_the_shard() {
        assert_eq!(options("a", None, None).out_dir(), PathBuf::from("runs/a"));
        assert_eq!(
            options("a", Some(2), Some(4)).out_dir(),
            PathBuf::from("runs/a-rank2")
        );
        let mut o = options("a", Some(2), Some(4));
        o.out = Some(PathBuf::from("/data/out"));
        assert_eq!(o.out_dir(), PathBuf::from("/data/out"));
        assert!(o.check_rank().is_ok());
        let err = options("a", Some(4), Some(4))
            .check_rank()
            .expect_err("rank 4 of 4");
        assert_eq!(err.to_string(), "--rank 4 is not below --world-size 4");
    }
}
