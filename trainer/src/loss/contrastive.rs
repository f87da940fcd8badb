//! The losses on the device: superpoint / superpixel pooling along a [`LossPlan`],
//! InfoNCE and the cosine distance, and [`SuperFlowLoss`], which weighs the terms.

use super::config::{D2sForm, LossConfig};
use super::plan::{LossPlan, Matched};
use crate::rows::RowOps;
use burn::tensor::activation::log_softmax;
use burn::tensor::{Int, Tensor};
use serde::{Deserialize, Serialize};

/// Mean of `rows` per slot: scatter-add, then divide by the (clamped) counts.
fn pool(
    rows: Tensor<2>,
    slot: &Tensor<1, Int>,
    slots: usize,
    counts: &Tensor<2>,
    ops: RowOps,
) -> Tensor<2> {
    let [_, d] = rows.dims();
    let device = rows.device();
    let sums = ops.scatter_add(Tensor::zeros([slots, d], &device), slot, rows);
    sums / counts.clone()
}

/// InfoNCE of matched rows: cross-entropy of `a·bᵀ/τ` against the diagonal.
///
/// # Shapes
///
/// - a: `[matched, channels]`, row `i` the anchor of pair `i`
/// - b: `[matched, channels]`, row `i` the positive of pair `i`, every other row a
///   negative
/// - output: `[1]`, the mean over the pairs
pub fn info_nce(a: Tensor<2>, b: Tensor<2>, temperature: f64) -> Tensor<1> {
    let [m, _] = a.dims();
    let device = a.device();
    let logits = a.matmul(b.transpose()).div_scalar(temperature);
    let log_p = log_softmax(logits, 1);
    let diagonal = (log_p * Tensor::<2>::eye(m, &device)).sum();
    diagonal.neg().div_scalar(m as f64)
}

/// `mean(1 − cos(a_i, b_i))`.
///
/// # Shapes
///
/// - a: `[matched, channels]`
/// - b: `[matched, channels]`, row `i` compared with row `i` of `a`
/// - output: `[1]`, the mean over the pairs
pub fn cosine_distance(a: Tensor<2>, b: Tensor<2>) -> Tensor<1> {
    let dot = (a.clone() * b.clone()).sum_dim(1);
    let na = a.square().sum_dim(1).sqrt();
    let nb = b.square().sum_dim(1).sqrt();
    let cos = dot / (na * nb).clamp_min(1e-8);
    cos.neg().add_scalar(1.0).mean()
}

/// The loss terms of one step (scalars, `[1]`).
#[derive(Debug, Clone)]
pub struct LossTerms {
    /// The weighted sum that is optimized.
    pub total: Tensor<1>,
    /// `L_sc` (mean over frames).
    pub sc: Tensor<1>,
    /// `L_sc` of each frame.
    pub sc_frames: Vec<Tensor<1>>,
    /// `L_tc` (mean over the non-key frames).
    pub tc: Tensor<1>,
    /// `L_d2s`.
    pub d2s: Tensor<1>,
}

/// The loss values of a step, read back from the device.
#[derive(Debug, Clone, Copy, Default, PartialEq, Serialize, Deserialize)]
pub struct LossValues {
    /// Weighted total.
    pub total: f64,
    /// `L_sc`.
    pub sc: f64,
    /// `L_tc`.
    pub tc: f64,
    /// `L_d2s`.
    pub d2s: f64,
}

impl LossTerms {
    /// Reads the scalars back (one transfer).
    pub fn values(&self) -> LossValues {
        let all = Tensor::cat(
            vec![
                self.total.clone(),
                self.sc.clone(),
                self.tc.clone(),
                self.d2s.clone(),
            ],
            0,
        );
        let v: Vec<f32> = all
            .into_data()
            .try_into_vec()
            .unwrap_or_else(|_| vec![f32::NAN; 4]);
        LossValues {
            total: f64::from(v[0]),
            sc: f64::from(v[1]),
            tc: f64::from(v[2]),
            d2s: f64::from(v[3]),
        }
    }
}

/// The SuperFlow objective.
#[derive(Debug, Clone)]
pub struct SuperFlowLoss {
    /// Temperature, weights and the `L_d2s` form.
    pub config: LossConfig,
}

impl SuperFlowLoss {
    /// The objective with `config`.
    pub fn new(config: LossConfig) -> Self {
        Self { config }
    }

    /// Superpoint features: mean 3D feature of each slot's pairings. `pairing_features`
    /// holds the 3D feature of every pairing's point, in pairing order.
    ///
    /// # Shapes
    ///
    /// - pairing_features: `[pairings, channels]`, one row per pairing of the batch
    /// - output: `[superpoint_slots, channels]`, one row per superpoint slot (cloud kind,
    ///   sample, superpixel id; see [the module](crate::loss)), zeros for a slot without
    ///   pairings
    pub fn superpoints(&self, pairing_features: Tensor<2>, plan: &LossPlan) -> Tensor<2> {
        pool(
            pairing_features,
            &plan.pairing_slot,
            plan.point_slots,
            &plan.point_counts,
            plan.ops,
        )
    }

    /// Superpixel features: mean 2D feature of each slot's sampled pixels
    /// (`pixel_features` in the order of `plan.pixels`).
    ///
    /// # Shapes
    ///
    /// - pixel_features: `[pixels, channels]`, one row per sampled pixel (`plan.pixels`)
    /// - output: `[superpixel_slots, channels]`, one row per superpixel slot (frame,
    ///   sample, superpixel id; see [the module](crate::loss)), zeros for a slot without
    ///   sampled pixels
    pub fn superpixels(&self, pixel_features: Tensor<2>, plan: &LossPlan) -> Tensor<2> {
        pool(
            pixel_features,
            &plan.pixel_slot,
            plan.pixel_slots,
            &plan.pixel_counts,
            plan.ops,
        )
    }

    fn nce(&self, a: &Tensor<2>, b: &Tensor<2>, m: &Matched, ops: RowOps) -> Option<Tensor<1>> {
        (m.len > 0).then(|| {
            info_nce(
                ops.gather(a.clone(), &m.a),
                ops.gather(b.clone(), &m.b),
                self.config.temperature,
            )
        })
    }

    /// All terms from the 3D features of the pairings' points and the 2D features of
    /// the sampled pixels.
    ///
    /// # Shapes
    ///
    /// - pairing_features: `[pairings, channels]`, one row per pairing of the batch, in
    ///   pairing order (what [`SuperFlowModel::point_features`] gives)
    /// - pixel_features: `[pixels, channels]`, one row per sampled pixel, in the order of
    ///   `plan.pixels` (what [`ImageHead::forward`] gives)
    /// - output: [`LossTerms`], every term `[1]`; `sc_frames` holds one `[1]` per frame
    ///
    /// [`SuperFlowModel::point_features`]: crate::model::SuperFlowModel::point_features
    /// [`ImageHead::forward`]: crate::model::ImageHead::forward
    pub fn forward(
        &self,
        pairing_features: Tensor<2>,
        pixel_features: Tensor<2>,
        plan: &LossPlan,
    ) -> LossTerms {
        let device = pairing_features.device();
        let zero = || Tensor::<1>::zeros([1], &device);
        let k = self.superpoints(pairing_features, plan);
        let q = self.superpixels(pixel_features, plan);
        let mean = |terms: Vec<Tensor<1>>| {
            let n = terms.len();
            if n == 0 {
                zero()
            } else {
                Tensor::cat(terms, 0).sum().div_scalar(n as f64)
            }
        };
        let sc_frames: Vec<Tensor<1>> = plan
            .sc
            .iter()
            .map(|m| self.nce(&k, &q, m, plan.ops).unwrap_or_else(zero))
            .collect();
        let sc = mean(sc_frames.clone());
        let tc = mean(
            plan.tc
                .iter()
                .map(|m| self.nce(&k, &k, m, plan.ops).unwrap_or_else(zero))
                .collect(),
        );
        let d2s = if plan.d2s.len == 0 {
            zero()
        } else {
            let key = plan.ops.gather(k.clone(), &plan.d2s.a);
            let dense = plan.ops.gather(k, &plan.d2s.b);
            match self.config.d2s {
                D2sForm::Cosine => cosine_distance(key, dense),
                D2sForm::Infonce => info_nce(dense, key, self.config.temperature),
            }
        };
        let c = &self.config;
        let total = sc.clone().mul_scalar(c.w_sc)
            + tc.clone().mul_scalar(c.w_tc)
            + d2s.clone().mul_scalar(c.w_d2s);
        LossTerms {
            total,
            sc,
            sc_frames,
            tc,
            d2s,
        }
    }
}
