//! How a run starts ([`begin`], the one way in): fresh, from its newest checkpoint
//! (`--resume`), or — a data-parallel job — as rank 0 decides, with every rank receiving
//! rank 0's parameters. Resuming asks the pipeline where the stream continues
//! ([`super::resume::ask_resume`]).

use super::error::RunError;
use super::job::Ddp;
use super::options::RunOptions;
use super::paths::RunPaths;
use super::resume::ask_resume;
use crate::checkpoint::CheckpointState;
use crate::metrics;
use crate::stream::StreamPosition;
use crate::subscribe::Subscription;
use crate::train::Trainer;
use std::path::PathBuf;
use std::time::Duration;

pub use super::error::ResumeRefused;

/// Where a run begins.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum Begun {
    /// Training starts: fresh (`None`) or where the pipeline continues the stream.
    At(Option<StreamPosition>),
    /// The pipeline has served every epoch of the run (a requeued job of a finished
    /// run): nothing to train, and not a failure.
    RunComplete,
}

/// Starts the run in `trainer`: as a rank of the data-parallel job `ddp`, from the
/// newest checkpoint (`--resume`), or fresh.
pub fn begin(
    options: &RunOptions,
    trainer: &mut Trainer,
    subscription: &Subscription,
    paths: &RunPaths,
    ddp: Option<&Ddp>,
) -> Result<Begun, RunError> {
    let started = match ddp {
        Some(ddp) => start_ranks(options, trainer, subscription, paths, ddp),
        None if options.resume => resume(options, trainer, subscription, paths),
        None => start_fresh(paths, true).map(|()| None),
    };
    match started {
        Ok(at) => Ok(Begun::At(at)),
        Err(e) if e.run_complete().is_some() => {
            tracing::info!(run = %options.run, step = trainer.step_count(), "{e}");
            Ok(Begun::RunComplete)
        }
        Err(e) => Err(e),
    }
}

/// `--ddp`: whether every rank resumed (`Ok` with this rank's position), from what each
/// rank's request gave (`asked`, this rank's): a run complete on every rank stays
/// [`ResumeRefused::RunComplete`] (the job ends successfully on all of them), a rank's
/// own failure is its error, and the ranks that succeeded fail too, naming the ranks
/// that did not, rather than wait for them in the next collective.
fn agree_on_resume(
    asked: Result<(u128, StreamPosition), RunError>,
    ddp: &Ddp,
) -> Result<StreamPosition, RunError> {
    let outcome = match &asked {
        Ok(_) => 0,
        Err(e) if e.run_complete().is_some() => 1,
        Err(_) => 2,
    };
    let all = ddp.all_gather(&[outcome], "every rank's resume outcome");
    let ranks =
        |wanted: u64| -> Vec<usize> { (0..all.len()).filter(|&r| all[r] == wanted).collect() };
    match asked {
        Err(e) if outcome == 2 => Err(e),
        _ if all.contains(&2) => Err(RunError::RanksCannotResume { ranks: ranks(2) }),
        Err(e) if all.iter().all(|&o| o == 1) => Err(e),
        Ok((_, position)) if all.iter().all(|&o| o == 0) => Ok(position),
        _ => Err(RunError::CompletionDiffers {
            complete: ranks(1),
            incomplete: ranks(0),
        }),
    }
}

/// How rank 0 starts a data-parallel job; every rank receives it.
#[derive(Debug, Default, serde::Serialize, serde::Deserialize)]
pub struct JobStart {
    /// Rank 0's configuration (TOML): every rank must run the same.
    pub config: String,
    /// The checkpoint the job continues from (`--resume` and one exists).
    pub resume: Option<CheckpointState>,
    /// Why rank 0 cannot start the job.
    pub error: Option<String>,
}

/// `--ddp`: rank 0 decides how the job starts (fresh, or from the newest checkpoint)
/// and every rank receives the same parameters and optimizer state from it; each rank
/// then asks its shard stream to continue at its own position. Returns that position
/// when resuming.
fn start_ranks(
    options: &RunOptions,
    trainer: &mut Trainer,
    subscription: &Subscription,
    paths: &RunPaths,
    ddp: &Ddp,
) -> Result<Option<StreamPosition>, RunError> {
    let rank = ddp.rank();
    // Rank 0 keeps its own error to return; the other ranks receive its text.
    let (start, model, optim, failed) = if rank == 0 {
        match first_rank_start(options.resume, trainer, paths) {
            Ok((start, model, optim)) => (start, model, optim, None),
            Err(e) => (
                JobStart {
                    error: Some(superflow_common::exit::describe(&e)),
                    ..JobStart::default()
                },
                Vec::new(),
                Vec::new(),
                Some(e),
            ),
        }
    } else {
        Default::default()
    };
    let start = serde_json::to_vec(&start).map_err(RunError::EncodeJobStart)?;
    let start = ddp.broadcast_bytes(start, "job start (rank 0's decision)");
    let start: JobStart = serde_json::from_slice(&start).map_err(RunError::DecodeJobStart)?;
    if let Some(error) = start.error {
        return Err(failed.unwrap_or(RunError::FirstRank(error)));
    }
    if start.config != trainer.config_toml() {
        return Err(RunError::ConfigDiffers { rank });
    }
    let model = ddp.broadcast_bytes(model, "rank 0's parameters");
    let optim = ddp.broadcast_bytes(optim, "rank 0's optimizer state");
    let step = start.resume.as_ref().map_or(0, |s| s.step);
    trainer.restore_bytes(model, optim, step, &paths.checkpoints)?;
    let Some(state) = start.resume else {
        start_fresh(paths, false)?;
        tracing::info!(
            rank,
            world_size = ddp.size(),
            "every rank starts from rank 0's parameters"
        );
        return Ok(None);
    };
    // Every rank resumes after the samples the whole job had consumed: the pipeline deals
    // the rest of the epoch to this job's ranks, however many there were before.
    let own = state
        .ranks
        .get(rank)
        .map(|&[e, b]| StreamPosition::new(e, b));
    let at = match (state.job, own) {
        (Some(_), _) => state.resume_at(state.next()),
        (None, Some(own)) if state.ranks.len() == ddp.size() => state.resume_at(own),
        (None, _) => {
            return Err(RunError::UncountedCheckpoint {
                step: state.step,
                ranks: state.ranks.len(),
            });
        }
    };
    let asked = ask_resume(
        subscription,
        &options.run,
        at,
        Duration::from_secs(options.timeout_secs),
    );
    let position = agree_on_resume(asked, ddp)?;
    tracing::info!(
        rank,
        step,
        epoch = position.epoch,
        batch = position.batch,
        ranks_before = state.ranks.len(),
        ranks = ddp.size(),
        "resuming: this rank's shard continues where the job stopped"
    );
    drop_redone_metrics(paths, step)?;
    Ok(Some(position))
}

/// Rank 0's part of [`start_ranks`]: the decision and the records to send.
fn first_rank_start(
    resume: bool,
    trainer: &Trainer,
    paths: &RunPaths,
) -> Result<(JobStart, Vec<u8>, Vec<u8>), RunError> {
    let config = trainer.config_toml();
    let latest = crate::checkpoint::latest(&paths.checkpoints)?;
    match latest {
        Some(ckpt) if resume => {
            let read = |p: PathBuf| std::fs::read(&p).map_err(|e| RunError::io("reading", p, e));
            let (model, optim) = (read(ckpt.model_path())?, read(ckpt.optim_path())?);
            tracing::info!(checkpoint = %ckpt.dir.display(), step = ckpt.state.step, "the job continues from this checkpoint");
            let start = JobStart {
                config,
                resume: Some(ckpt.state),
                error: None,
            };
            Ok((start, model, optim))
        }
        Some(_) => Err(holds_checkpoints(paths)),
        None => {
            if resume {
                tracing::warn!(dir = %paths.checkpoints.display(), "--resume: no checkpoint yet, starting fresh");
            }
            let start = JobStart {
                config,
                ..JobStart::default()
            };
            Ok((start, trainer.model_bytes()?, Vec::new()))
        }
    }
}

/// `--resume`: restores the newest checkpoint and asks the pipeline to continue at its
/// next batch (`None` when there is no checkpoint yet: a fresh start).
fn resume(
    options: &RunOptions,
    trainer: &mut Trainer,
    subscription: &Subscription,
    paths: &RunPaths,
) -> Result<Option<StreamPosition>, RunError> {
    let Some(state) = restore_newest(trainer, paths)? else {
        return Ok(None);
    };
    let (_, position) = ask_resume(
        subscription,
        &options.run,
        state.resume_at(state.next()),
        Duration::from_secs(options.timeout_secs),
    )?;
    tracing::info!(
        step = state.step,
        epoch = position.epoch,
        batch = position.batch,
        samples = state.job.map(|j| j.samples),
        "resuming: the pipeline continues at the checkpoint's next batch"
    );
    drop_redone_metrics(paths, state.step)?;
    Ok(Some(position))
}

/// Restores the newest checkpoint of `paths` into `trainer`; `None` (said in the log)
/// when there is none yet: the run starts fresh.
fn restore_newest(
    trainer: &mut Trainer,
    paths: &RunPaths,
) -> Result<Option<CheckpointState>, RunError> {
    let state = trainer.restore_latest(&paths.checkpoints)?;
    if state.is_none() {
        tracing::warn!(dir = %paths.checkpoints.display(), "--resume: no checkpoint yet, starting fresh");
    }
    Ok(state)
}

/// A resumed run redoes the steps after its checkpoint's `step`: their metrics lines go.
fn drop_redone_metrics(paths: &RunPaths, step: u64) -> Result<(), RunError> {
    let redone = metrics::truncate_after(&paths.metrics, step)?;
    if redone > 0 {
        tracing::warn!(
            steps = redone,
            after = step,
            "steps trained after the checkpoint are lost and will be redone on the same batches; their metrics lines are dropped"
        );
    }
    Ok(())
}

/// Why a fresh run does not start in `paths`: it holds checkpoints.
fn holds_checkpoints(paths: &RunPaths) -> RunError {
    RunError::HoldsCheckpoints {
        dir: paths.checkpoints.clone(),
    }
}

/// A fresh run: refuses an output directory holding checkpoints (`check_checkpoints`:
/// the process that writes them), drops old metrics.
fn start_fresh(paths: &RunPaths, check_checkpoints: bool) -> Result<(), RunError> {
    if check_checkpoints && crate::checkpoint::latest(&paths.checkpoints)?.is_some() {
        return Err(holds_checkpoints(paths));
    }
    if paths.metrics.exists() {
        std::fs::remove_file(&paths.metrics)
            .map_err(|e| RunError::io("replacing", &paths.metrics, e))?;
    }
    Ok(())
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::config::TrainerConfig;
    use crate::loss::LossValues;
    use crate::metrics::{MetricsWriter, StepRecord};
    use crate::subscribe::ResumeAt;
    use crate::unet::UNetPreset;
    use crate::vit::VitPreset;
    use superflow_schemas::service::ResumeReply;

    fn tiny_trainer(seed: u64) -> Trainer {
        let mut config = TrainerConfig::default();
        config.model.unet = UNetPreset::Tiny;
        config.model.vit = VitPreset::Tiny;
        config.model.seed = seed;
        Trainer::new(config, &burn::tensor::Device::flex()).expect("tiny trainer")
    }

    fn paths_in(dir: &std::path::Path) -> RunPaths {
        RunPaths::new(dir.to_path_buf(), &TrainerConfig::default(), None)
    }

    fn scratch(name: &str) -> PathBuf {
        let dir =
            std::env::temp_dir().join(format!("superflow-start-{name}-{}", std::process::id()));
        let _ = std::fs::remove_dir_all(&dir);
        dir
    }

    /// A checkpoint of `trainer` at `step` whose next batch is (epoch 1, batch `step`).
    fn checkpoint_at(trainer: &mut Trainer, paths: &RunPaths, step: u64) -> CheckpointState {
        let model = trainer.model_bytes().expect("model");
        trainer
            .restore_bytes(model, Vec::new(), step, &paths.checkpoints)
            .expect("step count");
        let state =
            trainer.checkpoint_state("r", StreamPosition::new(1, step), &LossValues::default());
        trainer
            .save_checkpoint(&paths.checkpoints, &state)
            .expect("saved");
        state
    }

    /// The pipeline's refusals in words; a finished run is told apart from any other
    /// refusal.
    #[test]
    fn refusals_name_the_reason_and_a_finished_run_is_its_own() {
        let at = ResumeAt::Sample {
            epoch: 2,
            sample: 36,
            global_batch: 6,
        };
        let reply = |reason, epoch| ResumeReply {
            reason,
            epoch,
            ..ResumeReply::default()
        };
        let done = ResumeRefused::of("r", at, &reply(ResumeReply::RUN_COMPLETE, 3));
        assert_eq!(done, ResumeRefused::RunComplete { epochs: 3 });
        assert_eq!(
            done.to_string(),
            "the run is complete (3 epochs): nothing left to train"
        );
        let error = RunError::from(done);
        assert_eq!(error.run_complete(), Some(3));
        let other = ResumeRefused::of("r", at, &reply(ResumeReply::OUT_OF_RANGE, 0));
        assert_eq!(
            other.to_string(),
            "the pipeline refused to resume run r at epoch 2 after 36 samples: no such position in its epochs: is it the same recording and configuration?"
        );
        assert_eq!(RunError::from(other).run_complete(), None);
        let step = ResumeAt::Step { epoch: 1, step: 4 };
        let text = ResumeRefused::of("r", step, &reply(ResumeReply::OTHER_JOB_SIZE, 0)).to_string();
        assert!(
            text.contains("at epoch 1 batch 4: the position was saved by a job of another size"),
            "{text}"
        );
    }

    #[test]
    fn rank_zero_starts_fresh_resumes_or_refuses_a_directory_holding_checkpoints() {
        let dir = scratch("rank0");
        let paths = paths_in(&dir);
        let mut trainer = tiny_trainer(1);
        // No checkpoint: a fresh job, with or without --resume, from rank 0's parameters.
        for resume in [false, true] {
            let (start, model, optim) = first_rank_start(resume, &trainer, &paths).expect("fresh");
            assert_eq!(start.config, trainer.config_toml());
            assert!(start.resume.is_none() && start.error.is_none());
            assert_eq!(model, trainer.model_bytes().expect("model"));
            assert!(optim.is_empty(), "a fresh optimizer is not sent");
        }
        let state = checkpoint_at(&mut trainer, &paths, 4);
        // A checkpoint and --resume: its records and state.
        let (start, model, optim) = first_rank_start(true, &trainer, &paths).expect("resume");
        let newest = crate::checkpoint::latest(&paths.checkpoints)
            .expect("read")
            .expect("one");
        assert_eq!(
            start.resume.as_ref().map(|s| (s.step, s.next())),
            Some((4, state.next()))
        );
        assert_eq!(
            model,
            std::fs::read(newest.model_path()).expect("model.bpk")
        );
        assert_eq!(
            optim,
            std::fs::read(newest.optim_path()).expect("optim.bpk")
        );
        // A checkpoint without --resume: refused, naming the directory.
        let err = first_rank_start(false, &trainer, &paths).expect_err("holds checkpoints");
        assert!(
            err.to_string()
                .contains("already holds checkpoints: pass --resume"),
            "{err}"
        );
        let err = start_fresh(&paths, true).expect_err("a lone trainer refuses too");
        assert!(
            err.to_string().contains("already holds checkpoints"),
            "{err}"
        );
        let _ = std::fs::remove_dir_all(&dir);
    }

    #[test]
    fn resuming_restores_the_newest_checkpoint_and_drops_the_metrics_of_redone_steps() {
        let dir = scratch("resume");
        let paths = paths_in(&dir);
        let mut saved = tiny_trainer(2);
        let state = checkpoint_at(&mut saved, &paths, 3);
        let mut writer = MetricsWriter::open(&paths.metrics).expect("metrics");
        for step in 1..=5 {
            writer
                .write(&StepRecord {
                    step,
                    ..StepRecord::default()
                })
                .expect("line");
        }
        drop(writer);
        let mut trainer = tiny_trainer(3);
        assert_ne!(trainer.params_hash(), saved.params_hash(), "another seed");
        let restored = restore_newest(&mut trainer, &paths)
            .expect("restore")
            .expect("one");
        assert_eq!((restored.step, restored.next()), (3, state.next()));
        assert_eq!(trainer.step_count(), 3);
        assert_eq!(
            trainer.params_hash(),
            saved.params_hash(),
            "the checkpoint's parameters"
        );
        drop_redone_metrics(&paths, restored.step).expect("truncate");
        let steps: Vec<u64> = metrics::read(&paths.metrics)
            .expect("read")
            .iter()
            .map(|r| r.step)
            .collect();
        assert_eq!(steps, [1, 2, 3], "steps 4 and 5 are redone");
        // Nothing to resume from: a fresh start.
        let empty = paths_in(&scratch("resume-empty"));
        assert!(
            restore_newest(&mut trainer, &empty)
                .expect("no checkpoint")
                .is_none()
        );
        let _ = std::fs::remove_dir_all(&dir);
    }
}
