//! The trainable SuperFlow model: the 3D UNet and the 2D projection head on top of the
//! frozen ViT.
//!
//! The 2D head is a 1×1 convolution (ViT width → 64), bilinear upsampling ×14 with
//! aligned corners, and L2 normalization per pixel. Both the convolution and the
//! upsampling are linear (and the bilinear weights sum to one, so the bias commutes), so
//! the head is applied at patch resolution and the upsampled map is evaluated only at
//! the pixels the superpixel pooling samples: the same values as the full map at those
//! pixels, at a fraction of the cost.

use crate::init::normal_param;
use crate::rows::RowOps;
use crate::unet::{LevelMaps, SparseUNet, UNetConfig, index_tensor, l2_normalize};
use burn::module::{Module, Param};
use burn::nn::Linear;
use burn::tensor::{Device, Int, Tensor, TensorData};

/// The 2D projection head.
#[derive(Module, Debug)]
pub struct ImageHead {
    conv: Linear,
}

/// Bilinear (aligned corners) sampling of a patch grid at chosen pixels: the four grid
/// cells around each pixel and their weights, computed on the host.
#[derive(Debug, Clone)]
pub struct PixelSampler {
    corners: [Tensor<1, Int>; 4],
    weights: [Tensor<2>; 4],
    ops: RowOps,
}

impl PixelSampler {
    /// Sampling of `pixels` (image, row, col) of `[H, W]` images from a `[gh, gw]` grid
    /// upsampled by `H/gh` with aligned corners: source = dst·(g − 1)/(size − 1).
    pub fn new(pixels: &[[u32; 3]], image: [usize; 2], grid: [usize; 2], device: &Device) -> Self {
        let [h, w] = image;
        let [gh, gw] = grid;
        let scale = |size: usize, g: usize| {
            if size > 1 {
                (g as f64 - 1.0) / (size as f64 - 1.0)
            } else {
                0.0
            }
        };
        let (sy, sx) = (scale(h, gh), scale(w, gw));
        let n = pixels.len();
        let mut idx: [Vec<i64>; 4] = std::array::from_fn(|_| Vec::with_capacity(n));
        let mut wt: [Vec<f32>; 4] = std::array::from_fn(|_| Vec::with_capacity(n));
        for &[image, r, c] in pixels {
            let y = f64::from(r) * sy;
            let x = f64::from(c) * sx;
            let (y0, x0) = (y.floor() as usize, x.floor() as usize);
            let (y1, x1) = ((y0 + 1).min(gh - 1), (x0 + 1).min(gw - 1));
            let (fy, fx) = (y - y0 as f64, x - x0 as f64);
            let base = image as usize * gh * gw;
            let cells = [(y0, x0), (y0, x1), (y1, x0), (y1, x1)];
            let weights = [
                (1.0 - fy) * (1.0 - fx),
                (1.0 - fy) * fx,
                fy * (1.0 - fx),
                fy * fx,
            ];
            for j in 0..4 {
                idx[j].push((base + cells[j].0 * gw + cells[j].1) as i64);
                wt[j].push(weights[j] as f32);
            }
        }
        Self {
            ops: RowOps::of(device),
            corners: idx.map(|v| index_tensor(v, device)),
            weights: wt.map(|v| {
                let len = v.len();
                Tensor::from_data(TensorData::new(v, [len, 1]), device)
            }),
        }
    }

    /// `[cells, C]` grid rows → `[pixels, C]`.
    ///
    /// # Shapes
    ///
    /// - grid_rows: `[I·gh·gw, C]`, the `[gh, gw]` grid cells of every image as rows, in
    ///   (image, grid row, grid column) order
    /// - output: `[pixels, C]`, one row per pixel given to [`new`](Self::new), in its order
    pub fn sample(&self, grid_rows: Tensor<2>) -> Tensor<2> {
        let mut out: Option<Tensor<2>> = None;
        for j in 0..4 {
            let term =
                self.ops.gather(grid_rows.clone(), &self.corners[j]) * self.weights[j].clone();
            out = Some(match out {
                Some(acc) => acc + term,
                None => term,
            });
        }
        out.expect("four corners")
    }
}

impl ImageHead {
    /// A head from `dim` ViT channels to `out_dim`.
    pub fn new(dim: usize, out_dim: usize, seed: u64, device: &Device) -> Self {
        Self {
            conv: Linear {
                weight: normal_param(
                    [dim, out_dim],
                    (1.0 / dim as f64).sqrt(),
                    seed,
                    "image_head.weight",
                    device,
                ),
                bias: Some(Param::from_tensor(Tensor::zeros([out_dim], device))),
            },
        }
    }

    /// ViT patch features `[I, dim, gh, gw]` (frozen: no gradient flows into them) →
    /// L2-normalized 64-d features at the sampled pixels, `[pixels, 64]`.
    ///
    /// The convolution's bias gradient sums over every patch of every image (a batch of
    /// 8 samples of 6 cameras × 3 frames of 512 patches: 73 728 rows), so it goes through
    /// [`RowOps::linear`] like the 3D network's layers; on the CPU that is burn's `Linear`.
    ///
    /// # Shapes
    ///
    /// - patches: `[I, dim, gh, gw]`, the ViT's patch features of every image of the batch
    ///   (`gh = H / 14`, `gw = W / 14`), as
    ///   [`DinoVit::forward`](crate::vit::DinoVit::forward) gives them
    /// - output: `[pixels, out_dim]`, one unit row per pixel of `sampler` (`out_dim`: the
    ///   UNet's, 64 in every preset)
    pub fn forward(&self, patches: Tensor<4>, sampler: &PixelSampler) -> Tensor<2> {
        let [i, d, gh, gw] = patches.dims();
        let rows = patches.permute([0, 2, 3, 1]).reshape([i * gh * gw, d]);
        l2_normalize(sampler.sample(sampler.ops.linear(&self.conv, rows)))
    }
}

/// Everything the optimizer trains.
#[derive(Module, Debug)]
pub struct SuperFlowModel {
    /// The 3D network with its head.
    pub unet: SparseUNet,
    /// The 2D head (the ViT itself is frozen and lives outside).
    pub image_head: ImageHead,
}

impl SuperFlowModel {
    /// A fresh model for a ViT of width `vit_dim`.
    pub fn new(unet: &UNetConfig, vit_dim: usize, seed: u64, device: &Device) -> Self {
        Self {
            unet: SparseUNet::new(unet, seed, device),
            image_head: ImageHead::new(vit_dim, unet.out_dim, seed, device),
        }
    }

    /// 3D features of the voxels → of the pairings' points.
    ///
    /// # Shapes
    ///
    /// - voxel_features: `[V₀, in_channels]`, one row per voxel of the finest level
    ///   (`levels[0].rows`)
    /// - pairing_voxel: `[pairings]`, the level-0 voxel row of every pairing's point,
    ///   over every cloud of every sample
    /// - output: `[pairings, out_dim]`, the UNet's head feature of each pairing's voxel
    ///
    /// # Panics
    ///
    /// As [`SparseUNet::backbone`].
    pub fn point_features(
        &self,
        voxel_features: Tensor<2>,
        levels: &[LevelMaps],
        pairing_voxel: Tensor<1, Int>,
    ) -> Tensor<2> {
        // The kernel maps know how this device runs gathers.
        let ops = levels.first().map_or(RowOps::Direct, |l| l.nbr.ops);
        ops.gather(self.unet.forward(voxel_features, levels), &pairing_voxel)
    }
}
