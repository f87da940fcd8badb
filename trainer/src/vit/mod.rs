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
//! By concern: `network` (the layers and the forward pass), `config` (the sizes), `blocks`
//! (attention, MLP, LayerScale), `pos_embed` (the bicubic resize of the position
//! embeddings), `weights` (where weights come from, the seeded random init included, and
//! how the network is assembled), `load` (safetensors names and loading), `error`
//! ([`WeightsError`]) and `normalize` (camera images as the network takes them).
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
mod network;
mod normalize;
mod pos_embed;
mod weights;

pub use config::{VitConfig, VitPreset};
pub use error::WeightsError;
pub use network::DinoVit;
pub use normalize::imagenet_normalize;
