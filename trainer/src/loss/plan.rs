//! The host-side index plan of a batch's losses ([`LossPlan`]): from the batch's integer
//! sections, which pairing falls into which superpoint slot, which sampled pixel into
//! which superpixel slot, and which slots each term compares. Built once per batch on the
//! CPU; the device only receives its index tensors.

use crate::rows::RowOps;
use crate::unet::index_tensor;
use burn::tensor::{Device, Int, Tensor, TensorData};
use superflow_schemas::batch::Section;

/// What the plan needs from a batch, as host arrays (see `pipeline/src/batch.rs`).
#[derive(Debug, Clone, Copy)]
pub struct LossInputs<'a> {
    /// Samples.
    pub batch: usize,
    /// Frames per sample.
    pub frames: usize,
    /// `[B + 1]` first camera slot of each sample: sample `b` has
    /// `K_b = sample_cameras[b+1] − sample_cameras[b]` cameras, and its images are
    /// `F · sample_cameras[b] + f · K_b + k`.
    pub sample_cameras: &'a [u32],
    /// Index of the key frame (offset 0).
    pub key_frame: usize,
    /// Image height and width.
    pub height: usize,
    /// See `height`.
    pub width: usize,
    /// `[B, F]`.
    pub num_superpixels: &'a [u32],
    /// `[F·S, H, W]` (`S = sample_cameras[B]`).
    pub superpixels: &'a [u16],
    /// Global point row of each pairing.
    pub pairing_point: &'a [u32],
    /// Superpixel id of each pairing.
    pub pairing_superpixel: &'a [u32],
    /// `B·C + 1` first pairing of each cloud.
    pub pairing_clouds: &'a [u32],
}

/// A malformed batch for the losses.
#[derive(Debug, thiserror::Error)]
#[error("batch section `{section}`: {reason}")]
pub struct PlanError {
    /// The section at fault.
    pub section: &'static str,
    /// What is wrong.
    pub reason: String,
}

fn bad(section: Section, reason: impl Into<String>) -> PlanError {
    PlanError {
        section: section.spec().name,
        reason: reason.into(),
    }
}

/// Rows of two pooled tables to compare (one pair per kept slot).
#[derive(Debug, Clone)]
pub struct Matched {
    /// Rows of the first table.
    pub a: Tensor<1, Int>,
    /// Rows of the second table.
    pub b: Tensor<1, Int>,
    /// Kept slots.
    pub len: usize,
}

impl Matched {
    fn new(a: Vec<i64>, b: Vec<i64>, device: &Device) -> Self {
        let len = a.len();
        Self {
            a: index_tensor(a, device),
            b: index_tensor(b, device),
            len,
        }
    }
}

/// The host-side index plan of one batch's losses.
#[derive(Debug, Clone)]
pub struct LossPlan {
    /// Point row of every pairing (to gather the 3D features).
    pub pairing_point: Tensor<1, Int>,
    /// Superpoint slot of every pairing.
    pub(super) pairing_slot: Tensor<1, Int>,
    /// `[superpoint slots, 1]` pairings per slot, clamped to ≥ 1.
    pub(super) point_counts: Tensor<2>,
    pub(super) point_slots: usize,
    /// Sampled pixels: image number, row, column.
    pub pixels: Vec<[u32; 3]>,
    /// Superpixel slot of every sampled pixel.
    pub(super) pixel_slot: Tensor<1, Int>,
    /// `[superpixel slots, 1]` sampled pixels per slot, clamped to ≥ 1.
    pub(super) pixel_counts: Tensor<2>,
    pub(super) pixel_slots: usize,
    /// `L_sc` per frame: (superpoint rows, superpixel rows).
    pub sc: Vec<Matched>,
    /// `L_tc` per non-key frame: (key superpoint rows, frame superpoint rows).
    pub tc: Vec<Matched>,
    /// `L_d2s`: (key superpoint rows, dense superpoint rows).
    pub d2s: Matched,
    /// Image height and width.
    pub image_size: [usize; 2],
    /// How the device runs the gathers and scatter-adds ([`RowOps::of`]).
    pub(super) ops: RowOps,
}

impl LossPlan {
    /// Plans the pooling and the matched slots; checks every id against its frame's
    /// superpixel count.
    pub fn new(
        x: &LossInputs<'_>,
        pixel_stride: usize,
        device: &Device,
    ) -> Result<Self, PlanError> {
        check_lengths(x)?;
        let slots = Slots::new(x);
        let (pt_count, pairing_slot) = slots.pairings()?;
        let sampled = slots.pixels(pixel_stride)?;
        let (sc, tc, d2s) = slots.matched(&pt_count, &sampled.count, device);
        let counts = |c: Vec<u32>| {
            let len = c.len();
            let values: Vec<f32> = c.into_iter().map(|v| v.max(1) as f32).collect();
            Tensor::<2>::from_data(TensorData::new(values, [len, 1]), device)
        };
        Ok(Self {
            pairing_point: index_tensor(
                x.pairing_point.iter().map(|&p| i64::from(p)).collect(),
                device,
            ),
            pairing_slot: index_tensor(pairing_slot, device),
            point_counts: counts(pt_count),
            point_slots: slots.point_slots,
            pixels: sampled.pixels,
            pixel_slot: index_tensor(sampled.slot, device),
            pixel_counts: counts(sampled.count),
            pixel_slots: slots.pixel_slots,
            ops: RowOps::of(device),
            sc,
            tc,
            d2s,
            image_size: [x.height, x.width],
        })
    }

    /// Pixels the superpixel pooling samples, over all images.
    pub fn sampled_pixels(&self) -> usize {
        self.pixels.len()
    }
}

/// Checks that the sections have the lengths their shapes promise.
fn check_lengths(x: &LossInputs<'_>) -> Result<(), PlanError> {
    let (b_n, f_n) = (x.batch, x.frames);
    if x.num_superpixels.len() != b_n * f_n {
        return Err(bad(Section::NumSuperpixels, "expected B×F entries"));
    }
    let slots = x.sample_cameras;
    if slots.len() != b_n + 1 || slots[0] != 0 || slots.windows(2).any(|w| w[0] > w[1]) {
        return Err(bad(
            Section::SampleCameras,
            "expected B+1 non-decreasing entries from 0",
        ));
    }
    let images = f_n * slots[b_n] as usize;
    if x.superpixels.len() != images * x.height * x.width {
        return Err(bad(Section::Superpixels, "expected F·S×H×W entries"));
    }
    if x.pairing_clouds.len() != b_n * (f_n + 1) + 1 {
        return Err(bad(Section::PairingClouds, "expected B·C+1 entries"));
    }
    if x.key_frame >= f_n {
        return Err(bad(Section::FrameOffsets, "no key frame"));
    }
    Ok(())
}

/// The slot layout of a batch: where each sample's superpoint slots (per cloud kind) and
/// superpixel slots (per frame) begin. Clouds `0..F` are the frames' sweeps, cloud `F`
/// the dense cloud (numbered with the key frame's superpixels).
struct Slots<'x, 'a> {
    x: &'x LossInputs<'a>,
    /// Superpoint slot bases: `[cloud kind][sample]`.
    pt_base: Vec<Vec<usize>>,
    point_slots: usize,
    /// Superpixel slot bases: `[frame][sample]`.
    px_base: Vec<Vec<usize>>,
    pixel_slots: usize,
}

/// The sampled pixels of a batch and their superpixel slots.
struct SampledPixels {
    /// Image number, row, column.
    pixels: Vec<[u32; 3]>,
    /// Superpixel slot of each.
    slot: Vec<i64>,
    /// Sampled pixels per superpixel slot.
    count: Vec<u32>,
}

// (b, f, c) index several tables at once: plain index loops read best here.
#[allow(clippy::needless_range_loop)]
impl<'x, 'a> Slots<'x, 'a> {
    fn new(x: &'x LossInputs<'a>) -> Self {
        let mut slots = Self {
            x,
            pt_base: vec![vec![0; x.batch]; x.frames + 1],
            point_slots: 0,
            px_base: vec![vec![0; x.batch]; x.frames],
            pixel_slots: 0,
        };
        let mut next = 0;
        for c in 0..=x.frames {
            for b in 0..x.batch {
                slots.pt_base[c][b] = next;
                next += slots.n(b, slots.frame_of(c));
            }
        }
        slots.point_slots = next;
        let mut next = 0;
        for f in 0..x.frames {
            for b in 0..x.batch {
                slots.px_base[f][b] = next;
                next += slots.n(b, f);
            }
        }
        slots.pixel_slots = next;
        slots
    }

    /// Superpixels of sample `b` at frame `f`.
    fn n(&self, b: usize, f: usize) -> usize {
        self.x.num_superpixels[b * self.x.frames + f] as usize
    }

    /// The frame whose superpixel ids cloud kind `c` uses.
    fn frame_of(&self, c: usize) -> usize {
        if c == self.x.frames {
            self.x.key_frame
        } else {
            c
        }
    }

    /// Pairings → superpoint slots: the pairings per slot and each pairing's slot.
    fn pairings(&self) -> Result<(Vec<u32>, Vec<i64>), PlanError> {
        let x = self.x;
        let c_n = x.frames + 1;
        let pairings = x.pairing_point.len();
        if x.pairing_superpixel.len() != pairings
            || x.pairing_clouds[x.batch * c_n] as usize != pairings
        {
            return Err(bad(Section::PairingClouds, "does not cover the pairings"));
        }
        let mut count = vec![0u32; self.point_slots];
        let mut slot_of = Vec::with_capacity(pairings);
        for b in 0..x.batch {
            for c in 0..c_n {
                let cloud = b * c_n + c;
                let (s, e) = (
                    x.pairing_clouds[cloud] as usize,
                    x.pairing_clouds[cloud + 1] as usize,
                );
                if s > e || e > pairings {
                    return Err(bad(Section::PairingClouds, "offsets not increasing"));
                }
                let limit = self.n(b, self.frame_of(c));
                for &id in &x.pairing_superpixel[s..e] {
                    let id = id as usize;
                    if id >= limit {
                        return Err(bad(
                            Section::PairingSuperpixel,
                            format!(
                                "id {id} of cloud {cloud} is not below its frame's {limit} superpixels"
                            ),
                        ));
                    }
                    let slot = self.pt_base[c][b] + id;
                    count[slot] += 1;
                    slot_of.push(slot as i64);
                }
            }
        }
        Ok((count, slot_of))
    }

    /// Sampled pixels (every `pixel_stride`-th of each row and column) → superpixel slots.
    fn pixels(&self, pixel_stride: usize) -> Result<SampledPixels, PlanError> {
        let x = self.x;
        let (h, w) = (x.height, x.width);
        let stride = pixel_stride.max(1);
        let mut sampled = SampledPixels {
            pixels: Vec::new(),
            slot: Vec::new(),
            count: vec![0u32; self.pixel_slots],
        };
        for b in 0..x.batch {
            // Sample b's own cameras: a rig with fewer has fewer images, none empty.
            let first = x.sample_cameras[b] as usize;
            let cameras = x.sample_cameras[b + 1] as usize - first;
            for f in 0..x.frames {
                let limit = self.n(b, f);
                for k in 0..cameras {
                    let image = x.frames * first + f * cameras + k;
                    let map = &x.superpixels[image * h * w..(image + 1) * h * w];
                    for r in (stride / 2..h).step_by(stride) {
                        for col in (stride / 2..w).step_by(stride) {
                            let id = map[r * w + col] as usize;
                            if id >= limit {
                                return Err(bad(
                                    Section::Superpixels,
                                    format!(
                                        "id {id} in image {image} is not below its frame's {limit} superpixels"
                                    ),
                                ));
                            }
                            let slot = self.px_base[f][b] + id;
                            sampled.count[slot] += 1;
                            sampled.pixels.push([image as u32, r as u32, col as u32]);
                            sampled.slot.push(slot as i64);
                        }
                    }
                }
            }
        }
        Ok(sampled)
    }

    /// The kept slots of each term: `L_sc` per frame, `L_tc` per non-key frame, `L_d2s`.
    fn matched(
        &self,
        pt_count: &[u32],
        px_count: &[u32],
        device: &Device,
    ) -> (Vec<Matched>, Vec<Matched>, Matched) {
        let (f_n, key) = (self.x.frames, self.x.key_frame);
        // Pairs (a_base + s, b_base + s) of every sample, over its ids below `ids(b)`,
        // kept where both slots are non-empty.
        let pairs = |a_base: &[usize],
                     a_count: &[u32],
                     b_base: &[usize],
                     b_count: &[u32],
                     ids: &dyn Fn(usize) -> usize| {
            let (mut a, mut bb) = (Vec::new(), Vec::new());
            for b in 0..self.x.batch {
                for s in 0..ids(b) {
                    let (p, q) = (a_base[b] + s, b_base[b] + s);
                    if a_count[p] > 0 && b_count[q] > 0 {
                        a.push(p as i64);
                        bb.push(q as i64);
                    }
                }
            }
            Matched::new(a, bb, device)
        };
        let sc = (0..f_n)
            .map(|f| {
                let ids = |b| self.n(b, f);
                pairs(&self.pt_base[f], pt_count, &self.px_base[f], px_count, &ids)
            })
            .collect();
        let tc = (0..f_n)
            .filter(|&f| f != key)
            .map(|f| {
                let ids = |b| self.n(b, key).min(self.n(b, f));
                pairs(
                    &self.pt_base[key],
                    pt_count,
                    &self.pt_base[f],
                    pt_count,
                    &ids,
                )
            })
            .collect();
        let ids = |b| self.n(b, key);
        let d2s = pairs(
            &self.pt_base[key],
            pt_count,
            &self.pt_base[f_n],
            pt_count,
            &ids,
        );
        (sc, tc, d2s)
    }
}
