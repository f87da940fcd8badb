//! One SuperFlow training step, and the state a run carries between steps: the
//! trainable model, the frozen ViT, AdamW with the one-cycle schedule, checkpoints.

use crate::checkpoint::{self, CheckpointState};
use crate::config::TrainerConfig;
use crate::error::TrainerError;
use crate::inputs::StepInputs;
use crate::loss::{LossValues, SuperFlowLoss};
use crate::lr_schedule::OneCycle;
use crate::model::SuperFlowModel;
use crate::stream::StreamPosition;
use crate::sync::{GradientBuffer, params_hash};
use crate::vit::{DinoVit, imagenet_normalize};
use burn::module::Module;
use burn::optim::{AdamWConfig, GradientsParams, ModuleOptimizer};
use burn::tensor::{Bytes, Device};
use std::path::{Path, PathBuf};
use std::time::Instant;
use superflow_schemas::batch::BatchView;

/// What one step did.
#[derive(Debug, Clone)]
pub struct StepOutcome {
    /// The loss terms.
    pub losses: LossValues,
    /// `L_sc` of each frame.
    pub sc_frames: Vec<f64>,
    /// Learning rate used.
    pub lr: f64,
    /// Seconds spent (tensors, forward, backward, update).
    pub seconds: f64,
    /// Where `seconds` went.
    pub phases: StepPhases,
    /// Points, pairings and level-0 voxels of the batch.
    pub counts: [usize; 3],
    /// (epoch, index in epoch) of each sample.
    pub sample_ids: Vec<[u64; 2]>,
    /// The step over all data-parallel ranks (`None` on a single process).
    pub global: Option<GlobalStep>,
}

/// Sums a [`GradientBuffer`]'s values over the data-parallel ranks, in place.
pub type Reduce<'a> = dyn FnMut(&mut [f32]) + 'a;

/// A data-parallel step over all ranks.
#[derive(Debug, Clone, PartialEq)]
pub struct GlobalStep {
    /// The loss terms, averaged over the ranks' samples.
    pub losses: LossValues,
    /// Samples of all ranks.
    pub samples: usize,
    /// Bytes each rank sent into the all-reduce.
    pub bytes: usize,
}

/// What this rank's batch gave (all zero on a rank without a batch at this step).
#[derive(Debug, Default)]
struct Local {
    samples: usize,
    losses: LossValues,
    sc_frames: Vec<f64>,
    counts: [usize; 3],
    sample_ids: Vec<[u64; 2]>,
}

/// Seconds of each phase of a step (the CPU backend runs eagerly, so each phase's
/// operations are done when the next starts; on GPU backends the split is indicative).
#[derive(Debug, Clone, Copy, Default, PartialEq)]
pub struct StepPhases {
    /// Batch → tensors and the loss plan.
    pub inputs: f64,
    /// The frozen ViT.
    pub vit: f64,
    /// 3D network, 2D head and losses.
    pub forward: f64,
    /// Backward pass.
    pub backward: f64,
    /// Gradient all-reduce (data-parallel steps).
    pub reduce: f64,
    /// AdamW update.
    pub update: f64,
}

/// A training run's state.
pub struct Trainer {
    model: Option<SuperFlowModel>,
    vit: DinoVit,
    optim: ModuleOptimizer,
    loss: SuperFlowLoss,
    schedule: OneCycle,
    config: TrainerConfig,
    device: Device,
    vit_device: Device,
    step: u64,
}

/// Times the phases of a step: each mark stores the seconds since the previous one.
struct Lap(Instant);

impl Lap {
    fn start() -> Self {
        Self(Instant::now())
    }

    fn mark(&mut self, slot: &mut f64) {
        *slot = self.0.elapsed().as_secs_f64();
        self.0 = Instant::now();
    }
}

impl std::fmt::Debug for Trainer {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.debug_struct("Trainer")
            .field("step", &self.step)
            .field("device", &self.device)
            .field("config", &self.config)
            .finish_non_exhaustive()
    }
}

impl Trainer {
    /// A fresh run on `device` (the training device; autodiff is enabled on it and the
    /// frozen ViT runs on the same hardware without it).
    pub fn new(config: TrainerConfig, device: &Device) -> Result<Self, TrainerError> {
        config.validate()?;
        let device = device.clone().autodiff();
        let vit_device = device.clone().inner();
        let model_config = &config.model;
        let vit = DinoVit::frozen(
            model_config.image_weights.as_deref(),
            model_config.vit,
            model_config.seed,
            &vit_device,
        )?;
        match &model_config.image_weights {
            Some(path) => {
                tracing::info!(weights = %path.display(), dim = vit.config().dim, depth = vit.config().depth, "2D network: DINOv2 weights loaded");
            }
            None => tracing::warn!(
                preset = ?model_config.vit,
                "2D network: RANDOM ViT weights (no --image-weights). The 2D features are \
                 meaningless: use this for tests and demos only, never for pretraining"
            ),
        }
        let model = SuperFlowModel::new(
            &config.model.unet_config(),
            vit.config().dim,
            config.model.seed,
            &device,
        );
        tracing::info!(
            unet = ?config.model.unet,
            parameters = model.num_params(),
            "3D network initialized"
        );
        let o = &config.optim;
        let optim = AdamWConfig::new()
            .with_beta_1(o.betas[0] as f32)
            .with_beta_2(o.betas[1] as f32)
            .with_epsilon(o.eps as f32)
            .with_weight_decay(o.weight_decay as f32)
            .init();
        Ok(Self {
            model: Some(model),
            vit,
            optim,
            loss: SuperFlowLoss::new(config.loss.clone()),
            schedule: config.optim.schedule(),
            config,
            device,
            vit_device,
            step: 0,
        })
    }

    /// Optimizer steps taken.
    pub fn step_count(&self) -> u64 {
        self.step
    }

    /// The run's configuration.
    pub fn config(&self) -> &TrainerConfig {
        &self.config
    }

    /// The trainable model.
    pub fn model(&self) -> &SuperFlowModel {
        self.model
            .as_ref()
            .expect("the model is only taken during a step")
    }

    /// One step on `view`: tensors, frozen ViT, 3D network, losses, backward, AdamW.
    pub fn step(&mut self, view: &BatchView<'_>) -> Result<StepOutcome, TrainerError> {
        self.step_synced(Some(view), None)
    }

    /// One data-parallel step: the gradients of `view` (none when this rank has no batch
    /// at this step: its shard's epoch ended first) are flattened, combined with the
    /// other ranks' by `reduce` (an elementwise sum over ranks, see [`crate::sync`]),
    /// and the mean gradient is applied. Every rank applies the same update.
    ///
    /// Everything that can fail runs on a borrowed model; the model is taken out only
    /// for the optimizer's update, which cannot fail, so an error leaves the trainer as
    /// it was before the step.
    ///
    /// When no rank had a sample (every batch of the step lost, or none), there is
    /// nothing to learn from: the parameters, the optimizer and the step count stay as
    /// they were, and the outcome's `global.samples` is 0.
    pub fn step_synced(
        &mut self,
        view: Option<&BatchView<'_>>,
        reduce: Option<&mut Reduce<'_>>,
    ) -> Result<StepOutcome, TrainerError> {
        let started = Instant::now();
        let mut phases = StepPhases::default();
        let mut lap = Lap::start();
        let (local, grads) = match view {
            Some(view) => self.local_gradients(view, &mut phases, &mut lap)?,
            None if reduce.is_some() => (Local::default(), GradientsParams::new()),
            None => {
                return Err(TrainerError::StepWithoutBatch);
            }
        };
        let (grads, global, averaged) = match reduce {
            Some(reduce) => {
                let (grads, global, buffer) = self.reduce_gradients(&local, grads, reduce);
                lap.mark(&mut phases.reduce);
                (grads, Some(global), Some(buffer))
            }
            None => (grads, None, None),
        };
        let lr = self.schedule.lr(self.step);
        // With no sample on any rank AdamW would still move the weights (decay,
        // momentum) and the schedule would advance: no update from nothing.
        if global.as_ref().is_none_or(|g| g.samples > 0) {
            let model = self
                .model
                .take()
                .expect("the model is present between steps");
            let mut model = self.optim.step(lr, model, grads);
            if let Some(buffer) = averaged {
                model = buffer.average_buffers(model);
            }
            self.model = Some(model);
            self.step += 1;
            lap.mark(&mut phases.update);
        }
        Ok(StepOutcome {
            losses: local.losses,
            sc_frames: local.sc_frames,
            lr,
            seconds: started.elapsed().as_secs_f64(),
            phases,
            counts: local.counts,
            sample_ids: local.sample_ids,
            global,
        })
    }

    /// This rank's part of a step: tensors, frozen ViT, 3D network, losses and backward
    /// on `view`.
    fn local_gradients(
        &self,
        view: &BatchView<'_>,
        phases: &mut StepPhases,
        lap: &mut Lap,
    ) -> Result<(Local, GradientsParams), TrainerError> {
        let model = self.model();
        let inputs = StepInputs::from_view(
            view,
            &self.device,
            &self.vit_device,
            self.config.loss.pixel_stride,
        )?;
        lap.mark(&mut phases.inputs);
        let patches = self.vit.forward(imagenet_normalize(inputs.images.clone()));
        let patches = patches.autodiff();
        lap.mark(&mut phases.vit);
        let point_features = model.point_features(
            inputs.voxel_features.clone(),
            &inputs.levels,
            inputs.pairing_voxel.clone(),
        );
        let pixel_features = model.image_head.forward(patches, &inputs.sampler);
        let terms = self
            .loss
            .forward(point_features, pixel_features, &inputs.plan);
        lap.mark(&mut phases.forward);
        let losses = terms.values();
        if !losses.total.is_finite() {
            return Err(TrainerError::NonFiniteLoss {
                loss: losses.total,
                step: self.step + 1,
                epoch: view.meta().epoch,
                batch: view.meta().step,
            });
        }
        let grads = GradientsParams::from_grads(terms.total.backward(), model);
        lap.mark(&mut phases.backward);
        let local = Local {
            samples: view.meta().sample_count as usize,
            sc_frames: terms
                .sc_frames
                .iter()
                .map(|t| {
                    t.clone()
                        .into_data()
                        .try_into_vec::<f32>()
                        .ok()
                        .and_then(|v| v.first().copied())
                        .map_or(f64::NAN, f64::from)
                })
                .collect(),
            losses,
            counts: inputs.counts,
            sample_ids: inputs.sample_ids.iter().map(|s| [s[0], s[1]]).collect(),
        };
        Ok((local, grads))
    }

    /// Sums this rank's gradients and loss scalars with the other ranks' (`reduce`) and
    /// returns the mean gradient, the step's global losses and the buffer (its averaged
    /// BatchNorm statistics are applied after the update).
    fn reduce_gradients(
        &self,
        local: &Local,
        mut grads: GradientsParams,
        reduce: &mut Reduce<'_>,
    ) -> (GradientsParams, GlobalStep, GradientBuffer) {
        let model = self.model();
        let n = local.samples as f32;
        let l = &local.losses;
        let scalars = [l.total, l.sc, l.tc, l.d2s].map(|v| v as f32 * n);
        let mut buffer = GradientBuffer::from_gradients(model, &mut grads, local.samples, &scalars);
        reduce(&mut buffer.values);
        let total = buffer.samples();
        let mean = |i: usize| f64::from(buffer.scalars()[i]) / f64::from(total.max(1.0));
        let global = GlobalStep {
            losses: LossValues {
                total: mean(0),
                sc: mean(1),
                tc: mean(2),
                d2s: mean(3),
            },
            samples: total.round() as usize,
            bytes: buffer.bytes(),
        };
        let grads = buffer.into_gradients(model, &self.vit_device);
        (grads, global, buffer)
    }

    /// A 64-bit hash of the trainable parameters (equal on replicas holding the same
    /// model; see [`crate::sync::params_hash`]).
    pub fn params_hash(&self) -> u64 {
        params_hash(self.model())
    }

    /// The trainable model as a burnpack record (what a checkpoint's `model.bpk` holds).
    pub fn model_bytes(&self) -> Result<Vec<u8>, TrainerError> {
        let bytes = self
            .model()
            .clone()
            .into_record()
            .into_bytes()
            .map_err(|error| TrainerError::Encode {
                what: "model",
                error,
            })?;
        Ok(bytes.to_vec())
    }

    /// The optimizer state as a record (what a checkpoint's `optim.bpk` holds).
    pub fn optim_bytes(&self) -> Result<Vec<u8>, TrainerError> {
        let bytes = self
            .optim
            .into_bytes()
            .map_err(|error| TrainerError::Encode {
                what: "optimizer",
                error,
            })?;
        Ok(bytes.to_vec())
    }

    /// Saves model, optimizer and `state` ([`checkpoint_state`](Self::checkpoint_state):
    /// schedule position, stream position of the next batch) into `root`, atomically.
    pub fn save_checkpoint(
        &self,
        root: &Path,
        state: &CheckpointState,
    ) -> Result<PathBuf, TrainerError> {
        checkpoint::save(
            root,
            state,
            &self.model_bytes()?,
            &self.optim_bytes()?,
            self.config.checkpoint.keep,
        )
    }

    /// The state a checkpoint taken now records.
    pub fn checkpoint_state(
        &self,
        run: &str,
        next: StreamPosition,
        last: &LossValues,
    ) -> CheckpointState {
        CheckpointState {
            format: checkpoint::FORMAT.into(),
            step: self.step,
            next_epoch: next.epoch,
            next_batch: next.batch,
            ranks: Vec::new(),
            job: None,
            run: run.to_string(),
            config: self.config_toml(),
            lr: self.schedule.lr(self.step.saturating_sub(1)),
            loss: last.total,
        }
    }

    /// The configuration as TOML (what checkpoints record; data-parallel ranks compare it).
    pub fn config_toml(&self) -> String {
        toml::to_string(&self.config).unwrap_or_default()
    }

    /// Restores the newest checkpoint of `root`; returns its state (None if there is
    /// none).
    pub fn restore_latest(&mut self, root: &Path) -> Result<Option<CheckpointState>, TrainerError> {
        let Some(ckpt) = checkpoint::latest(root)? else {
            return Ok(None);
        };
        let read = |p: PathBuf| std::fs::read(&p).map_err(|e| TrainerError::io("reading", p, e));
        self.restore_bytes(
            read(ckpt.model_path())?,
            read(ckpt.optim_path())?,
            ckpt.state.step,
            &ckpt.dir,
        )?;
        tracing::info!(checkpoint = %ckpt.dir.display(), step = self.step, "restored");
        Ok(Some(ckpt.state))
    }

    /// Takes the model and optimizer records (the bytes of [`model_bytes`](Self::model_bytes)
    /// and [`optim_bytes`](Self::optim_bytes), read from a checkpoint in `source` or
    /// received from another rank) and the step count. An empty `optim` keeps the
    /// optimizer as it is (a fresh run's).
    pub fn restore_bytes(
        &mut self,
        model: Vec<u8>,
        optim: Vec<u8>,
        step: u64,
        source: &Path,
    ) -> Result<(), TrainerError> {
        let record = checkpoint::decode_record(model, source.join("model.bpk"))?;
        let current = self
            .model
            .take()
            .expect("the model is present between steps");
        self.model = Some(current.load_record(record));
        if !optim.is_empty() {
            let old = std::mem::replace(&mut self.optim, AdamWConfig::new().init());
            self.optim = old
                .from_bytes(Bytes::from_bytes_vec(optim))
                .map_err(|error| TrainerError::Record {
                    path: source.join("optim.bpk"),
                    error,
                })?;
        }
        self.step = step;
        Ok(())
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::unet::UNetPreset;
    use crate::vit::VitPreset;

    /// A data-parallel step in which no rank had a sample (every batch lost): the
    /// reduction brings zero samples, and nothing changes — parameters, step count — and
    /// nothing is NaN.
    #[test]
    fn a_step_without_any_sample_leaves_the_model_alone() {
        let mut config = TrainerConfig::default();
        config.model.unet = UNetPreset::Tiny;
        config.model.vit = VitPreset::Tiny;
        let mut trainer =
            Trainer::new(config, &burn::tensor::Device::flex()).expect("tiny trainer");
        let before = trainer.params_hash();
        let mut reduced = 0;
        // One rank alone: the sum over ranks is its own buffer.
        let mut reduce = |values: &mut [f32]| {
            reduced += 1;
            assert!(values.iter().all(|v| v.is_finite()));
        };
        let outcome = trainer
            .step_synced(None, Some(&mut reduce))
            .expect("a step without a batch takes part");
        assert_eq!(reduced, 1, "the rank took part in the all-reduce");
        let global = outcome.global.expect("a data-parallel step");
        assert_eq!(global.samples, 0);
        for loss in [global.losses.total, global.losses.sc, outcome.losses.total] {
            assert!(loss.is_finite(), "{loss}");
        }
        assert_eq!(trainer.step_count(), 0, "no optimizer step");
        assert_eq!(trainer.params_hash(), before, "no parameter moved");
    }
}
