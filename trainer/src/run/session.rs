//! A run in progress: receiving batches, stepping, checkpointing, and the summary at the
//! end.

use super::error::RunError;
use super::job::Ddp;
use super::options::RunOptions;
use super::paths::RunPaths;
use super::resume::ask_resume;
use crate::checkpoint::JobPosition;
use crate::loss::LossValues;
use crate::metrics::{self, DdpRecord, MetricsWriter, StepRecord};
use crate::stream::{self, Action, PlanView, RankState, StreamPosition, StreamTracker};
use crate::subscribe::{Received, ResumeAt, Subscription};
use crate::train::{StepOutcome, Trainer};
use indicatif::{ProgressBar, ProgressStyle};
use std::path::PathBuf;
use std::sync::Arc;
use std::sync::atomic::{AtomicI32, Ordering};
use std::time::{Duration, Instant};
use superflow_schemas::batch::{BATCH_LOST, BatchMeta, BatchView};
use superflow_schemas::service::ScheduleReply;

/// How long to wait for the schedule of a pipeline that just sent a batch (it answers
/// from a thread of its own; an older pipeline does not answer at all).
const SCHEDULE_WAIT: Duration = Duration::from_secs(5);

/// Waits for the next batch; says when no pipeline publishes and keeps waiting for one
/// to come back, up to `timeout`. `None` once a stop signal was caught.
fn next_batch(
    subscription: &Subscription,
    run: &str,
    timeout: Duration,
    stop: &AtomicI32,
) -> Result<Option<Received>, RunError> {
    let t = Instant::now();
    let mut gone_reported = false;
    loop {
        if stop.load(Ordering::SeqCst) != 0 {
            return Ok(None);
        }
        if let Some(batch) = subscription.receive(Duration::from_secs(2))? {
            if gone_reported {
                tracing::info!(run, "a pipeline is publishing again");
            }
            return Ok(Some(batch));
        }
        let attached = subscription.pipeline_attached();
        if !attached && !gone_reported {
            tracing::warn!(
                run,
                "no pipeline is publishing; waiting for it to come back"
            );
            gone_reported = true;
        } else if attached && gone_reported {
            tracing::info!(run, "a pipeline is publishing again");
            gone_reported = false;
        }
        if t.elapsed() > timeout {
            return Err(RunError::NoBatch {
                run: run.to_string(),
                secs: timeout.as_secs(),
            });
        }
    }
}

pub fn progress_bar(steps: u64, position: u64) -> ProgressBar {
    let bar = ProgressBar::new(steps);
    bar.set_style(
        ProgressStyle::with_template(
            "{spinner} step {pos}/{len} [{elapsed_precise}<{eta_precise}] {msg}",
        )
        .unwrap_or_else(|_| ProgressStyle::default_bar()),
    );
    bar.set_position(position);
    bar
}

/// A run in progress: the stream, the trainer and what it writes.
pub(super) struct Session<'a> {
    pub(super) options: &'a RunOptions,
    pub(super) subscription: Subscription,
    pub(super) stop: Arc<AtomicI32>,
    pub(super) trainer: Trainer,
    pub(super) metrics: MetricsWriter,
    pub(super) stream: StreamTracker,
    /// `--ddp`: a batch received but kept for a later step (this rank's shard began its
    /// next epoch while others finish theirs).
    pub(super) held: Option<Received>,
    /// The pipeline's schedule of this stream (where its epochs and the stream end).
    pub(super) schedule: Option<ScheduleReply>,
    /// Publishers that did not say how their stream is scheduled.
    pub(super) unscheduled: Vec<u128>,
    /// The stream ended (the last batch of the pipeline's last epoch was trained on, or
    /// a data-parallel rank's was).
    pub(super) ended: bool,
    pub(super) ddp: Option<Ddp>,
    pub(super) bar: ProgressBar,
    pub(super) started: Instant,
    /// Seconds spent waiting for batches, and computing steps.
    pub(super) waiting: f64,
    pub(super) computing: f64,
    /// The losses of the last step.
    pub(super) last: Option<LossValues>,
    pub(super) steps: u64,
    pub(super) every: u64,
    pub(super) paths: RunPaths,
}

/// Where a batch lies in its stream.
fn position_of(batch: &Received) -> StreamPosition {
    StreamPosition::new(batch.header().epoch, batch.header().step)
}

/// Words per rank of the agreement before a step: the position of its batch, its state
/// (0 a batch, 1 stopping, 2 stream ended, 3 a lost batch), then the plan its pipeline
/// serves ([`PlanView::to_words`]).
const AGREEMENT_WORDS: usize = 3 + PlanView::WORDS;

impl Session<'_> {
    fn timeout(&self) -> Duration {
        Duration::from_secs(self.options.timeout_secs)
    }

    /// Steps until the run's length, the end of the stream (the last batch of the
    /// pipeline's last epoch, from its schedule) or a stop signal.
    pub fn train(&mut self) -> Result<(), RunError> {
        self.end_if_nothing_left()?;
        while self.trainer.step_count() < self.steps {
            let t = Instant::now();
            let batch = match self.held.take() {
                Some(batch) => Some(batch),
                None if self.ended => None,
                None => self.next_trainable()?,
            };
            let wait = t.elapsed().as_secs_f64();
            let Some(ddp) = &self.ddp else {
                let Some(batch) = batch else { break };
                let at = position_of(&batch);
                if self.step(Some(batch), at, wait)? || self.ended {
                    break;
                }
                continue;
            };
            // Data-parallel: every rank says where its batch lies, whether it is lost and
            // whether it stops (1: a signal, 2: its stream ended), and which plan its
            // pipeline serves; the step trains the earliest position (a rank whose shard
            // already began the next epoch keeps its batch for later and adds no
            // gradient, nor does a rank whose batch there is lost).
            let mine = batch.as_ref().map(position_of);
            let lost = batch
                .as_ref()
                .is_some_and(|b| b.header().flags & BATCH_LOST != 0);
            let state = if self.stop.load(Ordering::SeqCst) != 0 {
                1
            } else if batch.is_none() {
                2
            } else if lost {
                3
            } else {
                0
            };
            let what = format!("agreement before step {}", self.trainer.step_count() + 1);
            let plan = self
                .schedule
                .filter(|s| s.known == 1)
                .map(|s| PlanView::of(&s));
            let mut words = vec![
                mine.map_or(u64::MAX, |p| p.epoch),
                mine.map_or(u64::MAX, |p| p.batch),
                state,
            ];
            words.extend(PlanView::to_words(plan.as_ref()));
            let ranks = ddp.all_gather(&words, &what);
            let states: Vec<RankState> = ranks
                .chunks(AGREEMENT_WORDS)
                .map(|r| {
                    let at = StreamPosition::new(r[0], r[1]);
                    match r[2] {
                        1 => RankState::Stopping,
                        2 => RankState::Ended,
                        3 => RankState::Lost(at),
                        _ => RankState::At(at),
                    }
                })
                .collect();
            // Every rank sees the same words, so all of them stop here together.
            let plans: Vec<Option<PlanView>> = ranks
                .chunks(AGREEMENT_WORDS)
                .map(|r| PlanView::from_words(&r[3..]))
                .collect();
            stream::check_plans(&plans)?;
            let Some(at) = stream::agree(&states) else {
                self.held = batch;
                if states.contains(&RankState::Stopping) {
                    tracing::warn!("a rank is stopping: every rank stops after the same step");
                } else {
                    self.ended = true;
                    tracing::info!("every rank's stream ended");
                }
                break;
            };
            let batch = match batch {
                Some(b) if position_of(&b) == at => Some(b),
                other => {
                    self.held = other;
                    None
                }
            };
            if !stream::trains_at(&states, at) {
                // Every batch at this position is lost: no rank has a gradient, no rank
                // steps; the ranks holding one count it and move on.
                self.waiting += wait;
                if batch.is_some() {
                    self.pass_lost(at);
                }
                continue;
            }
            self.step(batch, at, wait)?;
        }
        Ok(())
    }

    /// Says that the batch at `at` is lost (once per batch).
    fn warn_lost(at: StreamPosition) {
        tracing::warn!(
            epoch = at.epoch,
            batch = at.batch,
            "batch lost: every sample failed in the pipeline"
        );
    }

    /// Counts the lost batch at `at` without a step: the stream moves past it, and its
    /// epoch (or the stream) ends after it as after any batch.
    fn pass_lost(&mut self, at: StreamPosition) {
        Self::warn_lost(at);
        self.passed(at);
    }

    /// The batch at `at` is behind this trainer (trained on, or lost): the next one is
    /// expected, and the stream ends when it was the pipeline's last.
    fn passed(&mut self, at: StreamPosition) {
        self.stream.trained(at);
        self.ended |= self
            .schedule
            .is_some_and(|s| s.ends_stream(at.epoch, at.batch));
    }

    /// The next batch to train on, past batches trained already and streams asked to
    /// continue elsewhere; `None` once a stop signal was caught.
    fn next_trainable(&mut self) -> Result<Option<Received>, RunError> {
        loop {
            let Some(batch) = next_batch(
                &self.subscription,
                &self.options.run,
                self.timeout(),
                &self.stop,
            )?
            else {
                return Ok(None);
            };
            let position = position_of(&batch);
            match self.stream.classify(batch.origin(), position) {
                Action::Train => {
                    self.learn_schedule(batch.origin())?;
                    return Ok(Some(batch));
                }
                Action::Skip { skipped } => {
                    tracing::warn!(
                        epoch = position.epoch,
                        batch = position.batch,
                        skipped,
                        "already trained on this batch: skipped"
                    );
                }
                Action::Resume { at, restarted } => {
                    drop(batch);
                    match self.continue_at(position, at, restarted) {
                        Ok(()) => {}
                        // A restarted pipeline that has already served every epoch: the
                        // stream ended.
                        Err(e) if e.run_complete().is_some() => {
                            tracing::info!(run = %self.options.run, "{e}");
                            self.ended = true;
                            return Ok(None);
                        }
                        Err(e) => return Err(e),
                    }
                }
            }
        }
    }

    /// A run resumed where its stream holds no batch any more has ended before its first
    /// batch, which would never come: a data-parallel job resumed on more ranks than the
    /// last epoch has samples left for gives some ranks an empty share of it. Such a rank
    /// then joins the others' steps without a gradient until their streams end too.
    fn end_if_nothing_left(&mut self) -> Result<(), RunError> {
        let Some(at) = self.stream.next() else {
            return Ok(()); // a fresh start: the first batch says where the stream is
        };
        let Some(reply) = self
            .subscription
            .schedule(SCHEDULE_WAIT)?
            .filter(|r| r.known == 1)
        else {
            return Ok(());
        };
        let last_epoch = reply.epochs > 0 && at.epoch + 1 >= reply.epochs;
        if last_epoch && at.batch >= reply.steps_in(at.epoch) {
            tracing::info!(
                epoch = at.epoch,
                batch = at.batch,
                "this stream holds no batch after the position resumed at (its share of the last epoch is empty): it has ended"
            );
            self.ended = true;
        }
        self.schedule = Some(reply);
        Ok(())
    }

    /// Asks the pipeline `origin` how this stream is scheduled, once per pipeline process.
    fn learn_schedule(&mut self, origin: u128) -> Result<(), RunError> {
        if self.schedule.is_some_and(|s| s.publisher() == origin)
            || self.unscheduled.contains(&origin)
        {
            return Ok(());
        }
        match self.subscription.schedule(SCHEDULE_WAIT)? {
            Some(reply) if reply.known == 1 => {
                tracing::debug!(
                    steps_per_epoch = reply.steps,
                    epochs = reply.epochs,
                    samples_per_epoch = reply.samples,
                    samples_per_step = reply.global_batch,
                    "the pipeline's schedule of this stream"
                );
                self.schedule = Some(reply);
            }
            _ => {
                tracing::warn!(
                    run = %self.options.run,
                    "the pipeline did not say how its epochs are scheduled: this trainer ends at --steps, a signal or --timeout-secs"
                );
                self.unscheduled.push(origin);
                self.schedule = None;
            }
        }
        Ok(())
    }

    /// The stream is not at this trainer's next batch `at` (a new pipeline, the old one
    /// died and was restarted, began elsewhere, or the stream jumped ahead): asks it to
    /// continue there.
    fn continue_at(
        &mut self,
        got: StreamPosition,
        at: StreamPosition,
        restarted: bool,
    ) -> Result<(), RunError> {
        tracing::warn!(
            got_epoch = got.epoch,
            got_batch = got.batch,
            epoch = at.epoch,
            batch = at.batch,
            restarted,
            "the stream is not at this trainer's next batch (a restarted pipeline, or another trainer's resume); asking it to continue there"
        );
        // By the samples the job had consumed when the old pipeline said how it deals
        // them: a pipeline restarted at another start sample still finds the place.
        let resume_at = match self.job_position(at) {
            Some(job) => job.resume_at(),
            None => ResumeAt::Step {
                epoch: at.epoch,
                step: at.batch,
            },
        };
        let (publisher, position) = ask_resume(
            &self.subscription,
            &self.options.run,
            resume_at,
            self.timeout(),
        )?;
        self.stream.resumed(publisher);
        self.stream.expect(position);
        // The new pipeline may deal the epoch differently: ask it at its first batch.
        self.schedule = None;
        Ok(())
    }

    /// The whole job's position when this stream's next batch is at `at` (data-parallel
    /// ranks step together), from the pipeline's schedule; `None` while it is unknown.
    fn job_position(&self, at: StreamPosition) -> Option<JobPosition> {
        let schedule = self
            .schedule
            .filter(|s| s.known == 1 && s.global_batch > 0)?;
        Some(JobPosition {
            epoch: at.epoch,
            samples: schedule.consumed(at.epoch, at.batch),
            global_batch: schedule.global_batch,
        })
    }

    /// One step at stream position `at` on `batch` (waited for `wait` seconds; `None`: a
    /// data-parallel rank without a batch at this step): metrics, log, progress and the
    /// periodic checkpoint. A lost batch is counted without a step on a lone trainer; a
    /// data-parallel rank takes part in the step without a gradient of its own. `true`
    /// when a stop signal was caught: a lone trainer ends here (data-parallel ranks agree
    /// on stopping before the next step).
    fn step(
        &mut self,
        batch: Option<Received>,
        at: StreamPosition,
        wait: f64,
    ) -> Result<bool, RunError> {
        let view = batch
            .as_ref()
            .map(Received::view)
            .transpose()
            .map_err(RunError::InvalidBatch)?;
        let had_batch = view.is_some();
        if view.as_ref().is_some_and(BatchView::is_lost) {
            if self.ddp.is_none() {
                drop(view);
                self.waiting += wait;
                self.pass_lost(at);
                return Ok(self.stop.load(Ordering::SeqCst) != 0);
            }
            Self::warn_lost(at);
        }
        let view = view.filter(|v| !v.is_lost());
        let meta = view.as_ref().map(|v| v.meta().clone());
        let number = self.trainer.step_count() + 1;
        let outcome = match (&self.ddp, &view) {
            (Some(ddp), view) => {
                let what = format!("gradient all-reduce of step {number}");
                let mut reduce = |values: &mut [f32]| ddp.all_reduce_sum(values, &what);
                self.trainer.step_synced(view.as_ref(), Some(&mut reduce))
            }
            (None, Some(view)) => self.trainer.step(view),
            (None, None) => return Err(RunError::NoBatchForStep { step: number }),
        }
        .map_err(|source| RunError::Step {
            step: number,
            at,
            source: Box::new(source),
        })?;
        drop(view);
        drop(batch);
        self.waiting += wait;
        self.computing += outcome.seconds;
        if had_batch {
            self.passed(at);
        }
        let mut record = step_record(number, at, meta.as_ref(), &outcome, wait);
        record.params_hash = self.trainer.params_hash();
        if let (Some(ddp), Some(global)) = (&self.ddp, &outcome.global) {
            record.ddp = Some(DdpRecord {
                rank: ddp.rank() as u32,
                world_size: ddp.size() as u32,
                loss: global.losses.total,
                samples: global.samples,
                reduce_ms: outcome.phases.reduce * 1e3,
                reduce_bytes: global.bytes,
            });
        }
        self.metrics.write(&record)?;
        log_step(&record, &outcome);
        self.bar.set_position(record.step);
        let shown = record.ddp.as_ref().map_or(record.loss, |d| d.loss);
        self.bar.set_message(format!("loss {shown:.4}"));
        let losses = outcome.global.map_or(outcome.losses, |g| g.losses);
        let stopping = self.stop.load(Ordering::SeqCst) != 0;
        let periodic = self.every > 0 && record.step.is_multiple_of(self.every);
        // Data-parallel ranks checkpoint together whatever their signals say (the stop
        // is agreed before the next step).
        if periodic
            && record.step < self.steps
            && (!stopping || self.ddp.is_some())
            && let Some(dir) = self.save_checkpoint(&losses)?
        {
            tracing::info!(checkpoint = %dir.display(), "checkpoint saved");
        }
        self.last = Some(losses);
        Ok(stopping)
    }

    /// The position this trainer continues at: the batch it holds, or the one after its
    /// last trained batch.
    fn next_position(&self) -> Option<StreamPosition> {
        self.held.as_ref().map(position_of).or(self.stream.next())
    }

    /// Saves a checkpoint (a data-parallel job: every rank calls this, rank 0 writes it
    /// with every rank's next position); the directory written, if this process wrote.
    /// `losses` are the last step's (over all ranks in a data-parallel job).
    fn save_checkpoint(&self, losses: &LossValues) -> Result<Option<PathBuf>, RunError> {
        let run = &self.options.run;
        let Some(ddp) = &self.ddp else {
            let next = self
                .next_position()
                .ok_or(RunError::CheckpointBeforeFirstStep)?;
            let mut state = self.trainer.checkpoint_state(run, next, losses);
            state.job = self.job_position(next);
            return Ok(Some(
                self.trainer
                    .save_checkpoint(&self.paths.checkpoints, &state)?,
            ));
        };
        let next = self.next_position().unwrap_or_default();
        let what = format!("checkpoint positions at step {}", self.trainer.step_count());
        let all = ddp.all_gather(&[next.epoch, next.batch], &what);
        if ddp.rank() != 0 {
            return Ok(None);
        }
        let mut state = self.trainer.checkpoint_state(run, next, losses);
        state.ranks = all.chunks(2).map(|p| [p[0], p[1]]).collect();
        // The job's samples: the slowest rank's position (ranks step together, so those
        // still in its epoch are all there; the others finished their share of it).
        let slowest = state
            .ranks
            .iter()
            .map(|&[e, b]| StreamPosition::new(e, b))
            .min()
            .unwrap_or(next);
        state.job = self.job_position(slowest);
        Ok(Some(
            self.trainer
                .save_checkpoint(&self.paths.checkpoints, &state)?,
        ))
    }

    /// The final checkpoint, the plot and the summary; the exit code of a signal
    /// ([`superflow_common::exit::signalled`]) when stopped by one.
    pub fn finish(self) -> Result<Option<i32>, RunError> {
        self.bar.finish_and_clear();
        let signal = self.stop.load(Ordering::SeqCst);
        let checkpoint = match &self.ddp {
            // Every rank takes part (the same steps on all ranks).
            Some(_) => self.last.filter(|_| self.trainer.step_count() > 0),
            None => self.last.filter(|_| self.stream.next().is_some()),
        };
        if let Some(losses) = checkpoint
            && let Some(dir) = self.save_checkpoint(&losses)?
        {
            if signal != 0 {
                tracing::warn!(
                    checkpoint = %dir.display(),
                    step = self.trainer.step_count(),
                    "stopped by a signal; checkpoint saved: continue with --resume"
                );
            } else {
                tracing::info!(checkpoint = %dir.display(), "final checkpoint saved");
            }
        }
        // Stopped early: by this process's signal, or (data-parallel) another rank's.
        let stopped_early = signal != 0
            || (self.ddp.is_some() && self.trainer.step_count() < self.steps && !self.ended);
        if stopped_early {
            let signal = if signal != 0 { signal } else { 15 };
            return Ok(Some(i32::from(superflow_common::exit::signalled(signal))));
        }
        if self.options.plot {
            metrics::plot_svg(&metrics::read(&self.paths.metrics)?, &self.paths.plot)?;
            tracing::info!(plot = %self.paths.plot.display(), "loss curves written");
        }
        if self.ended && self.trainer.step_count() < self.steps {
            tracing::info!(
                trained = self.trainer.step_count(),
                asked = self.steps,
                "the stream ended (the pipeline served its last epoch): trained {} of the {} steps asked",
                self.trainer.step_count(),
                self.steps
            );
        }
        let total = self.started.elapsed().as_secs_f64();
        tracing::info!(
            steps = self.trainer.step_count(),
            seconds = format_args!("{total:.1}"),
            data_stall_fraction = format_args!("{:.3}", self.waiting / total.max(1e-9)),
            compute_fraction = format_args!("{:.3}", self.computing / total.max(1e-9)),
            metrics = %self.paths.metrics.display(),
            "done training"
        );
        Ok(None)
    }
}

/// The metrics line of step `step` at stream position `at`, trained on the batch `meta`
/// (none: a data-parallel rank without a batch at this step) after waiting `wait`
/// seconds for it.
fn step_record(
    step: u64,
    at: StreamPosition,
    meta: Option<&BatchMeta>,
    outcome: &StepOutcome,
    wait: f64,
) -> StepRecord {
    let samples = meta.map_or(0, |m| m.sample_count as usize);
    StepRecord {
        step,
        epoch: at.epoch,
        batch: at.batch,
        loss: outcome.losses.total,
        l_sc: outcome.losses.sc,
        l_tc: outcome.losses.tc,
        l_d2s: outcome.losses.d2s,
        lr: outcome.lr,
        wait_ms: wait * 1e3,
        step_ms: outcome.seconds * 1e3,
        samples_per_s: samples as f64 / (wait + outcome.seconds).max(1e-9),
        samples,
        points: outcome.counts[0],
        pairings: outcome.counts[1],
        voxels: outcome.counts[2],
        sample_ids: outcome.sample_ids.clone(),
        params_hash: 0,
        ddp: None,
    }
}

fn log_step(record: &StepRecord, outcome: &StepOutcome) {
    tracing::info!(
        step = record.step,
        epoch = record.epoch,
        batch = record.batch,
        loss = format_args!("{:.4}", record.loss),
        l_sc = format_args!("{:.4}", record.l_sc),
        l_tc = format_args!("{:.4}", record.l_tc),
        l_d2s = format_args!("{:.4}", record.l_d2s),
        lr = format_args!("{:.2e}", record.lr),
        wait_ms = format_args!("{:.1}", record.wait_ms),
        step_ms = format_args!("{:.1}", record.step_ms),
        vit_ms = format_args!("{:.1}", outcome.phases.vit * 1e3),
        forward_ms = format_args!("{:.1}", outcome.phases.forward * 1e3),
        backward_ms = format_args!("{:.1}", outcome.phases.backward * 1e3),
        "step"
    );
}
