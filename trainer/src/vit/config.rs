//! The shape of a [`DinoVit`](super::DinoVit): the released sizes ([`VitPreset`]) and the
//! dimensions of one network ([`VitConfig`]).

use serde::{Deserialize, Serialize};
use std::fmt;
use superflow_common::InvalidSetting;

/// The backbone sizes [`VitConfig::preset`] knows. Names are lowercase in serde, on the
/// command line ([`clap::ValueEnum`]: `--vit small`, listed by `--help`) and in
/// [`Display`](fmt::Display): `tiny`, `small`, `base`, `large`.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Hash, Serialize, Deserialize, clap::ValueEnum)]
#[serde(rename_all = "lowercase")]
#[value(rename_all = "lowercase")]
pub enum VitPreset {
    /// A 2-block, 32-wide model for tests and CPU demos (no released checkpoint).
    Tiny,
    /// ViT-S/14 (`dinov2_vits14`, `facebook/dinov2-small`).
    Small,
    /// ViT-B/14 (`dinov2_vitb14`, `facebook/dinov2-base`).
    Base,
    /// ViT-L/14 (`dinov2_vitl14`, `facebook/dinov2-large`).
    Large,
}

impl VitPreset {
    /// Every preset, smallest first.
    pub const ALL: [VitPreset; 4] = [Self::Tiny, Self::Small, Self::Base, Self::Large];

    /// The preset's lowercase name.
    pub fn name(self) -> &'static str {
        match self {
            Self::Tiny => "tiny",
            Self::Small => "small",
            Self::Base => "base",
            Self::Large => "large",
        }
    }
}

impl fmt::Display for VitPreset {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        f.write_str(self.name())
    }
}

/// The shape of a [`DinoVit`](super::DinoVit).
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct VitConfig {
    /// Token width (embedding dimension).
    pub dim: usize,
    /// Number of transformer blocks.
    pub depth: usize,
    /// Attention heads per block; `dim` is a multiple of it.
    pub heads: usize,
    /// Hidden width of each block's MLP.
    pub mlp_hidden: usize,
    /// Patch side in pixels; image sides must be multiples of it.
    pub patch: usize,
    /// Patch grid `[rows, cols]` the position embeddings were trained for. Images with another
    /// grid get the embeddings resized bicubically.
    pub pos_grid: [usize; 2],
    /// Epsilon of every LayerNorm.
    pub eps: f64,
}

impl VitConfig {
    /// The configuration of a preset. The released sizes have 64-wide heads, a 4× MLP and a
    /// 37×37 position grid (the public checkpoints are trained at 518×518 pixels).
    pub fn preset(preset: VitPreset) -> Self {
        let (dim, depth, heads, pos_side) = match preset {
            VitPreset::Tiny => (32, 2, 2, 4),
            VitPreset::Small => (384, 12, 6, 37),
            VitPreset::Base => (768, 12, 12, 37),
            VitPreset::Large => (1024, 24, 16, 37),
        };
        Self {
            dim,
            depth,
            heads,
            mlp_hidden: 4 * dim,
            patch: 14,
            pos_grid: [pos_side, pos_side],
            eps: 1e-6,
        }
    }

    /// Width of one attention head.
    pub fn head_dim(&self) -> usize {
        self.dim / self.heads
    }

    /// Checks that every size is positive and that `dim` splits evenly into `heads`.
    pub fn validate(&self) -> Result<(), InvalidSetting> {
        let sizes = [
            ("vit.dim", self.dim),
            ("vit.depth", self.depth),
            ("vit.heads", self.heads),
            ("vit.mlp_hidden", self.mlp_hidden),
            ("vit.patch", self.patch),
            ("vit.pos_grid rows", self.pos_grid[0]),
            ("vit.pos_grid cols", self.pos_grid[1]),
        ];
        for (setting, size) in sizes {
            if size == 0 {
                return Err(InvalidSetting::new(setting, size, "must be positive"));
            }
        }
        if !self.dim.is_multiple_of(self.heads) {
            return Err(InvalidSetting::new(
                "vit.dim",
                self.dim,
                "must be a multiple of vit.heads",
            ));
        }
        if self.eps.is_nan() || self.eps <= 0.0 {
            return Err(InvalidSetting::new("vit.eps", self.eps, "must be positive"));
        }
        Ok(())
    }

    /// The attention head count for a checkpoint of width `dim`, which its tensors do not
    /// record: a preset's count when `dim` is a preset's width, else 64-wide heads (all DINOv2
    /// releases use them).
    pub(super) fn heads_for_dim(dim: usize) -> Option<usize> {
        VitPreset::ALL
            .into_iter()
            .map(Self::preset)
            .find(|config| config.dim == dim)
            .map(|config| config.heads)
            .or(dim.is_multiple_of(64).then_some(dim / 64))
    }
}
