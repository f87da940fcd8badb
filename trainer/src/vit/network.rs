//! [`DinoVit`]: the network's layers and its forward pass.

use super::blocks::Block;
use super::config::VitConfig;
use burn::module::{Module, Param};
use burn::nn::{LayerNorm, Linear};
use burn::tensor::Tensor;

/// A DINOv2-architecture ViT (no register tokens, LayerScale, exact-erf GELU MLP), used frozen:
/// its parameters are created without gradients (`unfreeze` it to fine-tune).
#[derive(Module, Debug)]
pub struct DinoVit {
    /// The patch-embedding convolution as a linear map of flattened `[3, p, p]` patches:
    /// weight `[3·p·p, dim]`.
    pub(super) patch_embed: Linear,
    /// Class token `[dim]`.
    pub(super) cls_token: Param<Tensor<1>>,
    /// Position embeddings for `config.pos_grid`, class token first: `[1 + rows·cols, dim]`.
    pub(super) pos_embed: Param<Tensor<2>>,
    /// The transformer blocks, input first.
    pub(super) blocks: Vec<Block>,
    /// Final LayerNorm.
    pub(super) norm: LayerNorm,
    /// The shape this network was built with.
    #[module(skip)]
    pub(super) config: VitConfig,
}

impl DinoVit {
    /// The shape this network was built with.
    pub fn config(&self) -> &VitConfig {
        &self.config
    }

    /// The patch tokens of `images`, after the final LayerNorm, as a feature map.
    ///
    /// # Shapes
    ///
    /// - images: `[I, 3, H, W]`, ImageNet-normalized (see
    ///   [`imagenet_normalize`](super::imagenet_normalize))
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
    /// - images: `[I, 3, H, W]`, ImageNet-normalized (see
    ///   [`imagenet_normalize`](super::imagenet_normalize))
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
