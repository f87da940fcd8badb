//! One pre-norm transformer block of the ViT: multi-head self-attention and the GELU MLP,
//! each scaled by its LayerScale and added to the tokens.

use burn::module::{Module, Param};
use burn::nn::{LayerNorm, Linear};
use burn::tensor::Tensor;
use burn::tensor::activation::gelu;
use burn::tensor::module::attention;
use burn::tensor::ops::AttentionModuleOptions;

/// One pre-norm transformer block with LayerScale.
#[derive(Module, Debug)]
pub(super) struct Block {
    pub(super) norm1: LayerNorm,
    /// Fused query/key/value projection `[dim, 3·dim]`; outputs ordered (q|k|v, head, channel).
    pub(super) qkv: Linear,
    /// Attention output projection `[dim, dim]`.
    pub(super) proj: Linear,
    /// LayerScale of the attention branch `[dim]`.
    pub(super) ls1: Param<Tensor<1>>,
    pub(super) norm2: LayerNorm,
    /// MLP input layer `[dim, mlp_hidden]`.
    pub(super) fc1: Linear,
    /// MLP output layer `[mlp_hidden, dim]`.
    pub(super) fc2: Linear,
    /// LayerScale of the MLP branch `[dim]`.
    pub(super) ls2: Param<Tensor<1>>,
    #[module(skip)]
    pub(super) heads: usize,
}

impl Block {
    /// # Shapes
    ///
    /// - tokens: `[I, N, dim]`
    /// - output: `[I, N, dim]`
    pub(super) fn forward(&self, tokens: Tensor<3>) -> Tensor<3> {
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
