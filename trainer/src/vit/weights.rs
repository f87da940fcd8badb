//! Where the ViT's weights come from ([`WeightSource`]: a checkpoint or the seeded random
//! init) and how they become layers: [`DinoVit::build`] assembles the network from them.

use super::blocks::Block;
use super::config::VitConfig;
use super::error::WeightsError;
use super::network::DinoVit;
use burn::module::{Module, Param};
use burn::nn::{LayerNorm, LayerNormConfig, Linear};
use burn::tensor::{Device, Tensor, TensorData};

impl DinoVit {
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

    /// Assembles the network from `source`, which hands out each weight in PyTorch's layout.
    pub(super) fn build(
        config: &VitConfig,
        device: &Device,
        source: &mut impl WeightSource,
    ) -> Result<Self, WeightsError> {
        let VitConfig {
            dim,
            depth,
            patch,
            pos_grid: [rows, cols],
            eps,
            ..
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

        let blocks = (0..depth)
            .map(|index| {
                block(config, device, &mut |weight, shape| {
                    take(WeightKey::Block(index, weight), shape)
                })
            })
            .collect::<Result<Vec<_>, _>>()?;
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

/// One transformer block from `take`, which hands out the block's weights.
fn block(
    config: &VitConfig,
    device: &Device,
    take: &mut impl FnMut(BlockWeight, &[usize]) -> Result<Vec<f32>, WeightsError>,
) -> Result<Block, WeightsError> {
    let VitConfig {
        dim,
        heads,
        mlp_hidden,
        eps,
        ..
    } = *config;
    let mut norm = |weight, bias| -> Result<LayerNorm, WeightsError> {
        Ok(layer_norm(
            take(weight, &[dim])?,
            take(bias, &[dim])?,
            eps,
            device,
        ))
    };
    let norm1 = norm(BlockWeight::Norm1Weight, BlockWeight::Norm1Bias)?;
    let norm2 = norm(BlockWeight::Norm2Weight, BlockWeight::Norm2Bias)?;
    Ok(Block {
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
    })
}

/// A weight of the network, named independently of any checkpoint layout.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub(super) enum WeightKey {
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
pub(super) enum BlockWeight {
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
pub(super) trait WeightSource {
    /// The values of `weight`, which has `shape`.
    fn take(&mut self, weight: WeightKey, shape: &[usize]) -> Result<Vec<f32>, WeightsError>;
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
pub(super) struct RandomInit {
    rng: crate::init::InitRng,
}

impl RandomInit {
    /// Standard deviation of the random matrices and embeddings.
    const STD: f32 = 0.02;

    pub(super) fn new(seed: u64) -> Self {
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
    fn take(&mut self, weight: WeightKey, shape: &[usize]) -> Result<Vec<f32>, WeightsError> {
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
