//! One SuperFlow training step, and the state a run carries between steps: the
//! trainable model, the frozen ViT, AdamW with the one-cycle schedule, checkpoints.

use crate::checkpoint::{self, CheckpointState};
use crate::config::TrainerConfig;
use crate::error::TrainerError;
use crate::inputs::StepInputs;
use crate::loss::{LossValues, SuperFlowLoss};
use crate::model::SuperFlowModel;
use crate::schedule::OneCycle;
use crate::stream::StreamPosition;
use crate::vit::{DinoVit, VitConfig, imagenet_normalize};
use burn::module::Module;
use burn::optim::{AdamWConfig, GradientsParams, ModuleOptimizer};
use burn::store::ModuleRecord;
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
        let vit = match &config.model.image_weights {
            Some(path) => {
                let vit = DinoVit::load_safetensors(path, &vit_device)?;
                tracing::info!(weights = %path.display(), dim = vit.config().dim, depth = vit.config().depth, "2D network: DINOv2 weights loaded");
                vit
            }
            None => {
                let vit_config = VitConfig::preset(config.model.vit);
                tracing::warn!(
                    preset = ?config.model.vit,
                    "2D network: RANDOM ViT weights (no --image-weights). The 2D features are \
                     meaningless: use this for tests and demos only, never for pretraining"
                );
                DinoVit::random(
                    &vit_config,
                    config.model.seed ^ 0x005e_ed0f_u64,
                    &vit_device,
                )
            }
        };
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
        let started = Instant::now();
        let mut phases = StepPhases::default();
        let mut lap = Instant::now();
        let mut mark = |slot: &mut f64| {
            *slot = lap.elapsed().as_secs_f64();
            lap = Instant::now();
        };
        let inputs = StepInputs::from_view(
            view,
            &self.device,
            &self.vit_device,
            self.config.loss.pixel_stride,
        )?;
        mark(&mut phases.inputs);
        let patches = self.vit.forward(imagenet_normalize(inputs.images.clone()));
        let patches = patches.autodiff();
        mark(&mut phases.vit);
        let model = self
            .model
            .take()
            .expect("the model is present between steps");
        let point_features = model.point_features(
            inputs.voxel_features.clone(),
            &inputs.levels,
            inputs.pairing_voxel.clone(),
        );
        let pixel_features = model.image_head.forward(patches, &inputs.sampler);
        let terms = self
            .loss
            .forward(point_features, pixel_features, &inputs.plan);
        mark(&mut phases.forward);
        let grads = GradientsParams::from_grads(terms.total.backward(), &model);
        mark(&mut phases.backward);
        let lr = self.schedule.lr(self.step);
        self.model = Some(self.optim.step(lr, model, grads));
        self.step += 1;
        mark(&mut phases.update);
        let losses = terms.values();
        if !losses.total.is_finite() {
            return Err(TrainerError::NonFiniteLoss {
                loss: losses.total,
                step: self.step,
                epoch: view.meta().epoch,
                batch: view.meta().step,
            });
        }
        let sc_frames = terms
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
            .collect();
        Ok(StepOutcome {
            losses,
            sc_frames,
            lr,
            seconds: started.elapsed().as_secs_f64(),
            phases,
            counts: inputs.counts,
            sample_ids: inputs.sample_ids.iter().map(|s| [s[0], s[1]]).collect(),
        })
    }

    /// Saves model, optimizer, schedule position and `next`, the stream position of the
    /// next batch to train on, into `root` (atomically).
    pub fn save_checkpoint(
        &self,
        root: &Path,
        run: &str,
        next: StreamPosition,
        last: &LossValues,
    ) -> Result<PathBuf, TrainerError> {
        let model = (self.model().clone().into_record().into_bytes()).map_err(|error| {
            TrainerError::Encode {
                what: "model",
                error,
            }
        })?;
        let optim = self
            .optim
            .into_bytes()
            .map_err(|error| TrainerError::Encode {
                what: "optimizer",
                error,
            })?;
        let state = CheckpointState {
            format: checkpoint::FORMAT.into(),
            step: self.step,
            next_epoch: next.epoch,
            next_batch: next.batch,
            run: run.to_string(),
            config: toml::to_string(&self.config).unwrap_or_default(),
            lr: self.schedule.lr(self.step.saturating_sub(1)),
            loss: last.total,
        };
        checkpoint::save(root, &state, &model, &optim, self.config.checkpoint.keep)
    }

    /// Restores the newest checkpoint of `root`; returns its state (None if there is
    /// none).
    pub fn restore_latest(&mut self, root: &Path) -> Result<Option<CheckpointState>, TrainerError> {
        let Some(ckpt) = checkpoint::latest(root)? else {
            return Ok(None);
        };
        let read = |p: PathBuf| std::fs::read(&p).map_err(|e| TrainerError::io("reading", p, e));
        let record = ModuleRecord::from_bytes(Bytes::from_bytes_vec(read(ckpt.model_path())?))
            .map_err(|error| TrainerError::Record {
                path: ckpt.model_path(),
                error,
            })?;
        let model = self
            .model
            .take()
            .expect("the model is present between steps");
        self.model = Some(model.load_record(record));
        let optim = std::mem::replace(&mut self.optim, AdamWConfig::new().init());
        self.optim = optim
            .from_bytes(Bytes::from_bytes_vec(read(ckpt.optim_path())?))
            .map_err(|error| TrainerError::Record {
                path: ckpt.optim_path(),
                error,
            })?;
        self.step = ckpt.state.step;
        tracing::info!(checkpoint = %ckpt.dir.display(), step = self.step, "restored");
        Ok(Some(ckpt.state))
    }
}
