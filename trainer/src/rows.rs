//! Row gathers and scatter-adds over index tensors of any length, on every backend.
//!
//! burn 0.22.1's scatter-add (`select_assign(0, index, values, IndexingUpdateOp::Add)`) is
//! silently wrong on `wgpu` from 65 536 index rows on Mesa's llvmpipe, whose adapter
//! reports 65 535 workgroups per dispatch dimension; the trainer takes the adapter's limit
//! as the bound (see `pipeline/docs/FIELD_NOTES.md`, burn). A gather's backward is that
//! scatter-add, so gathers are affected too. Where [`device::index_rows_limit`](crate::device::index_rows_limit)
//! names a limit ([`RowOps::Pieces`]), the ops run in pieces of at most that many index rows
//! (the same sums: every piece adds into the same output), as burn's `gather` and
//! `scatter`, which use every thread of the device; elsewhere ([`RowOps::Direct`]) they
//! are the single burn op, at no extra cost.
//!
//! burn's reductions over the row dimension (`sum_dim(0)`, `mean_dim(0)`, and so the
//! backward of every broadcast over rows: batch norm, a linear layer's bias) are wrong on
//! wgpu past the same number of rows. [`RowOps::batch_norm`] and [`RowOps::linear`] therefore sum
//! and broadcast rows in pieces on such a device; the CPU keeps burn's modules as they are.

use burn::nn::{BatchNorm, Linear};
use burn::tensor::{IndexingUpdateOp, Int, Tensor};

/// The pieces `[start, start + len)` of `0..n` no longer than `limit`.
fn pieces(n: usize, limit: usize) -> impl Iterator<Item = (usize, usize)> {
    let limit = limit.max(1);
    (0..n).step_by(limit).map(move |s| (s, limit.min(n - s)))
}

/// How a backend is to run row gathers and scatter-adds.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum RowOps {
    /// burn's `select` and `select_assign` as they are (the CPU backends).
    Direct,
    /// `gather` and `scatter` with the index broadcast over the channels (fully parallel,
    /// atomic adds where the device has them; their backward passes are each other), in
    /// launches of at most this many index rows (the adapter's workgroup limit).
    Pieces(usize),
}

impl RowOps {
    /// What `device` needs: [`Pieces`](Self::Pieces) of the adapter's limit on the wgpu
    /// devices [`device::select`](crate::device::select) opened, [`Direct`](Self::Direct)
    /// elsewhere.
    pub fn of(device: &burn::tensor::Device) -> Self {
        match crate::device::index_rows_limit(device) {
            Some(limit) => Self::Pieces(limit.max(1)),
            None => Self::Direct,
        }
    }

    /// Rows `index` of `x` (`x.select(0, index)`).
    pub fn gather(self, x: Tensor<2>, index: &Tensor<1, Int>) -> Tensor<2> {
        match self {
            Self::Direct => x.select(0, index.clone()),
            Self::Pieces(limit) => {
                let n = index.dims()[0];
                let c = x.dims()[1];
                let piece = |s: usize, len: usize| {
                    let i = index.clone().narrow(0, s, len).reshape([len, 1]);
                    x.clone().gather(0, i.expand([len, c]))
                };
                if n <= limit {
                    return piece(0, n);
                }
                Tensor::cat(pieces(n, limit).map(|(s, len)| piece(s, len)).collect(), 0)
            }
        }
    }

    /// `out` with row `i` of `values` added into its row `index[i]`, for every `i`
    /// (`out.select_assign(0, index, values, Add)`).
    pub fn scatter_add(
        self,
        out: Tensor<2>,
        index: &Tensor<1, Int>,
        values: Tensor<2>,
    ) -> Tensor<2> {
        match self {
            Self::Direct => out.select_assign(0, index.clone(), values, IndexingUpdateOp::Add),
            Self::Pieces(limit) => {
                let n = index.dims()[0];
                let c = values.dims()[1];
                pieces(n, limit).fold(out, |acc, (s, len)| {
                    let i = index.clone().narrow(0, s, len).reshape([len, 1]);
                    acc.scatter(
                        0,
                        i.expand([len, c]),
                        values.clone().narrow(0, s, len),
                        IndexingUpdateOp::Add,
                    )
                })
            }
        }
    }

    /// Rows per piece of a sum over rows on a device with a limit: small enough that f32
    /// sums of positive terms stay within ~1e-5 of the CPU's (burn's wgpu reduction adds
    /// a column's rows one after the other), and never above the adapter's limit.
    fn sum_piece(limit: usize) -> usize {
        limit.clamp(1, 1024)
    }

    /// Column sums `[1, C]` of `x` (`x.sum_dim(0)`). On a device with a limit: padded
    /// with zero rows to `p` pieces, reshaped to `[p, piece, C]`, summed over each piece,
    /// then over the `p` piece sums the same way.
    pub fn sum_rows(self, x: Tensor<2>) -> Tensor<2> {
        let [n, c] = x.dims();
        match self {
            Self::Pieces(limit) if n > Self::sum_piece(limit) => {
                let piece = Self::sum_piece(limit);
                let p = n.div_ceil(piece);
                let device = x.device();
                let padded = if p * piece > n {
                    Tensor::cat(vec![x, Tensor::zeros([p * piece - n, c], &device)], 0)
                } else {
                    x
                };
                let partial = padded.reshape([p, piece, c]).sum_dim(1).reshape([p, c]);
                self.sum_rows(partial)
            }
            _ => x.sum_dim(0),
        }
    }

    /// `row` (`[1, C]`) repeated `n` times (its gradient: [`sum_rows`](Self::sum_rows)
    /// of the incoming one, in pieces on a device with a limit).
    pub fn broadcast_rows(self, row: Tensor<2>, n: usize) -> Tensor<2> {
        let c = row.dims()[1];
        match self {
            Self::Pieces(limit) if n > Self::sum_piece(limit) => {
                let piece = Self::sum_piece(limit);
                let p = n.div_ceil(piece);
                self.broadcast_rows(row, p)
                    .reshape([p, 1, c])
                    .expand([p, piece, c])
                    .reshape([p * piece, c])
                    .narrow(0, 0, n)
            }
            _ => row.expand([n, c]),
        }
    }

    /// `bn.forward(x)` over rows `[N, C]`. On a device with a limit, the training-mode
    /// statistics (biased batch mean and variance, as burn's) and every broadcast over
    /// rows go through [`sum_rows`](Self::sum_rows) and
    /// [`broadcast_rows`](Self::broadcast_rows); the running statistics are updated as
    /// burn updates them.
    pub fn batch_norm(self, bn: &BatchNorm, x: Tensor<2>) -> Tensor<2> {
        let training = x.device().is_autodiff() && bn.training.is_enabled();
        if self == Self::Direct || !training {
            // Inference is element-wise: no reduction over rows.
            return bn.forward(x);
        }
        let [n, c] = x.dims();
        let mean = self.sum_rows(x.clone()).div_scalar(n as f64);
        let centered = x - self.broadcast_rows(mean.clone(), n);
        let variance = self
            .sum_rows(centered.clone().square())
            .div_scalar(n as f64);
        let scale =
            variance.clone().add_scalar(bn.epsilon).sqrt().recip() * bn.gamma.val().reshape([1, c]);
        let out = centered * self.broadcast_rows(scale, n)
            + self.broadcast_rows(bn.beta.val().reshape([1, c]), n);

        let device = out.device();
        let update = |state: &burn::module::RunningState<Tensor<1>>, batch: Tensor<2>| {
            let running = state
                .value_sync()
                .to_device(&device)
                .mul_scalar(1.0 - bn.momentum)
                .add(batch.detach().reshape([c]).mul_scalar(bn.momentum));
            state.update(running.detach());
        };
        update(&bn.running_mean, mean);
        update(&bn.running_var, variance);
        out
    }

    /// `linear.forward(x)` over rows `[N, C]`; on a device with a limit, the bias is
    /// broadcast with [`broadcast_rows`](Self::broadcast_rows).
    pub fn linear(self, linear: &Linear, x: Tensor<2>) -> Tensor<2> {
        match (self, &linear.bias) {
            (Self::Pieces(_), Some(bias)) => {
                let n = x.dims()[0];
                let out = x.matmul(linear.weight.val());
                let c = out.dims()[1];
                out + self.broadcast_rows(bias.val().reshape([1, c]), n)
            }
            _ => linear.forward(x),
        }
    }
}
