//! `[loss]` of trainer.toml: the temperature, the terms' weights, the form of `L_d2s` and
//! the superpixel pooling's pixel stride.

use serde::{Deserialize, Serialize};

/// Which form of the dense-to-sparse term.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Default, Serialize, Deserialize)]
#[serde(rename_all = "lowercase")]
pub enum D2sForm {
    /// `mean(1 − cos)`, the paper's Eq. 3.
    Cosine,
    /// InfoNCE, as the official code.
    #[default]
    Infonce,
}

/// `[loss]` of trainer.toml.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields, default)]
pub struct LossConfig {
    /// InfoNCE temperature τ.
    pub temperature: f64,
    /// Weight of `L_sc`.
    pub w_sc: f64,
    /// Weight of `L_tc`.
    pub w_tc: f64,
    /// Weight of `L_d2s`.
    pub w_d2s: f64,
    /// Form of `L_d2s`.
    pub d2s: D2sForm,
    /// Superpixel pooling evaluates the 2D features at every `pixel_stride`-th pixel of
    /// each row and column (1 = every pixel, as the official code; larger strides make
    /// CPU training affordable — the features at those pixels are exact).
    pub pixel_stride: usize,
}

impl Default for LossConfig {
    fn default() -> Self {
        Self {
            temperature: 0.07,
            w_sc: 1.0,
            w_tc: 1.0,
            w_d2s: 1.0,
            d2s: D2sForm::Infonce,
            pixel_stride: 1,
        }
    }
}
