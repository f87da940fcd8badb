//! The 3D network: a sparse-convolution residual UNet (MinkUNet) driven by the kernel
//! maps that arrive in the batch.
//!
//! A sparse convolution is computed offset by offset: gather the input rows of the
//! offset's (input, output) pairs, multiply by the offset's weight, scatter-add into the
//! output rows. The pipeline precomputes the pairs (`l{l}_nbr`: the 3×3×3 maps at level
//! `l`, grouped by offset; `l{l}_down`: the stride-2 maps from level `l` to `l + 1`,
//! grouped by the child's position in its parent cell), so the trainer does no hashing.
//! The transposed (up) convolution uses the down map backwards: every child row receives
//! its parent's row times the weight of its position.
//!
//! The architecture is MinkowskiEngine's MinkUNet as used by SLidR and SuperFlow: a stem
//! convolution, four encoder stages (stride-2 convolution + BN + ReLU, then residual
//! basic blocks), four decoder stages (transposed convolution + BN + ReLU, concatenation
//! with the encoder features of the same level, basic blocks), and a linear head to 64
//! channels, L2-normalized. Our maps are 3×3×3, so the stem is a 3×3×3 convolution
//! (MinkowskiEngine's example uses 5×5×5).

use crate::init::normal_param;
use crate::rows::RowOps;
use burn::module::{Module, Param};
use burn::nn::{BatchNorm, BatchNormConfig, Linear};
use burn::tensor::activation::relu;
use burn::tensor::{Device, Int, Tensor, TensorData};
use serde::{Deserialize, Serialize};

/// Number of offsets of a 3×3×3 kernel.
pub const KERNEL_3: usize = 27;
/// Number of child positions of a stride-2 cell.
pub const KERNEL_2: usize = 8;

/// The kernel maps of one level, as device index tensors (built once per batch, used by
/// every convolution at that level).
#[derive(Debug, Clone)]
pub struct LevelMaps {
    /// Voxel rows at this level.
    pub rows: usize,
    /// 3×3×3 map: the pairs of every offset (input rows, output rows).
    pub nbr: KernelPairs,
    /// Stride-2 map to the next level (absent at the coarsest level): child rows here,
    /// parent rows at `l + 1`, and where each child position's pairs start (9).
    pub down: Option<DownMap>,
}

/// The stride-2 map from one level to the next: (child row here, parent row at the next
/// level) pairs, grouped by the child's position in its parent cell.
pub type DownMap = KernelPairs;

/// A kernel map on the device: for every offset, the rows it gathers from and the rows
/// it adds into (empty offsets are `None`), plus all target rows in offset order for the
/// single scatter-add. Gathering per offset (rather than gathering all pairs and slicing)
/// keeps the backward pass at one scatter per offset into the input's size.
#[derive(Debug, Clone)]
pub struct KernelPairs {
    /// First column of the pairs, per offset.
    pub first: Vec<Option<Tensor<1, Int>>>,
    /// Second column of the pairs, per offset.
    pub second: Vec<Option<Tensor<1, Int>>>,
    /// Second column of all pairs, offset by offset.
    pub second_all: Tensor<1, Int>,
    /// First column of all pairs, offset by offset.
    pub first_all: Tensor<1, Int>,
    /// How the device runs the gathers and scatter-adds ([`RowOps::of`]).
    pub ops: RowOps,
}

impl KernelPairs {
    /// From interleaved pairs and the start of each offset's pairs (one transfer; the
    /// per-offset index tensors are views cut on the device).
    pub fn new(pairs: &[u32], starts: &[u32], device: &Device) -> Self {
        let (first_all, second_all) = split_pairs(pairs, device);
        let mut first = Vec::with_capacity(starts.len().saturating_sub(1));
        let mut second = Vec::with_capacity(first.capacity());
        for w in starts.windows(2) {
            let (s, e) = (w[0] as usize, w[1] as usize);
            if e > s {
                first.push(Some(first_all.clone().narrow(0, s, e - s)));
                second.push(Some(second_all.clone().narrow(0, s, e - s)));
            } else {
                first.push(None);
                second.push(None);
            }
        }
        Self {
            first,
            second,
            second_all,
            first_all,
            ops: RowOps::of(device),
        }
    }
}

impl LevelMaps {
    /// Builds the device tensors of a level from host arrays: `nbr` as (input, output)
    /// pairs, `down` as (child, parent) pairs, with their start tables.
    pub fn from_host(
        rows: usize,
        nbr: &[u32],
        nbr_starts: &[u32],
        down: Option<(&[u32], &[u32])>,
        device: &Device,
    ) -> Self {
        Self {
            rows,
            nbr: KernelPairs::new(nbr, nbr_starts, device),
            down: down.map(|(pairs, starts)| KernelPairs::new(pairs, starts, device)),
        }
    }
}

/// Interleaved (a, b) pairs → two index tensors (one transfer, split on the device).
fn split_pairs(pairs: &[u32], device: &Device) -> (Tensor<1, Int>, Tensor<1, Int>) {
    let n = pairs.len() / 2;
    let values: Vec<i64> = pairs[..2 * n].iter().map(|&v| i64::from(v)).collect();
    let both = Tensor::<2, Int>::from_data(TensorData::new(values, [n, 2]), device);
    (
        both.clone().narrow(1, 0, 1).reshape([n]),
        both.narrow(1, 1, 1).reshape([n]),
    )
}

/// An index tensor from host values.
pub fn index_tensor(values: Vec<i64>, device: &Device) -> Tensor<1, Int> {
    let n = values.len();
    Tensor::from_data(TensorData::new(values, [n]), device)
}

/// A sparse convolution's weights: one `[c_in, c_out]` matrix per kernel offset.
#[derive(Module, Debug)]
pub struct SparseConv {
    /// `[offsets, c_in, c_out]`.
    pub weight: Param<Tensor<3>>,
}

impl SparseConv {
    /// Kaiming-normal weights (fan-out, ReLU gain), as MinkowskiEngine initializes them.
    pub fn new(
        offsets: usize,
        c_in: usize,
        c_out: usize,
        seed: u64,
        name: &str,
        device: &Device,
    ) -> Self {
        let std = (2.0 / (offsets * c_out) as f64).sqrt();
        Self {
            weight: normal_param([offsets, c_in, c_out], std, seed, name, device),
        }
    }

    /// Offsets, input channels, output channels.
    pub fn dims(&self) -> [usize; 3] {
        self.weight.val().dims()
    }

    /// The generic gather → matmul → scatter-add: for every offset `k`, the rows
    /// `gather[k]` of `x` times weight `k`; all products added into rows `scatter_all`
    /// (the same pairs, offset by offset) of an `out_rows` output.
    fn apply(
        &self,
        x: Tensor<2>,
        gather: &[Option<Tensor<1, Int>>],
        scatter_all: &Tensor<1, Int>,
        out_rows: usize,
        ops: RowOps,
    ) -> Tensor<2> {
        let [offsets, c_in, c_out] = self.dims();
        assert_eq!(gather.len(), offsets, "kernel map has one entry per offset");
        let device = x.device();
        let weight = self.weight.val();
        let parts: Vec<Tensor<2>> = gather
            .iter()
            .enumerate()
            .filter_map(|(k, rows)| {
                let rows = rows.as_ref()?;
                let w = weight.clone().narrow(0, k, 1).reshape([c_in, c_out]);
                Some(ops.gather(x.clone(), rows).matmul(w))
            })
            .collect();
        if parts.is_empty() {
            return Tensor::zeros([out_rows, c_out], &device);
        }
        ops.scatter_add(
            Tensor::zeros([out_rows, c_out], &device),
            scatter_all,
            Tensor::cat(parts, 0),
        )
    }

    /// Submanifold 3×3×3 convolution at one level (output rows = input rows).
    ///
    /// # Shapes
    ///
    /// - x: `[voxels, c_in]`, one row per voxel of `maps`' level (`maps.rows`)
    /// - output: `[voxels, c_out]`, the same voxels
    pub fn forward(&self, x: Tensor<2>, maps: &LevelMaps) -> Tensor<2> {
        self.apply(
            x,
            &maps.nbr.first,
            &maps.nbr.second_all,
            maps.rows,
            maps.nbr.ops,
        )
    }

    /// Stride-2 convolution from `maps`' level to the next (`next_rows` rows).
    ///
    /// # Shapes
    ///
    /// - x: `[voxels, c_in]`, one row per voxel of `maps`' level (`maps.rows`)
    /// - output: `[next_voxels, c_out]`, one row per voxel of the next, coarser level
    ///   (`next_rows`)
    ///
    /// # Panics
    ///
    /// Panics if `maps` is the coarsest level (it has no down map).
    pub fn forward_down(&self, x: Tensor<2>, maps: &LevelMaps, next_rows: usize) -> Tensor<2> {
        let down = maps
            .down
            .as_ref()
            .expect("a level below the coarsest has a down map");
        self.apply(x, &down.first, &down.second_all, next_rows, down.ops)
    }

    /// Transposed stride-2 convolution from the next level back to `maps`' level.
    ///
    /// # Shapes
    ///
    /// - x_next: `[next_voxels, c_in]`, one row per voxel of the next, coarser level
    ///   (that level's `rows`)
    /// - output: `[voxels, c_out]`, one row per voxel of `maps`' level (`maps.rows`)
    ///
    /// # Panics
    ///
    /// Panics if `maps` is the coarsest level (it has no down map).
    pub fn forward_up(&self, x_next: Tensor<2>, maps: &LevelMaps) -> Tensor<2> {
        let down = maps
            .down
            .as_ref()
            .expect("a level below the coarsest has a down map");
        self.apply(x_next, &down.second, &down.first_all, maps.rows, down.ops)
    }
}

/// Batch norm over voxel rows (`[rows, channels]`), training statistics on an autodiff
/// device, running statistics otherwise; momentum 0.1, ε 1e-5 (PyTorch's BatchNorm1d).
fn batch_norm(channels: usize, device: &Device) -> BatchNorm {
    BatchNormConfig::new(channels).init(device)
}

/// A linear layer without bias, Kaiming-normal.
fn projection(c_in: usize, c_out: usize, seed: u64, name: &str, device: &Device) -> Linear {
    Linear {
        weight: normal_param(
            [c_in, c_out],
            (2.0 / c_out as f64).sqrt(),
            seed,
            name,
            device,
        ),
        bias: None,
    }
}

/// The residual basic block: conv-BN-ReLU-conv-BN, plus the input (through a linear
/// projection + BN when the channels change), then ReLU.
#[derive(Module, Debug)]
pub struct BasicBlock {
    conv1: SparseConv,
    bn1: BatchNorm,
    conv2: SparseConv,
    bn2: BatchNorm,
    shortcut: Option<Shortcut>,
}

/// The projection of a block's input when its channels change.
#[derive(Module, Debug)]
pub struct Shortcut {
    linear: Linear,
    bn: BatchNorm,
}

impl BasicBlock {
    fn new(c_in: usize, c_out: usize, seed: u64, name: &str, device: &Device) -> Self {
        Self {
            conv1: SparseConv::new(
                KERNEL_3,
                c_in,
                c_out,
                seed,
                &format!("{name}.conv1"),
                device,
            ),
            bn1: batch_norm(c_out, device),
            conv2: SparseConv::new(
                KERNEL_3,
                c_out,
                c_out,
                seed,
                &format!("{name}.conv2"),
                device,
            ),
            bn2: batch_norm(c_out, device),
            shortcut: (c_in != c_out).then(|| Shortcut {
                linear: projection(c_in, c_out, seed, &format!("{name}.shortcut"), device),
                bn: batch_norm(c_out, device),
            }),
        }
    }

    fn forward(&self, x: Tensor<2>, maps: &LevelMaps) -> Tensor<2> {
        let ops = maps.nbr.ops;
        let out = relu(ops.batch_norm(&self.bn1, self.conv1.forward(x.clone(), maps)));
        let out = ops.batch_norm(&self.bn2, self.conv2.forward(out, maps));
        let identity = match &self.shortcut {
            Some(s) => ops.batch_norm(&s.bn, ops.linear(&s.linear, x)),
            None => x,
        };
        relu(out + identity)
    }
}

/// A convolution that changes level (stride 2 down, or transposed up), with BN + ReLU.
#[derive(Module, Debug)]
pub struct LevelChange {
    conv: SparseConv,
    bn: BatchNorm,
}

/// A stage: a level change followed by residual blocks.
#[derive(Module, Debug)]
pub struct Stage {
    change: LevelChange,
    blocks: Vec<BasicBlock>,
}

/// Shape of a UNet: stem width, eight stage widths and block counts (4 encoder stages,
/// then 4 decoder stages), input channels and the head's output dimension.
#[derive(Debug, Clone, PartialEq, Eq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct UNetConfig {
    /// Channels of the stem convolution.
    pub stem: usize,
    /// Channels of the 8 stages.
    pub planes: [usize; 8],
    /// Basic blocks of the 8 stages.
    pub blocks: [usize; 8],
    /// Input channels per voxel (x, y, z, intensity).
    pub in_channels: usize,
    /// Output dimension of the head.
    pub out_dim: usize,
}

/// The named UNet sizes; lowercase names in serde and on the command line
/// (`--unet minkunet34`, listed by `--help`).
#[derive(Debug, Clone, Copy, PartialEq, Eq, Serialize, Deserialize, clap::ValueEnum)]
#[serde(rename_all = "lowercase")]
#[value(rename_all = "lowercase")]
pub enum UNetPreset {
    /// MinkUNet-34 (the paper's 3D backbone).
    Minkunet34,
    /// MinkUNet-18.
    Minkunet18,
    /// A small UNet that trains at a useful speed on a 2-core CPU (tests, the demo).
    Tiny,
}

impl UNetConfig {
    /// The preset's shape, 4 input channels, a 64-d head.
    pub fn preset(preset: UNetPreset) -> Self {
        let mink_planes = [32, 64, 128, 256, 256, 128, 96, 96];
        let (stem, planes, blocks) = match preset {
            UNetPreset::Minkunet34 => (32, mink_planes, [2, 3, 4, 6, 2, 2, 2, 2]),
            UNetPreset::Minkunet18 => (32, mink_planes, [2; 8]),
            UNetPreset::Tiny => (16, [16, 32, 32, 32, 32, 32, 16, 16], [1; 8]),
        };
        Self {
            stem,
            planes,
            blocks,
            in_channels: 4,
            out_dim: 64,
        }
    }

    /// Levels of the kernel maps the network needs (4 down-samplings).
    pub const LEVELS: usize = 5;
}

/// The sparse residual UNet with its projection head.
#[derive(Module, Debug)]
pub struct SparseUNet {
    stem: SparseConv,
    stem_bn: BatchNorm,
    encoder: Vec<Stage>,
    decoder: Vec<Stage>,
    head: Linear,
}

impl SparseUNet {
    /// A freshly initialized network; the same `seed` gives the same weights.
    pub fn new(config: &UNetConfig, seed: u64, device: &Device) -> Self {
        let p = config.planes;
        let blocks = |stage: usize, c_in: usize, c_out: usize| -> Vec<BasicBlock> {
            (0..config.blocks[stage])
                .map(|i| {
                    let c = if i == 0 { c_in } else { c_out };
                    BasicBlock::new(c, c_out, seed, &format!("stage{stage}.block{i}"), device)
                })
                .collect()
        };
        let change = |stage: usize, c_in: usize, c_out: usize| LevelChange {
            conv: SparseConv::new(
                KERNEL_2,
                c_in,
                c_out,
                seed,
                &format!("stage{stage}.change"),
                device,
            ),
            bn: batch_norm(c_out, device),
        };
        // Encoder stage i: level i → i + 1, then blocks to planes[i].
        let mut encoder = Vec::with_capacity(4);
        let mut c = config.stem;
        for (i, &width) in p.iter().take(4).enumerate() {
            encoder.push(Stage {
                change: change(i, c, c),
                blocks: blocks(i, c, width),
            });
            c = width;
        }
        // Decoder stage i: level 4 − i → 3 − i, concatenated with the encoder features
        // of that level (the stem's at level 0).
        let skips = [p[2], p[1], p[0], config.stem];
        let mut decoder = Vec::with_capacity(4);
        for i in 0..4 {
            let out = p[4 + i];
            decoder.push(Stage {
                change: change(4 + i, c, out),
                blocks: blocks(4 + i, out + skips[i], out),
            });
            c = out;
        }
        let head_std = (1.0 / c as f64).sqrt();
        let head = Linear {
            weight: normal_param([c, config.out_dim], head_std, seed, "head.weight", device),
            bias: Some(Param::from_tensor(Tensor::zeros([config.out_dim], device))),
        };
        Self {
            stem: SparseConv::new(
                KERNEL_3,
                config.in_channels,
                config.stem,
                seed,
                "stem",
                device,
            ),
            stem_bn: batch_norm(config.stem, device),
            encoder,
            decoder,
            head,
        }
    }

    /// Voxel features `[V₀, in_channels]` → L2-normalized head features `[V₀, out_dim]`.
    /// `levels` must hold the maps of 5 levels, finest first.
    ///
    /// # Shapes
    ///
    /// - features: `[V₀, in_channels]`, one row per voxel of the finest level
    ///   (`levels[0].rows`; the batch's `voxel_features`: x, y, z, intensity)
    /// - output: `[V₀, out_dim]`, the same voxels, each row of unit length (a row of
    ///   zeros stays zeros)
    ///
    /// # Panics
    ///
    /// As [`backbone`](Self::backbone).
    pub fn forward(&self, features: Tensor<2>, levels: &[LevelMaps]) -> Tensor<2> {
        let ops = levels.first().map_or(RowOps::Direct, |l| l.nbr.ops);
        l2_normalize(ops.linear(&self.head, self.backbone(features, levels)))
    }

    /// Channels of [`backbone`](Self::backbone)'s output.
    pub fn backbone_dim(&self) -> usize {
        self.head.weight.dims()[0]
    }

    /// Voxel features → the last decoder stage's features `[V₀, backbone_dim]`, before
    /// the pretraining head: what downstream probes and fine-tuning start from.
    ///
    /// # Shapes
    ///
    /// - features: `[V₀, in_channels]`, one row per voxel of the finest level
    ///   (`levels[0].rows`)
    /// - output: `[V₀, backbone_dim]`, the same voxels (`backbone_dim`: the last decoder
    ///   stage's width, `planes[7]` of the [`UNetConfig`])
    ///
    /// Inside, level `l` holds `V_l = levels[l].rows` voxels: the encoder goes down to
    /// `[V₄, planes[3]]`, the decoder back up to `[V₀, planes[7]]`.
    ///
    /// # Panics
    ///
    /// Panics if `levels` holds fewer than [`UNetConfig::LEVELS`] levels.
    pub fn backbone(&self, features: Tensor<2>, levels: &[LevelMaps]) -> Tensor<2> {
        assert!(
            levels.len() >= UNetConfig::LEVELS,
            "the UNet needs kernel maps of {} levels, the batch has {}",
            UNetConfig::LEVELS,
            levels.len()
        );
        let ops = levels[0].nbr.ops;
        let mut x = relu(ops.batch_norm(&self.stem_bn, self.stem.forward(features, &levels[0])));
        let mut skips = Vec::with_capacity(4);
        for (i, stage) in self.encoder.iter().enumerate() {
            skips.push(x.clone());
            let next = &levels[i + 1];
            x = relu(ops.batch_norm(
                &stage.change.bn,
                stage.change.conv.forward_down(x, &levels[i], next.rows),
            ));
            for block in &stage.blocks {
                x = block.forward(x, next);
            }
        }
        for (i, stage) in self.decoder.iter().enumerate() {
            let level = &levels[3 - i];
            x = relu(ops.batch_norm(&stage.change.bn, stage.change.conv.forward_up(x, level)));
            let skip = skips.pop().expect("one skip per encoder stage");
            x = Tensor::cat(vec![x, skip], 1);
            for block in &stage.blocks {
                x = block.forward(x, level);
            }
        }
        x
    }
}

/// Divided by the L2 norm over dimension 1 (rows of `[N, C]`, pixels of `[I, C, H, W]`);
/// norms below 1e-12 are clamped, as in PyTorch's `F.normalize`. The clamp comes before
/// the square root: a row of zeros (a voxel whose features all died in ReLUs) then has a
/// finite gradient, as in PyTorch, where √ at 0 would make it NaN and the next step's
/// parameters with it.
///
/// # Shapes
///
/// - x: `[N, C, ...]`, any rank, normalized over `C` (dimension 1)
/// - output: the shape of `x`
pub fn l2_normalize<const D: usize>(x: Tensor<D>) -> Tensor<D> {
    let norm = x.clone().square().sum_dim(1).clamp_min(1e-24).sqrt();
    x / norm
}

#[cfg(test)]
mod tests {
    use super::*;

    /// A row of zeros (a voxel whose features all died in ReLUs) normalizes to zeros with
    /// a finite gradient, as `F.normalize` does; other rows are unit vectors.
    #[test]
    fn a_zero_row_normalizes_with_a_finite_gradient() {
        let device = Device::flex().autodiff();
        let x = Tensor::<2>::from_data(
            TensorData::new(vec![0.0f32, 0.0, 3.0, 4.0], [2, 2]),
            &device,
        )
        .require_grad();
        let y = l2_normalize(x.clone());
        let values: Vec<f32> = y.clone().into_data().try_into_vec().unwrap_or_default();
        assert_eq!(values, [0.0, 0.0, 0.6, 0.8]);
        let grads = (y * Tensor::<2>::ones([2, 2], &device)).sum().backward();
        let gradient: Vec<f32> = x
            .grad(&grads)
            .map(|g| g.into_data().try_into_vec().unwrap_or_default())
            .unwrap_or_default();
        assert_eq!(gradient.len(), 4);
        assert!(gradient.iter().all(|g| g.is_finite()), "{gradient:?}");
    }
}
