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
//! By concern: `config` (the sizes), `blocks` (attention, MLP, LayerScale), `pos_embed`
//! (the bicubic resize of the position embeddings), `weights` (where weights come from and
//! how the network is assembled) and `load` (safetensors names and loading, [`WeightsError`]).
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

mod blocks;
mod config;
mod error;
mod load;
mod pos_embed;
mod weights;

pub use config::{UnknownPreset, VitConfig, VitPreset};
pub use error::WeightsError;

use blocks::Block;
use burn::module::{Module, Param};
use burn::nn::{LayerNorm, Linear};
use burn::tensor::{Device, Tensor};
use weights::RandomInit;

/// Per-channel (RGB) mean of ImageNet, on the 0..1 scale.
const IMAGENET_MEAN: [f32; 3] = [0.485, 0.456, 0.406];
/// Per-channel (RGB) standard deviation of ImageNet, on the 0..1 scale.
const IMAGENET_STD: [f32; 3] = [0.229, 0.224, 0.225];

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
