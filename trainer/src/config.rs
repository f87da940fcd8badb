//! `trainer.toml`: the networks, losses, optimizer, checkpoints and metrics of a run.
//! Every field has the official code's default; the command line overrides the common
//! ones. Unknown fields are errors (a typo must not silently train something else).

use crate::error::{InvalidConfig, TrainerError};
use crate::loss::LossConfig;
use crate::schedule::OneCycle;
use crate::sparse::{UNetConfig, UNetPreset};
use crate::vit::VitPreset;
use serde::{Deserialize, Serialize};
use std::path::{Path, PathBuf};

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

impl TrainerConfig {
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
    pub fn validate(&self) -> Result<(), InvalidConfig> {
        self.optim.schedule().validate()?;
        let l = &self.loss;
        if !(l.temperature > 0.0 && l.temperature.is_finite()) {
            return Err(InvalidConfig::new(
                "loss.temperature",
                l.temperature,
                "must be positive",
            ));
        }
        if l.pixel_stride == 0 {
            return Err(InvalidConfig::new(
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
                return Err(InvalidConfig::new(setting, value, rule));
            }
        }
        if let Some(b) = o.betas.iter().find(|b| !(0.0..1.0).contains(*b)) {
            return Err(InvalidConfig::new("optim.betas", b, "must be in [0, 1)"));
        }
        if self.checkpoint.keep == 0 {
            return Err(InvalidConfig::new(
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
}
