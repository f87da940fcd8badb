//! The frozen 2D backbone: a DINOv2-architecture vision transformer.
//!
//! [`DinoVit`] cuts an ImageNet-normalized image into 14×14 patches, embeds them, prepends a
//! class token, adds learned position embeddings (resized bicubically when the image's patch
//! grid differs from the trained one) and runs pre-norm transformer blocks with LayerScale:
//! `x + ls1·attn(norm1(x))`, then `x + ls2·mlp(norm2(x))`. [`DinoVit::forward`] returns the
//! patch tokens after the final LayerNorm as a feature map `[I, dim, H/14, W/14]`.
//!
//! Weights come from a DINOv2 checkpoint in safetensors format ([`DinoVit::load_safetensors`]:
//! Hugging Face or facebookresearch/dinov2 torch-hub names, f32/f16/bf16) or from a seeded random
//! init ([`DinoVit::random`]) for tests and CPU demos. Camera images enter through
//! [`imagenet_normalize`].
//!
//! ```no_run
//! use burn::tensor::{Device, Tensor};
//! use superflow_trainer::vit::{DinoVit, VitConfig, VitPreset, imagenet_normalize};
//!
//! let device = Device::flex();
//! let vit = DinoVit::random(&VitConfig::preset(VitPreset::Small), 0, &device);
//! let rgb = Tensor::<4>::zeros([1, 224, 448, 3], &device); // [I, H, W, 3], 0..255
//! let features = vit.forward(imagenet_normalize(rgb));
//! assert_eq!(features.dims(), [1, 384, 16, 32]);
//! ```

use std::fmt;
use std::path::Path;
use std::str::FromStr;

use anyhow::{Context, bail, ensure};
use burn::module::{Module, Param};
use burn::nn::{LayerNorm, LayerNormConfig, Linear};
use burn::tensor::activation::gelu;
use burn::tensor::module::attention;
use burn::tensor::ops::AttentionModuleOptions;
use burn::tensor::{Device, Tensor, TensorData, bf16, f16};
use safetensors::{Dtype, SafeTensors};
use serde::{Deserialize, Serialize};

/// Per-channel (RGB) mean of ImageNet, on the 0..1 scale.
const IMAGENET_MEAN: [f32; 3] = [0.485, 0.456, 0.406];
/// Per-channel (RGB) standard deviation of ImageNet, on the 0..1 scale.
const IMAGENET_STD: [f32; 3] = [0.229, 0.224, 0.225];

/// The backbone sizes [`VitConfig::preset`] knows. Names are lowercase in serde, [`FromStr`]
/// and [`Display`](fmt::Display): `tiny`, `small`, `base`, `large`.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Hash, Serialize, Deserialize)]
#[serde(rename_all = "lowercase")]
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

impl FromStr for VitPreset {
    type Err = UnknownPreset;

    fn from_str(name: &str) -> Result<Self, Self::Err> {
        Self::ALL
            .into_iter()
            .find(|preset| preset.name() == name)
            .ok_or_else(|| UnknownPreset(name.to_owned()))
    }
}

/// A name that is none of [`VitPreset`]'s.
#[derive(Debug, Clone, PartialEq, Eq, thiserror::Error)]
#[error("unknown ViT preset `{0}`: expected tiny, small, base or large")]
pub struct UnknownPreset(pub String);

/// The shape of a [`DinoVit`].
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
    pub fn validate(&self) -> anyhow::Result<()> {
        let sizes = [
            ("dim", self.dim),
            ("depth", self.depth),
            ("heads", self.heads),
            ("mlp_hidden", self.mlp_hidden),
            ("patch", self.patch),
            ("pos_grid rows", self.pos_grid[0]),
            ("pos_grid cols", self.pos_grid[1]),
        ];
        for (name, size) in sizes {
            ensure!(size > 0, "ViT config: {name} must be positive");
        }
        ensure!(
            self.dim.is_multiple_of(self.heads),
            "ViT config: dim {} is not a multiple of heads {}",
            self.dim,
            self.heads
        );
        ensure!(
            self.eps > 0.0,
            "ViT config: eps must be positive, got {}",
            self.eps
        );
        Ok(())
    }

    /// The attention head count for a checkpoint of width `dim`, which its tensors do not
    /// record: a preset's count when `dim` is a preset's width, else 64-wide heads (all DINOv2
    /// releases use them).
    fn heads_for_dim(dim: usize) -> Option<usize> {
        VitPreset::ALL
            .into_iter()
            .map(Self::preset)
            .find(|config| config.dim == dim)
            .map(|config| config.heads)
            .or(dim.is_multiple_of(64).then_some(dim / 64))
    }
}

/// A DINOv2-architecture ViT (no register tokens, LayerScale, exact-erf GELU MLP), used frozen:
/// its parameters are created without gradients (`unfreeze` it to fine-tune).
#[derive(Module, Debug)]
pub struct DinoVit {
    /// The patch-embedding convolution as a linear map of flattened `[3, p, p]` patches:
    /// weight `[3·p·p, dim]`.
    patch_embed: Linear,
    /// Class token `[dim]`.
    cls_token: Param<Tensor<1>>,
    /// Position embeddings for `config.pos_grid`, class token first: `[1 + rows·cols, dim]`.
    pos_embed: Param<Tensor<2>>,
    /// The transformer blocks, input first.
    blocks: Vec<Block>,
    /// Final LayerNorm.
    norm: LayerNorm,
    /// The shape this network was built with.
    #[module(skip)]
    config: VitConfig,
}

/// One pre-norm transformer block with LayerScale.
#[derive(Module, Debug)]
struct Block {
    norm1: LayerNorm,
    /// Fused query/key/value projection `[dim, 3·dim]`; outputs ordered (q|k|v, head, channel).
    qkv: Linear,
    /// Attention output projection `[dim, dim]`.
    proj: Linear,
    /// LayerScale of the attention branch `[dim]`.
    ls1: Param<Tensor<1>>,
    norm2: LayerNorm,
    /// MLP input layer `[dim, mlp_hidden]`.
    fc1: Linear,
    /// MLP output layer `[mlp_hidden, dim]`.
    fc2: Linear,
    /// LayerScale of the MLP branch `[dim]`.
    ls2: Param<Tensor<1>>,
    #[module(skip)]
    heads: usize,
}

impl DinoVit {
    /// The shape this network was built with.
    pub fn config(&self) -> &VitConfig {
        &self.config
    }

    /// A network with seeded random weights: the same `seed` gives the same weights on every
    /// device. Matrices, tokens and position embeddings are drawn from a normal distribution
    /// with standard deviation 0.02 truncated at 2σ; biases are zero, LayerNorms identity and
    /// LayerScales one (so that every block contributes).
    ///
    /// # Panics
    ///
    /// Panics if `config` does not pass [`VitConfig::validate`].
    pub fn random(config: &VitConfig, seed: u64, device: &Device) -> Self {
        if let Err(error) = config.validate() {
            panic!("DinoVit::random: {error}");
        }
        Self::build(config, device, &mut RandomInit::new(seed))
            .expect("random init produces every weight at the requested shape")
    }

    /// Loads a DINOv2 checkpoint, inferring the shape from its tensors.
    ///
    /// Accepts the Hugging Face `Dinov2Model` names (`embeddings.cls_token`,
    /// `encoder.layer.{i}.attention.attention.query`, …) and the facebookresearch/dinov2
    /// torch-hub names (`cls_token`, `blocks.{i}.attn.qkv`, …), under any common prefix such as
    /// `backbone.`; tensors in f32, f16 or bf16 (computed in f32). Other tensors in the file
    /// (heads, `mask_token`) are ignored. The head count, which no tensor records, is taken to
    /// be a preset's when the width matches one and `dim / 64` otherwise.
    ///
    /// # Errors
    ///
    /// Fails, naming the file and the tensor, when a tensor is missing or has another shape or
    /// dtype, and refuses register-token (`*_reg`) and SwiGLU (ViT-g) checkpoints.
    pub fn load_safetensors(path: &Path, device: &Device) -> anyhow::Result<Self> {
        let bytes = std::fs::read(path).with_context(|| format!("reading {}", path.display()))?;
        let file = SafeTensors::deserialize(&bytes)
            .with_context(|| format!("parsing safetensors file {}", path.display()))?;
        let mut checkpoint = Checkpoint::new(path, &file)?;
        let config = checkpoint.infer_config()?;
        Self::build(&config, device, &mut checkpoint)
    }

    /// The patch tokens of `images`, after the final LayerNorm, as a feature map.
    ///
    /// # Shapes
    ///
    /// - images: `[I, 3, H, W]`, ImageNet-normalized (see [`imagenet_normalize`])
    /// - output: `[I, dim, H / patch, W / patch]`
    ///
    /// # Panics
    ///
    /// Panics if the images do not have 3 channels or a side is not a positive multiple of the
    /// patch size.
    pub fn forward(&self, images: Tensor<4>) -> Tensor<4> {
        let [batch, _, height, width] = images.dims();
        let [rows, cols] = [height / self.config.patch, width / self.config.patch];
        let dim = self.config.dim;
        self.forward_tokens(images) // [I, 1 + rows·cols, dim]
            .narrow(1, 1, rows * cols) // [I, rows·cols, dim]
            .reshape([batch, rows, cols, dim])
            .permute([0, 3, 1, 2]) // [I, dim, rows, cols]
    }

    /// Every token after the final LayerNorm: the class token, then the patch tokens in
    /// row-major order.
    ///
    /// # Shapes
    ///
    /// - images: `[I, 3, H, W]`, ImageNet-normalized (see [`imagenet_normalize`])
    /// - output: `[I, 1 + (H / patch)·(W / patch), dim]`
    ///
    /// # Panics
    ///
    /// As [`forward`](Self::forward).
    pub fn forward_tokens(&self, images: Tensor<4>) -> Tensor<3> {
        let [batch, channels, height, width] = images.dims();
        let VitConfig { dim, patch, .. } = self.config;
        assert!(
            channels == 3
                && height > 0
                && width > 0
                && height.is_multiple_of(patch)
                && width.is_multiple_of(patch),
            "DinoVit: images must be [I, 3, H, W] with H and W positive multiples of {patch}, \
             got [{batch}, {channels}, {height}, {width}]"
        );
        let [rows, cols] = [height / patch, width / patch];

        let patches = images
            .reshape([batch, 3, rows, patch, cols, patch])
            .permute([0, 2, 4, 1, 3, 5]) // [I, rows, cols, 3, p, p]
            .reshape([batch, rows * cols, 3 * patch * patch]);
        let patch_tokens = self.patch_embed.forward(patches); // [I, rows·cols, dim]
        let cls = self
            .cls_token
            .val()
            .reshape([1, 1, dim])
            .repeat_dim(0, batch); // [I, 1, dim]
        let pos = self.position_embeddings([rows, cols]); // [1 + rows·cols, dim]
        let tokens = Tensor::cat(vec![cls, patch_tokens], 1) + pos.unsqueeze::<3>();

        let tokens = self
            .blocks
            .iter()
            .fold(tokens, |tokens, block| block.forward(tokens));
        self.norm.forward(tokens)
    }

    /// The position embeddings for a patch grid: the trained ones when `grid` is
    /// `config.pos_grid`, else their patch part resized bicubically as Hugging Face's
    /// `Dinov2Embeddings.interpolate_pos_encoding` does (see [`resize_matrix`]), the class
    /// position kept.
    ///
    /// # Shapes
    ///
    /// - output: `[1 + rows·cols, dim]`
    fn position_embeddings(&self, grid: [usize; 2]) -> Tensor<2> {
        let pos = self.pos_embed.val();
        if grid == self.config.pos_grid {
            return pos;
        }
        let [rows, cols] = grid;
        let [trained_rows, trained_cols] = self.config.pos_grid;
        let dim = self.config.dim;
        let device = pos.device();

        let cls = pos.clone().narrow(0, 0, 1); // [1, dim]
        // Bicubic resize is separable: along the columns, then along the rows.
        let by_cols = resize_matrix(trained_cols, cols, &device); // [cols, trained_cols]
        let by_rows = resize_matrix(trained_rows, rows, &device); // [rows, trained_rows]
        let patch = pos
            .narrow(0, 1, trained_rows * trained_cols)
            .reshape([trained_rows, trained_cols, dim])
            .swap_dims(0, 1)
            .reshape([trained_cols, trained_rows * dim]);
        let patch = by_cols
            .matmul(patch) // [cols, trained_rows·dim]
            .reshape([cols, trained_rows, dim])
            .swap_dims(0, 1)
            .reshape([trained_rows, cols * dim]);
        let patch = by_rows
            .matmul(patch) // [rows, cols·dim]
            .reshape([rows * cols, dim]);
        Tensor::cat(vec![cls, patch], 0)
    }

    /// Assembles the network from `source`, which hands out each weight in PyTorch's layout.
    fn build(
        config: &VitConfig,
        device: &Device,
        source: &mut impl WeightSource,
    ) -> anyhow::Result<Self> {
        let VitConfig {
            dim,
            depth,
            heads,
            mlp_hidden,
            patch,
            pos_grid: [rows, cols],
            eps,
        } = *config;
        let mut take = |weight: WeightKey, shape: &[usize]| source.take(weight, shape);

        let cls_token = tensor_param(take(WeightKey::ClsToken, &[1, 1, dim])?, [dim], device);
        let pos_embed = tensor_param(
            take(WeightKey::PosEmbed, &[1, 1 + rows * cols, dim])?,
            [1 + rows * cols, dim],
            device,
        );
        let patch_embed = linear(
            take(WeightKey::PatchWeight, &[dim, 3, patch, patch])?,
            take(WeightKey::PatchBias, &[dim])?,
            [dim, 3 * patch * patch],
            device,
        );

        let mut blocks = Vec::with_capacity(depth);
        for index in 0..depth {
            let mut take =
                |weight: BlockWeight, shape: &[usize]| take(WeightKey::Block(index, weight), shape);
            let mut norm = |weight, bias| -> anyhow::Result<LayerNorm> {
                Ok(layer_norm(
                    take(weight, &[dim])?,
                    take(bias, &[dim])?,
                    eps,
                    device,
                ))
            };
            let norm1 = norm(BlockWeight::Norm1Weight, BlockWeight::Norm1Bias)?;
            let norm2 = norm(BlockWeight::Norm2Weight, BlockWeight::Norm2Bias)?;
            blocks.push(Block {
                norm1,
                qkv: linear(
                    take(BlockWeight::QkvWeight, &[3 * dim, dim])?,
                    take(BlockWeight::QkvBias, &[3 * dim])?,
                    [3 * dim, dim],
                    device,
                ),
                proj: linear(
                    take(BlockWeight::ProjWeight, &[dim, dim])?,
                    take(BlockWeight::ProjBias, &[dim])?,
                    [dim, dim],
                    device,
                ),
                ls1: tensor_param(take(BlockWeight::Ls1, &[dim])?, [dim], device),
                norm2,
                fc1: linear(
                    take(BlockWeight::Fc1Weight, &[mlp_hidden, dim])?,
                    take(BlockWeight::Fc1Bias, &[mlp_hidden])?,
                    [mlp_hidden, dim],
                    device,
                ),
                fc2: linear(
                    take(BlockWeight::Fc2Weight, &[dim, mlp_hidden])?,
                    take(BlockWeight::Fc2Bias, &[dim])?,
                    [dim, mlp_hidden],
                    device,
                ),
                ls2: tensor_param(take(BlockWeight::Ls2, &[dim])?, [dim], device),
                heads,
            });
        }
        let norm = layer_norm(
            take(WeightKey::NormWeight, &[dim])?,
            take(WeightKey::NormBias, &[dim])?,
            eps,
            device,
        );

        let vit = Self {
            patch_embed,
            cls_token,
            pos_embed,
            blocks,
            norm,
            config: config.clone(),
        };
        Ok(vit.no_grad())
    }
}

impl Block {
    /// # Shapes
    ///
    /// - tokens: `[I, N, dim]`
    /// - output: `[I, N, dim]`
    fn forward(&self, tokens: Tensor<3>) -> Tensor<3> {
        let attended = self.attention(self.norm1.forward(tokens.clone()));
        let tokens = tokens + attended * self.ls1.val().unsqueeze::<3>();
        let hidden = gelu(self.fc1.forward(self.norm2.forward(tokens.clone()))); // [I, N, mlp]
        tokens + self.fc2.forward(hidden) * self.ls2.val().unsqueeze::<3>()
    }

    /// Multi-head self-attention with scale `1/sqrt(head_dim)`.
    ///
    /// # Shapes
    ///
    /// - tokens: `[I, N, dim]`
    /// - output: `[I, N, dim]`
    fn attention(&self, tokens: Tensor<3>) -> Tensor<3> {
        let [batch, count, dim] = tokens.dims();
        let qkv = self
            .qkv
            .forward(tokens) // [I, N, 3·dim]
            .reshape([batch, count, 3, self.heads, dim / self.heads])
            .permute([2, 0, 3, 1, 4]); // [3, I, heads, N, head_dim]
        let [query, key, value] =
            [0, 1, 2].map(|part| qkv.clone().narrow(0, part, 1).squeeze_dim::<4>(0));
        let options = AttentionModuleOptions::default(); // scale 1/sqrt(head_dim)
        let attended = attention(query, key, value, None, None, options); // [I, heads, N, head_dim]
        self.proj
            .forward(attended.swap_dims(1, 2).reshape([batch, count, dim]))
    }
}

/// ImageNet normalization of RGB images, moved to channels-first: `(x / 255 − mean) / std`
/// with mean (0.485, 0.456, 0.406) and std (0.229, 0.224, 0.225).
///
/// # Shapes
///
/// - images: `[I, H, W, 3]`, RGB values in 0..=255
/// - output: `[I, 3, H, W]`
///
/// # Panics
///
/// Panics if the last axis is not 3.
pub fn imagenet_normalize(images: Tensor<4>) -> Tensor<4> {
    let [.., channels] = images.dims();
    assert_eq!(
        channels, 3,
        "imagenet_normalize: images must be [I, H, W, 3]"
    );
    let device = images.device();
    let mean = Tensor::<1>::from_floats(IMAGENET_MEAN, &device).reshape([1, 3, 1, 1]);
    let std = Tensor::<1>::from_floats(IMAGENET_STD, &device).reshape([1, 3, 1, 1]);
    (images.permute([0, 3, 1, 2]).div_scalar(255.0) - mean) / std
}

// ---------------------------------------------------------------------------------------------
// Position-embedding resize.

/// The `[output, input]` matrix that resizes a length-`input` signal to length `output` as
/// PyTorch's `interpolate(size=…, mode="bicubic", align_corners=False)` does without
/// antialiasing — the call in Hugging Face's `Dinov2Embeddings.interpolate_pos_encoding`
/// (transformers 5; see `trainer/reference/make_vit_fixture.py`).
fn resize_matrix(input: usize, output: usize, device: &Device) -> Tensor<2> {
    Tensor::from_data(
        TensorData::new(bicubic_weights(input, output), [output, input]),
        device,
    )
}

/// Row-major `[output, input]` weights of [`resize_matrix`], in f32 like PyTorch's CPU kernel
/// for f32 tensors. Output sample `o` sits at source position `s = (o + ½)·input/output − ½`
/// (not clamped at 0) and takes the inputs `⌊s⌋ − 1 ..= ⌊s⌋ + 2`, clamped to the borders (edge
/// replication), weighted by Keys' cubic convolution kernel with a = −0.75.
fn bicubic_weights(input: usize, output: usize) -> Vec<f32> {
    const A: f32 = -0.75;
    // The kernel for distances |x| ≤ 1 and 1 < |x| < 2.
    let near = |x: f32| ((A + 2.0) * x - (A + 3.0)) * x * x + 1.0;
    let far = |x: f32| ((A * x - 5.0 * A) * x + 8.0 * A) * x - 4.0 * A;

    let scale = input as f32 / output as f32;
    let last = input as i64 - 1;
    let mut weights = vec![0.0; output * input];
    for (o, row) in weights.chunks_exact_mut(input).enumerate() {
        let source = scale * (o as f32 + 0.5) - 0.5;
        // PyTorch's guard: the base tap stays inside and the fraction in [0, 1].
        let base = (source.floor() as i64).min(last);
        let t = (source - base as f32).clamp(0.0, 1.0);
        let taps = [far(1.0 + t), near(t), near(1.0 - t), far(2.0 - t)];
        for (offset, weight) in (-1..=2).zip(taps) {
            row[(base + offset).clamp(0, last) as usize] += weight;
        }
    }
    weights
}

// ---------------------------------------------------------------------------------------------
// Weights.

/// A weight of the network, named independently of any checkpoint layout.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
enum WeightKey {
    ClsToken,
    PosEmbed,
    PatchWeight,
    PatchBias,
    Block(usize, BlockWeight),
    NormWeight,
    NormBias,
}

/// A weight of one transformer block.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
enum BlockWeight {
    Norm1Weight,
    Norm1Bias,
    QkvWeight,
    QkvBias,
    ProjWeight,
    ProjBias,
    Ls1,
    Norm2Weight,
    Norm2Bias,
    Fc1Weight,
    Fc1Bias,
    Fc2Weight,
    Fc2Bias,
    Ls2,
}

/// Where [`DinoVit::build`] gets its weights: f32 values in PyTorch's layout (`[1, 1, dim]`
/// class token, `[1, 1 + N, dim]` position embeddings, `[dim, 3, p, p]` patch kernel,
/// `[out, in]` linear weights, the fused `qkv` as q, k, v stacked along `out`).
trait WeightSource {
    /// The values of `weight`, which has `shape`.
    fn take(&mut self, weight: WeightKey, shape: &[usize]) -> anyhow::Result<Vec<f32>>;
}

/// A learnable tensor holding `values` with `shape`.
fn tensor_param<const D: usize>(
    values: Vec<f32>,
    shape: [usize; D],
    device: &Device,
) -> Param<Tensor<D>> {
    Param::from_data(TensorData::new(values, shape), device)
}

/// A linear layer from a PyTorch `[out, in]` weight (burn stores `[in, out]`).
fn linear(
    weight: Vec<f32>,
    bias: Vec<f32>,
    [outputs, inputs]: [usize; 2],
    device: &Device,
) -> Linear {
    let mut transposed = vec![0.0; weight.len()];
    for (o, row) in weight.chunks_exact(inputs).enumerate() {
        for (i, &w) in row.iter().enumerate() {
            transposed[i * outputs + o] = w;
        }
    }
    Linear {
        weight: tensor_param(transposed, [inputs, outputs], device),
        bias: Some(tensor_param(bias, [outputs], device)),
    }
}

/// A LayerNorm with the given scale and shift.
fn layer_norm(weight: Vec<f32>, bias: Vec<f32>, eps: f64, device: &Device) -> LayerNorm {
    let dim = weight.len();
    let mut norm = LayerNormConfig::new(dim).with_epsilon(eps).init(device);
    norm.gamma = tensor_param(weight, [dim], device);
    norm.beta = Some(tensor_param(bias, [dim], device));
    norm
}

/// Seeded random weights (see [`DinoVit::random`]).
#[derive(Debug)]
struct RandomInit {
    rng: crate::init::InitRng,
}

impl RandomInit {
    /// Standard deviation of the random matrices and embeddings.
    const STD: f32 = 0.02;

    fn new(seed: u64) -> Self {
        Self {
            rng: crate::init::InitRng::new(seed, "vit"),
        }
    }

    /// Standard normal truncated to [−2, 2] (redrawn outside).
    fn truncated_normal(&mut self) -> f32 {
        loop {
            let z = self.rng.normal();
            if z.abs() <= 2.0 {
                return z as f32;
            }
        }
    }
}

impl WeightSource for RandomInit {
    fn take(&mut self, weight: WeightKey, shape: &[usize]) -> anyhow::Result<Vec<f32>> {
        use BlockWeight as B;
        let count = shape.iter().product();
        let constant = match weight {
            WeightKey::NormWeight
            | WeightKey::Block(_, B::Norm1Weight | B::Norm2Weight | B::Ls1 | B::Ls2) => Some(1.0),
            WeightKey::PatchBias
            | WeightKey::NormBias
            | WeightKey::Block(
                _,
                B::Norm1Bias | B::Norm2Bias | B::QkvBias | B::ProjBias | B::Fc1Bias | B::Fc2Bias,
            ) => Some(0.0),
            _ => None,
        };
        Ok(match constant {
            Some(value) => vec![value; count],
            None => (0..count)
                .map(|_| Self::STD * self.truncated_normal())
                .collect(),
        })
    }
}

// ---------------------------------------------------------------------------------------------
// Checkpoints.

/// The two DINOv2 naming schemes.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
enum Naming {
    /// Hugging Face transformers' `Dinov2Model`.
    HuggingFace,
    /// facebookresearch/dinov2's torch-hub `DinoVisionTransformer`.
    TorchHub,
}

impl Naming {
    /// The class token's name, by which the scheme and the prefix are recognized.
    fn cls_token(self) -> &'static str {
        match self {
            Self::HuggingFace => "embeddings.cls_token",
            Self::TorchHub => "cls_token",
        }
    }

    /// The names (without prefix) holding `weight`: one, or for Hugging Face's separate
    /// query/key/value projections three, stacked along the first axis.
    fn names(self, weight: WeightKey) -> Vec<String> {
        use BlockWeight as B;
        let hf = self == Self::HuggingFace;
        let pick = |hugging_face: &str, torch_hub: &str| {
            if hf { hugging_face } else { torch_hub }.to_owned()
        };
        let name = match weight {
            WeightKey::ClsToken => self.cls_token().to_owned(),
            WeightKey::PosEmbed => pick("embeddings.position_embeddings", "pos_embed"),
            WeightKey::PatchWeight => pick(
                "embeddings.patch_embeddings.projection.weight",
                "patch_embed.proj.weight",
            ),
            WeightKey::PatchBias => pick(
                "embeddings.patch_embeddings.projection.bias",
                "patch_embed.proj.bias",
            ),
            WeightKey::NormWeight => pick("layernorm.weight", "norm.weight"),
            WeightKey::NormBias => pick("layernorm.bias", "norm.bias"),
            WeightKey::Block(index, weight) => {
                let block = self.block(index);
                let local = match weight {
                    B::QkvWeight | B::QkvBias if hf => {
                        let suffix = if weight == B::QkvWeight {
                            "weight"
                        } else {
                            "bias"
                        };
                        return ["query", "key", "value"]
                            .map(|part| format!("{block}attention.attention.{part}.{suffix}"))
                            .into();
                    }
                    B::Norm1Weight => "norm1.weight",
                    B::Norm1Bias => "norm1.bias",
                    B::QkvWeight => "attn.qkv.weight",
                    B::QkvBias => "attn.qkv.bias",
                    B::ProjWeight if hf => "attention.output.dense.weight",
                    B::ProjWeight => "attn.proj.weight",
                    B::ProjBias if hf => "attention.output.dense.bias",
                    B::ProjBias => "attn.proj.bias",
                    B::Ls1 if hf => "layer_scale1.lambda1",
                    B::Ls1 => "ls1.gamma",
                    B::Norm2Weight => "norm2.weight",
                    B::Norm2Bias => "norm2.bias",
                    B::Fc1Weight => "mlp.fc1.weight",
                    B::Fc1Bias => "mlp.fc1.bias",
                    B::Fc2Weight => "mlp.fc2.weight",
                    B::Fc2Bias => "mlp.fc2.bias",
                    B::Ls2 if hf => "layer_scale2.lambda1",
                    B::Ls2 => "ls2.gamma",
                };
                format!("{block}{local}")
            }
        };
        vec![name]
    }

    /// The prefix of block `index`'s names.
    fn block(self, index: usize) -> String {
        match self {
            Self::HuggingFace => format!("encoder.layer.{index}."),
            Self::TorchHub => format!("blocks.{index}."),
        }
    }

    /// Names whose presence marks an architecture this module does not implement, with why.
    fn unsupported(self) -> [(String, &'static str); 2] {
        let registers = "register tokens (a `*_reg` checkpoint) are not supported";
        let swiglu = "the SwiGLU MLP (ViT-g) is not supported";
        match self {
            Self::HuggingFace => [
                ("embeddings.register_tokens".to_owned(), registers),
                (format!("{}mlp.weights_in.weight", self.block(0)), swiglu),
            ],
            Self::TorchHub => [
                ("register_tokens".to_owned(), registers),
                (format!("{}mlp.w12.weight", self.block(0)), swiglu),
            ],
        }
    }
}

/// A parsed safetensors checkpoint with its naming scheme and prefix.
struct Checkpoint<'a> {
    path: &'a Path,
    file: &'a SafeTensors<'a>,
    naming: Naming,
    /// Prefix of every name, such as `backbone.` (often empty).
    prefix: String,
}

impl<'a> Checkpoint<'a> {
    /// Recognizes the naming scheme and prefix from the class token's name.
    fn new(path: &'a Path, file: &'a SafeTensors<'a>) -> anyhow::Result<Self> {
        let mut found: Vec<(Naming, String)> = file
            .names()
            .into_iter()
            .filter_map(|name| {
                let naming = if name.ends_with(Naming::HuggingFace.cls_token()) {
                    Naming::HuggingFace
                } else {
                    Naming::TorchHub
                };
                let prefix = name.strip_suffix(naming.cls_token())?;
                (prefix.is_empty() || prefix.ends_with('.')).then(|| (naming, prefix.to_owned()))
            })
            .collect();
        let (naming, prefix) = match found.len() {
            1 => found.remove(0),
            0 => bail!(
                "{}: no DINOv2 class token (`cls_token` or `embeddings.cls_token`, possibly \
                 prefixed) among its {} tensors",
                path.display(),
                file.len()
            ),
            _ => bail!(
                "{}: several class tokens ({}); expected one DINOv2 backbone",
                path.display(),
                found
                    .iter()
                    .map(|(naming, prefix)| format!("`{prefix}{}`", naming.cls_token()))
                    .collect::<Vec<_>>()
                    .join(", ")
            ),
        };
        let checkpoint = Self {
            path,
            file,
            naming,
            prefix,
        };
        for (name, why) in naming.unsupported() {
            if checkpoint.shape(&name).is_some() {
                bail!(
                    "{}: tensor `{}{name}`: {why}",
                    path.display(),
                    checkpoint.prefix
                );
            }
        }
        Ok(checkpoint)
    }

    /// The shape of tensor `name` (without prefix), if present.
    fn shape(&self, name: &str) -> Option<Vec<usize>> {
        let view = self.file.tensor(&format!("{}{name}", self.prefix)).ok()?;
        Some(view.shape().to_vec())
    }

    /// The shape of the tensor holding `weight`, which must exist with `rank` axes.
    fn required_shape(&self, weight: WeightKey, rank: usize) -> anyhow::Result<Vec<usize>> {
        let name = &self.naming.names(weight)[0];
        let shape = self.shape(name).with_context(|| self.missing(name))?;
        ensure!(
            shape.len() == rank,
            "{}: tensor `{}{name}` has shape {shape:?}, expected {rank} axes",
            self.path.display(),
            self.prefix
        );
        Ok(shape)
    }

    fn missing(&self, name: &str) -> String {
        format!(
            "{}: missing tensor `{}{name}`",
            self.path.display(),
            self.prefix
        )
    }

    /// The network's shape, read off the tensors' shapes (see [`DinoVit::load_safetensors`]).
    fn infer_config(&self) -> anyhow::Result<VitConfig> {
        let path = self.path.display();
        let cls = self.required_shape(WeightKey::ClsToken, 3)?;
        let dim = cls[2];
        let patch = self.required_shape(WeightKey::PatchWeight, 4)?[2];
        let positions = self.required_shape(WeightKey::PosEmbed, 3)?[1];
        let side = positions.saturating_sub(1).isqrt();
        ensure!(
            side > 0 && side * side == positions - 1,
            "{path}: tensor `{}{}` holds {positions} positions, not a class token plus a square \
             grid",
            self.prefix,
            self.naming.names(WeightKey::PosEmbed)[0]
        );
        let depth = (0..)
            .take_while(|&index| {
                let name = &self
                    .naming
                    .names(WeightKey::Block(index, BlockWeight::Norm1Weight))[0];
                self.shape(name).is_some()
            })
            .count();
        ensure!(
            depth > 0,
            "{}",
            self.missing(
                &self
                    .naming
                    .names(WeightKey::Block(0, BlockWeight::Norm1Weight))[0]
            )
        );
        let mlp_hidden = self.required_shape(WeightKey::Block(0, BlockWeight::Fc1Weight), 2)?[0];
        let heads = VitConfig::heads_for_dim(dim).with_context(|| {
            format!(
                "{path}: width {dim} (tensor `{}{}`) is no preset's and not a multiple of 64; \
                 the head count is unknown",
                self.prefix,
                self.naming.cls_token()
            )
        })?;
        let config = VitConfig {
            dim,
            depth,
            heads,
            mlp_hidden,
            patch,
            pos_grid: [side, side],
            eps: 1e-6,
        };
        config
            .validate()
            .with_context(|| format!("{path}: inferred an invalid shape"))?;
        Ok(config)
    }

    /// Tensor `name` (without prefix) as f32 values, checked to have `shape`.
    fn read(&self, name: &str, shape: &[usize]) -> anyhow::Result<Vec<f32>> {
        let full = format!("{}{name}", self.prefix);
        let path = self.path.display();
        let view = self
            .file
            .tensor(&full)
            .ok()
            .with_context(|| self.missing(name))?;
        ensure!(
            view.shape() == shape,
            "{path}: tensor `{full}` has shape {:?}, expected {shape:?}",
            view.shape()
        );
        let bytes = view.data();
        Ok(match view.dtype() {
            Dtype::F32 => bytes
                .chunks_exact(4)
                .map(|b| f32::from_le_bytes([b[0], b[1], b[2], b[3]]))
                .collect(),
            Dtype::F16 => bytes
                .chunks_exact(2)
                .map(|b| f16::from_le_bytes([b[0], b[1]]).to_f32())
                .collect(),
            Dtype::BF16 => bytes
                .chunks_exact(2)
                .map(|b| bf16::from_le_bytes([b[0], b[1]]).to_f32())
                .collect(),
            other => {
                bail!("{path}: tensor `{full}` has dtype {other:?}; expected F32, F16 or BF16")
            }
        })
    }
}

impl WeightSource for Checkpoint<'_> {
    fn take(&mut self, weight: WeightKey, shape: &[usize]) -> anyhow::Result<Vec<f32>> {
        let names = self.naming.names(weight);
        let mut part_shape = shape.to_vec();
        part_shape[0] /= names.len();
        let mut values = Vec::with_capacity(shape.iter().product());
        for name in &names {
            values.extend(self.read(name, &part_shape)?);
        }
        Ok(values)
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    /// The position embeddings equal the ones transformers added (`pos_embed` in
    /// `tests/fixtures/vit.json`), on the trained grid and on a resized one.
    #[test]
    fn position_embeddings_match_transformers() {
        let fixtures = Path::new(env!("CARGO_MANIFEST_DIR")).join("tests/fixtures");
        let json = std::fs::read_to_string(fixtures.join("vit.json")).expect("reading vit.json");
        let fixture: serde_json::Value = serde_json::from_str(&json).expect("parsing vit.json");
        let vit =
            DinoVit::load_safetensors(&fixtures.join("tiny_dinov2.safetensors"), &Device::flex())
                .expect("loading the fixture checkpoint");
        let cases = fixture["cases"].as_array().expect("a list of cases");
        for case in cases {
            let grid: [usize; 2] =
                serde_json::from_value(case["grid"].clone()).expect("a [rows, cols] grid");
            let expected: Vec<f32> =
                serde_json::from_value(case["pos_embed"].clone()).expect("a list of floats");
            let actual = vit
                .position_embeddings(grid)
                .into_data()
                .try_into_vec::<f32>()
                .expect("f32 values");
            assert_eq!(actual.len(), expected.len(), "grid {grid:?}");
            let diff = actual
                .iter()
                .zip(&expected)
                .map(|(a, e)| (a - e).abs())
                .fold(0.0, f32::max);
            assert!(
                diff < 1e-6,
                "grid {grid:?}: position embeddings differ by {diff}"
            );
        }
    }

    /// Every output is an affine combination of the inputs (a constant stays constant), and
    /// resizing to the same length is the identity.
    #[test]
    fn bicubic_weights_are_affine_and_identity_at_equal_size() {
        for (input, output) in [
            (4, 3),
            (4, 6),
            (4, 16),
            (37, 16),
            (37, 32),
            (37, 80),
            (1, 3),
        ] {
            let weights = bicubic_weights(input, output);
            for (o, row) in weights.chunks_exact(input).enumerate() {
                let sum: f32 = row.iter().sum();
                assert!(
                    (sum - 1.0).abs() < 1e-6,
                    "{input} → {output}, row {o}: sum {sum}"
                );
            }
        }
        let weights = bicubic_weights(5, 5);
        for (o, row) in weights.chunks_exact(5).enumerate() {
            for (i, &w) in row.iter().enumerate() {
                assert_eq!(w, f32::from(u8::from(i == o)), "5 → 5 at ({o}, {i})");
            }
        }
    }
}
