//! Where a run's files go: its output directory, checkpoints, metrics and plot.

use crate::config::TrainerConfig;
use std::path::PathBuf;

/// The files of a run.
#[derive(Debug)]
pub struct RunPaths {
    /// Output directory.
    pub out: PathBuf,
    /// Checkpoint directory.
    pub checkpoints: PathBuf,
    /// `metrics.jsonl` (`rank-<r>/metrics.jsonl` in a data-parallel job).
    pub metrics: PathBuf,
    /// `losses.svg`, beside the metrics.
    pub plot: PathBuf,
}

impl RunPaths {
    /// The files of this process in the output directory `out`: rank `ddp_rank` of a
    /// `--ddp` job, or a lone trainer.
    pub fn new(out: PathBuf, config: &TrainerConfig, ddp_rank: Option<usize>) -> Self {
        let checkpoints = config
            .checkpoint
            .dir
            .clone()
            .unwrap_or_else(|| out.join("checkpoints"));
        let own = match ddp_rank {
            Some(rank) => out.join(format!("rank-{rank}")),
            None => out.clone(),
        };
        Self {
            metrics: own.join("metrics.jsonl"),
            plot: own.join("losses.svg"),
            out,
            checkpoints,
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn a_lone_trainer_and_each_rank_write_their_own_metrics_beside_shared_checkpoints() {
        let config = TrainerConfig::default();
        let lone = RunPaths::new(PathBuf::from("runs/a"), &config, None);
        assert_eq!(lone.out, PathBuf::from("runs/a"));
        assert_eq!(lone.checkpoints, PathBuf::from("runs/a/checkpoints"));
        assert_eq!(lone.metrics, PathBuf::from("runs/a/metrics.jsonl"));
        assert_eq!(lone.plot, PathBuf::from("runs/a/losses.svg"));
        let rank = RunPaths::new(PathBuf::from("runs/a"), &config, Some(3));
        assert_eq!(
            rank.checkpoints, lone.checkpoints,
            "rank 0 writes the job's checkpoints"
        );
        assert_eq!(rank.metrics, PathBuf::from("runs/a/rank-3/metrics.jsonl"));
        assert_eq!(rank.plot, PathBuf::from("runs/a/rank-3/losses.svg"));
        let mut elsewhere = config.clone();
        elsewhere.checkpoint.dir = Some(PathBuf::from("/ckpt"));
        let paths = RunPaths::new(PathBuf::from("runs/a"), &elsewhere, Some(1));
        assert_eq!(
            paths.checkpoints,
            PathBuf::from("/ckpt"),
            "`checkpoint.dir` wins"
        );
    }
}
