//! The SuperFlow losses: superpoint / superpixel pooling with count masks, InfoNCE, and
//! the spatial (`L_sc`), temporal (`L_tc`) and dense-to-sparse (`L_d2s`) terms.
//!
//! Everything that depends only on the batch's integer sections — which pairing falls
//! into which superpoint, which pixel into which superpixel, which slots are non-empty
//! — is computed once on the host into a [`LossPlan`]; the device work is two
//! scatter-adds (pooling), a few row selections and the similarity matrices.
//!
//! Slots: a *superpoint slot* is (cloud kind `c`, sample `b`, superpixel id `s`) with
//! `s < num_superpixels[b, frame(c)]` (the dense cloud uses the key frame's ids); a
//! *superpixel slot* is (frame `f`, sample `b`, id `s`). Slots of one kind are
//! concatenated over the samples, so negatives come from the whole batch (as in SLidR
//! and SuperFlow's code). Pooled features are plain means — not re-normalized.
//!
//! * `L_sc` = mean over frames f of InfoNCE(superpoints of frame f, superpixels of f),
//!   on slots with pairings and pixels;
//! * `L_tc` = mean over f ≠ key of InfoNCE(superpoints at the key frame, superpoints at
//!   f), on ids below both frames' counts with pairings in both;
//! * `L_d2s` on ids of the key frame with pairings in the key cloud and the dense
//!   cloud: `mean(1 − cos(q_key, q_dense))` (paper, Eq. 3) or InfoNCE(q_dense, q_key)
//!   (official code);
//! * total = w_sc·L_sc + w_tc·L_tc + w_d2s·L_d2s. A term without slots is 0.
//!
//! InfoNCE(a, b) = mean_i −log softmax_j(a_i·b_j / τ)\[i\].
//!
//! By role: `config` (the `[loss]` table), `plan` (the host-side [`LossPlan`] of a
//! batch) and `contrastive` (the pooling and the terms on the device, [`SuperFlowLoss`]).

mod config;
mod contrastive;
mod plan;

pub use config::{D2sForm, LossConfig};
pub use contrastive::{LossTerms, LossValues, SuperFlowLoss, cosine_distance, info_nce};
pub use plan::{LossInputs, LossPlan, Matched, PlanError};
