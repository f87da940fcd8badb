//! `trainer.toml`: the networks, losses, optimizer, checkpoints and metrics of a run.
//! Every field has the official code's default; the command line overrides the common
//! ones. Unknown fields are errors (a typo must not silently train something else).

use crate::error::TrainerError;
use crate::loss::LossConfig;
use crate::lr_schedule::OneCycle;
use crate::unet::{UNetConfig, UNetPreset};
use crate::vit::VitPreset;
use serde::{Deserialize, Serialize};
use std::path::{Path, PathBuf};
use superflow_common::InvalidSetting;

/// The whole file.
#[derive(Debug, Clone, PartialEq, Default, Serialize, Deserialize)]
#[serde(deny_unknown_fields, default)]
pub struct TrainerConfig {
    /// `[model]`.
    pub model: ModelConfig,
    /// `[loss]`.
    pub loss: LossConfig,
    /// `[optim]`.
    pub optim: OptimConfig,
    /// `[checkpoint]`.
    pub checkpoint: CheckpointConfig,
}

/// `[model]`.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields, default)]
pub struct ModelConfig {
    /// 3D network size.
    pub unet: UNetPreset,
    /// 2D network size (ignored when `image_weights` is given: the file decides).
    pub vit: VitPreset,
    /// DINOv2 weights (safetensors, Hugging Face or torch-hub tensor names). Without
    /// them the ViT is random — useful for tests and the CPU demo only.
    pub image_weights: Option<PathBuf>,
    /// Seed of the initial weights.
    pub seed: u64,
}

impl Default for ModelConfig {
    fn default() -> Self {
        Self {
            unet: UNetPreset::Minkunet34,
            vit: VitPreset::Small,
            image_weights: None,
            seed: 0,
        }
    }
}

impl ModelConfig {
    /// The UNet's shape.
    pub fn unet_config(&self) -> UNetConfig {
        UNetConfig::preset(self.unet)
    }
}

/// `[optim]`: AdamW with a one-cycle schedule.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields, default)]
pub struct OptimConfig {
    /// Peak learning rate.
    pub lr: f64,
    /// Adam β₁, β₂.
    pub betas: [f64; 2],
    /// Decoupled weight decay.
    pub weight_decay: f64,
    /// Adam ε.
    pub eps: f64,
    /// Steps of the schedule (the run's length).
    pub steps: u64,
    /// Fraction of the steps spent warming up.
    pub pct_start: f64,
    /// Initial lr = lr / div_factor.
    pub div_factor: f64,
    /// Final lr = initial lr / final_div_factor.
    pub final_div_factor: f64,
}

impl Default for OptimConfig {
    fn default() -> Self {
        let s = OneCycle::superflow(1);
        Self {
            lr: s.max_lr,
            betas: [0.9, 0.999],
            weight_decay: 0.01,
            eps: 1e-6,
            steps: 1000,
            pct_start: s.pct_start,
            div_factor: s.div_factor,
            final_div_factor: s.final_div_factor,
        }
    }
}

impl OptimConfig {
    /// The learning-rate schedule.
    pub fn schedule(&self) -> OneCycle {
        OneCycle {
            max_lr: self.lr,
            total_steps: self.steps,
            pct_start: self.pct_start,
            div_factor: self.div_factor,
            final_div_factor: self.final_div_factor,
        }
    }
}

/// `[checkpoint]`.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields, default)]
pub struct CheckpointConfig {
    /// Directory of the run's checkpoints (`checkpoints/<run>` when unset).
    pub dir: Option<PathBuf>,
    /// Save every this many steps (0 = only at the end).
    pub every: u64,
    /// Checkpoints kept (older ones are removed).
    pub keep: usize,
}

impl Default for CheckpointConfig {
    fn default() -> Self {
        Self {
            dir: None,
            every: 500,
            keep: 3,
        }
    }
}

/// The settings a command line may override, each `None` when not given: the one place
/// flags become configuration ([`TrainerConfig::apply`]).
#[derive(Debug, Clone, Default, PartialEq)]
pub struct Overrides {
    /// `optim.steps`.
    pub steps: Option<u64>,
    /// `model.unet`.
    pub unet: Option<UNetPreset>,
    /// `model.vit`.
    pub vit: Option<VitPreset>,
    /// `model.image_weights`.
    pub image_weights: Option<PathBuf>,
    /// `loss.pixel_stride`.
    pub pixel_stride: Option<usize>,
    /// `optim.lr`.
    pub lr: Option<f64>,
    /// `model.seed`.
    pub seed: Option<u64>,
    /// `checkpoint.every`.
    pub checkpoint_every: Option<u64>,
}

impl TrainerConfig {
    /// `path`'s configuration (the defaults without one) with `overrides` applied,
    /// validated: what a command runs with.
    pub fn resolve(path: Option<&Path>, overrides: &Overrides) -> Result<Self, TrainerError> {
        let mut config = match path {
            Some(path) => Self::load(path)?,
            None => Self::default(),
        };
        config.apply(overrides);
        config.validate()?;
        Ok(config)
    }

    /// Replaces every setting `overrides` gives; the others keep their values.
    pub fn apply(&mut self, overrides: &Overrides) {
        let Overrides {
            steps,
            unet,
            vit,
            image_weights,
            pixel_stride,
            lr,
            seed,
            checkpoint_every,
        } = overrides;
        if let Some(v) = *steps {
            self.optim.steps = v;
        }
        if let Some(v) = *unet {
            self.model.unet = v;
        }
        if let Some(v) = *vit {
            self.model.vit = v;
        }
        if let Some(v) = image_weights {
            self.model.image_weights = Some(v.clone());
        }
        if let Some(v) = *pixel_stride {
            self.loss.pixel_stride = v;
        }
        if let Some(v) = *lr {
            self.optim.lr = v;
        }
        if let Some(v) = *seed {
            self.model.seed = v;
        }
        if let Some(v) = *checkpoint_every {
            self.checkpoint.every = v;
        }
    }

    /// Reads and validates `path`; errors name the file.
    pub fn load(path: &Path) -> Result<Self, TrainerError> {
        let text = std::fs::read_to_string(path)
            .map_err(|error| TrainerError::io("reading", path, error))?;
        let config: Self = toml::from_str(&text).map_err(|error| TrainerError::Toml {
            path: path.to_path_buf(),
            error,
        })?;
        config
            .validate()
            .map_err(|error| TrainerError::ConfigFile {
                path: path.to_path_buf(),
                error,
            })?;
        Ok(config)
    }

    /// Checks values a run cannot use; the error names the setting (`optim.steps`, ...).
    pub fn validate(&self) -> Result<(), InvalidSetting> {
        self.optim.schedule().validate()?;
        let l = &self.loss;
        if !(l.temperature > 0.0 && l.temperature.is_finite()) {
            return Err(InvalidSetting::new(
                "loss.temperature",
                l.temperature,
                "must be positive",
            ));
        }
        if l.pixel_stride == 0 {
            return Err(InvalidSetting::new(
                "loss.pixel_stride",
                l.pixel_stride,
                "must be at least 1",
            ));
        }
        let o = &self.optim;
        for (setting, value, ok, rule) in [
            ("optim.lr", o.lr, o.lr > 0.0, "must be positive"),
            ("optim.eps", o.eps, o.eps > 0.0, "must be positive"),
            (
                "optim.weight_decay",
                o.weight_decay,
                o.weight_decay >= 0.0,
                "must be ≥ 0",
            ),
        ] {
            if !ok {
                return Err(InvalidSetting::new(setting, value, rule));
            }
        }
        if let Some(b) = o.betas.iter().find(|b| !(0.0..1.0).contains(*b)) {
            return Err(InvalidSetting::new("optim.betas", b, "must be in [0, 1)"));
        }
        if self.checkpoint.keep == 0 {
            return Err(InvalidSetting::new(
                "checkpoint.keep",
                self.checkpoint.keep,
                "must be at least 1",
            ));
        }
        Ok(())
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn the_example_file_holds_the_defaults_and_typos_are_errors() {
        let path = Path::new(env!("CARGO_MANIFEST_DIR")).join("trainer.toml");
        assert_eq!(
            TrainerConfig::load(&path).expect("example parses"),
            TrainerConfig::default()
        );
        let err = toml::from_str::<TrainerConfig>("[loss]\ntemprature = 0.1\n").expect_err("typo");
        assert!(err.to_string().contains("temprature"), "{err}");
        let mut c = TrainerConfig::default();
        c.optim.steps = 1;
        let err = c.validate().expect_err("one step");
        assert_eq!(err.setting, "optim.steps", "{err}");
        assert!(err.to_string().starts_with("optim.steps = 1 "), "{err}");
    }

    #[test]
    fn overrides_replace_only_the_settings_given() {
        let mut file = TrainerConfig::default();
        file.optim.lr = 0.5;
        file.model.seed = 7;
        file.checkpoint.every = 40;
        let mut c = file.clone();
        c.apply(&Overrides::default());
        assert_eq!(c, file, "no flag changes nothing");
        c.apply(&Overrides {
            steps: Some(12),
            unet: Some(UNetPreset::Tiny),
            lr: Some(0.25),
            image_weights: Some(PathBuf::from("vit.safetensors")),
            ..Overrides::default()
        });
        assert_eq!(c.optim.steps, 12);
        assert_eq!(c.model.unet, UNetPreset::Tiny);
        assert_eq!(c.optim.lr, 0.25);
        assert_eq!(
            c.model.image_weights,
            Some(PathBuf::from("vit.safetensors"))
        );
        assert_eq!(c.model.seed, 7, "the file's value stays");
        assert_eq!(c.checkpoint.every, 40, "the file's value stays");
        let err = TrainerConfig::resolve(
            None,
            &Overrides {
                pixel_stride: Some(0),
                ..Overrides::default()
            },
        )
        .expect_err("a flag out of range is validated");
        assert!(err.to_string().contains("loss.pixel_stride"), "{err}");
    }
}
