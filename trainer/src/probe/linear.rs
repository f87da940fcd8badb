//! Downstream evaluation of a pretrained 3D backbone, as the SuperFlow paper reports it:
//! per-point semantic segmentation scored by mIoU on a validation split.
//!
//! The pieces that do not depend on where the features come from:
//!
//! * [`split_by_time`]: keyframes into train and validation by time within each drive
//!   (the last `val_fraction` of every drive's span is validation, with a guard gap so
//!   that no validation keyframe's sweeps overlap a training one's);
//! * [`LinearProbe`]: a linear classifier (softmax regression) trained on frozen
//!   per-point features with cross-entropy, points of the ignore index left out;
//! * [`ConfusionMatrix`]: per-class IoU = TP / (TP + FP + FN) and their mean over the
//!   classes that occur (in the labels or the predictions) of the validation split;
//! * [`ProbeReport`]: what `superflow-trainer probe --json` prints.

use crate::error::TrainerError;
use crate::probe_error::ProbeError;
use crate::rows::RowOps;
use burn::module::Module;
use burn::nn::loss::CrossEntropyLossConfig;
use burn::nn::{Initializer, Linear, LinearConfig};
use burn::optim::{AdamWConfig, GradientsParams};
use burn::tensor::{Device, Int, Tensor, TensorData};
use serde::{Deserialize, Serialize};
use std::collections::BTreeMap;

/// Counts of (label, prediction) pairs over `classes` classes; labels equal to the ignore
/// index are not counted.
#[derive(Debug, Clone, PartialEq, Eq)]
pub struct ConfusionMatrix {
    classes: usize,
    ignore: u16,
    /// Row = label, column = prediction.
    counts: Vec<u64>,
}

impl ConfusionMatrix {
    /// An empty matrix.
    pub fn new(classes: usize, ignore: u16) -> Self {
        Self {
            classes,
            ignore,
            counts: vec![0; classes * classes],
        }
    }

    /// Counts `predictions` against `labels` (same length); ignored labels are skipped, a
    /// label or prediction outside the classes is an error.
    pub fn add(&mut self, labels: &[u16], predictions: &[u16]) -> Result<(), TrainerError> {
        if labels.len() != predictions.len() {
            return Err(ProbeError::Lengths {
                labels: labels.len(),
                predictions: predictions.len(),
            }
            .into());
        }
        for (&l, &p) in labels.iter().zip(predictions) {
            if l == self.ignore {
                continue;
            }
            let (l, p) = (usize::from(l), usize::from(p));
            if l >= self.classes || p >= self.classes {
                return Err(ProbeError::Class {
                    class: l.max(p),
                    classes: self.classes,
                }
                .into());
            }
            self.counts[l * self.classes + p] += 1;
        }
        Ok(())
    }

    /// The count of label `l` predicted as `p`.
    pub fn get(&self, l: usize, p: usize) -> u64 {
        self.counts[l * self.classes + p]
    }

    /// Points counted.
    pub fn total(&self) -> u64 {
        self.counts.iter().sum()
    }

    /// IoU of class `c`, `None` when it occurs neither in the labels nor the predictions.
    pub fn iou(&self, c: usize) -> Option<f64> {
        let tp = self.get(c, c);
        let labelled: u64 = (0..self.classes).map(|p| self.get(c, p)).sum();
        let predicted: u64 = (0..self.classes).map(|l| self.get(l, c)).sum();
        let union = labelled + predicted - tp;
        (union > 0).then(|| tp as f64 / union as f64)
    }

    /// Mean IoU over the classes that occur.
    pub fn miou(&self) -> f64 {
        let ious: Vec<f64> = (0..self.classes).filter_map(|c| self.iou(c)).collect();
        if ious.is_empty() {
            return 0.0;
        }
        ious.iter().sum::<f64>() / ious.len() as f64
    }

    /// Overall accuracy.
    pub fn accuracy(&self) -> f64 {
        let correct: u64 = (0..self.classes).map(|c| self.get(c, c)).sum();
        correct as f64 / self.total().max(1) as f64
    }
}

/// A keyframe's place in time, for the split.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub struct KeyframeTime {
    /// The drive it belongs to.
    pub drive: usize,
    /// Its stamp, nanoseconds.
    pub stamp_ns: i64,
}

/// Which keyframes train the probe and which score it.
#[derive(Debug, Clone, Default, PartialEq, Eq, Serialize, Deserialize)]
pub struct Split {
    /// Indices of the training keyframes.
    pub train: Vec<usize>,
    /// Indices of the validation keyframes.
    pub val: Vec<usize>,
    /// Keyframes in neither (the guard gap between the two).
    pub dropped: Vec<usize>,
}

/// Splits keyframes by time within each drive: those in the last `val_fraction` of the
/// drive's span are validation, those in the `gap_ns` before it are dropped (a keyframe
/// and its neighbours share sweeps of the multi-sweep cloud), the rest train.
pub fn split_by_time(keyframes: &[KeyframeTime], val_fraction: f64, gap_ns: i64) -> Split {
    let mut span: BTreeMap<usize, (i64, i64)> = BTreeMap::new();
    for k in keyframes {
        let e = span.entry(k.drive).or_insert((k.stamp_ns, k.stamp_ns));
        e.0 = e.0.min(k.stamp_ns);
        e.1 = e.1.max(k.stamp_ns);
    }
    let mut split = Split::default();
    for (i, k) in keyframes.iter().enumerate() {
        let (first, last) = span[&k.drive];
        let cut = last - ((last - first) as f64 * val_fraction.clamp(0.0, 1.0)).round() as i64;
        if k.stamp_ns > cut || (val_fraction >= 1.0) {
            split.val.push(i);
        } else if k.stamp_ns > cut - gap_ns {
            split.dropped.push(i);
        } else {
            split.train.push(i);
        }
    }
    split
}

/// The first `fraction` of `train` (at least one keyframe), evenly spread: the few-label
/// protocols (1 %, 10 % of the training scans).
pub fn label_fraction(train: &[usize], fraction: f64) -> Vec<usize> {
    if train.is_empty() || fraction >= 1.0 {
        return train.to_vec();
    }
    let keep = ((train.len() as f64 * fraction).round() as usize).clamp(1, train.len());
    (0..keep).map(|i| train[i * train.len() / keep]).collect()
}

/// Settings of the linear classifier's training.
#[derive(Debug, Clone, Copy, PartialEq, Serialize, Deserialize)]
pub struct ProbeTraining {
    /// Passes over the training points.
    pub epochs: usize,
    /// Points per step.
    pub batch: usize,
    /// AdamW learning rate.
    pub lr: f64,
    /// AdamW weight decay.
    pub weight_decay: f64,
    /// Seed of the classifier's initial weights and the point order.
    pub seed: u64,
}

impl Default for ProbeTraining {
    fn default() -> Self {
        Self {
            epochs: 20,
            batch: 4096,
            lr: 1e-2,
            weight_decay: 1e-4,
            seed: 0,
        }
    }
}

/// A linear classifier over frozen `dim`-wide features.
#[derive(Module, Debug)]
pub struct LinearProbe {
    linear: Linear,
}

impl LinearProbe {
    /// Trains on `features` (`[n, dim]` row-major) and their `labels` (`ignore` left
    /// out) for `classes` classes.
    pub fn train(
        features: &[f32],
        labels: &[u16],
        dim: usize,
        classes: usize,
        ignore: u16,
        settings: &ProbeTraining,
        device: &Device,
    ) -> Result<Self, TrainerError> {
        let kept: Vec<usize> = (0..labels.len()).filter(|&i| labels[i] != ignore).collect();
        if kept.is_empty() {
            return Err(ProbeError::NoTrainingPoint.into());
        }
        if features.len() != labels.len() * dim {
            return Err(ProbeError::Features {
                values: features.len(),
                points: labels.len(),
                dim,
            }
            .into());
        }
        if let Some(&bad) = kept.iter().find(|&&i| usize::from(labels[i]) >= classes) {
            return Err(ProbeError::Label {
                label: labels[bad],
                classes,
            }
            .into());
        }
        let device = device.clone().autodiff();
        let mut probe = Self {
            linear: LinearConfig::new(dim, classes)
                .with_initializer(Initializer::Zeros)
                .init(&device),
        };
        let mut optim = AdamWConfig::new()
            .with_weight_decay(settings.weight_decay as f32)
            .init();
        let loss = CrossEntropyLossConfig::new().init(&device);
        // A step's rows are `settings.batch` points: the bias gradient sums over them.
        let ops = RowOps::of(&device);
        let mut order = kept;
        let mut state = settings.seed ^ 0x9e37_79b9_7f4a_7c15;
        for _ in 0..settings.epochs {
            shuffle(&mut order, &mut state);
            for chunk in order.chunks(settings.batch.max(1)) {
                let (x, y) = gather(features, labels, dim, chunk);
                let n = chunk.len();
                let x = Tensor::<2>::from_data(TensorData::new(x, [n, dim]), &device);
                let y = Tensor::<1, Int>::from_data(TensorData::new(y, [n]), &device);
                let l = loss.forward(ops.linear(&probe.linear, x), y);
                let grads = GradientsParams::from_grads(l.backward(), &probe);
                probe = optim.step(settings.lr, probe, grads);
            }
        }
        Ok(probe)
    }

    /// The predicted class of every point of `features` (`[n, dim]`).
    pub fn predict(&self, features: &[f32], dim: usize, device: &Device) -> Vec<u16> {
        let n = features.len() / dim.max(1);
        let mut out = Vec::with_capacity(n);
        // Inference: the plain device, no autodiff graph.
        let probe = self.valid();
        let device = device.clone().inner();
        let ops = RowOps::of(&device);
        for start in (0..n).step_by(65_536) {
            let end = (start + 65_536).min(n);
            let x = Tensor::<2>::from_data(
                TensorData::new(
                    features[start * dim..end * dim].to_vec(),
                    [end - start, dim],
                ),
                &device,
            );
            let classes = ops.linear(&probe.linear, x).argmax(1).into_data();
            let classes = classes.convert::<i64>();
            out.extend(
                classes
                    .as_slice::<i64>()
                    .expect("converted to i64")
                    .iter()
                    .map(|&c| c as u16),
            );
        }
        out
    }
}

/// Rows `rows` of `features` and their labels.
fn gather(features: &[f32], labels: &[u16], dim: usize, rows: &[usize]) -> (Vec<f32>, Vec<i64>) {
    let mut x = Vec::with_capacity(rows.len() * dim);
    let mut y = Vec::with_capacity(rows.len());
    for &r in rows {
        x.extend_from_slice(&features[r * dim..(r + 1) * dim]);
        y.push(i64::from(labels[r]));
    }
    (x, y)
}

/// Fisher–Yates with a splitmix64 stream (deterministic for a seed).
fn shuffle(values: &mut [usize], state: &mut u64) {
    for i in (1..values.len()).rev() {
        *state = state.wrapping_add(0x9e37_79b9_7f4a_7c15);
        let mut z = *state;
        z = (z ^ (z >> 30)).wrapping_mul(0xbf58_476d_1ce4_e5b9);
        z = (z ^ (z >> 27)).wrapping_mul(0x94d0_49bb_1331_11eb);
        z ^= z >> 31;
        values.swap(i, (z % (i as u64 + 1)) as usize);
    }
}

/// What `superflow-trainer probe --json` prints.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct ProbeReport {
    /// Mean IoU over the classes that occur in the validation split.
    pub miou: f64,
    /// IoU per class name (classes that occur; `class_NN` when the configuration names
    /// none).
    pub per_class: BTreeMap<String, f64>,
    /// Overall point accuracy.
    pub accuracy: f64,
    /// Labelled points scored (validation) and trained on.
    pub points: PointCounts,
    /// Keyframes in each part.
    pub split: SplitCounts,
}

/// Point counts of a probe.
#[derive(Debug, Clone, Copy, Default, PartialEq, Eq, Serialize, Deserialize)]
pub struct PointCounts {
    /// Training points (ignored ones excluded).
    pub train: u64,
    /// Validation points scored.
    pub val: u64,
}

/// Keyframe counts of a split.
#[derive(Debug, Clone, Copy, Default, PartialEq, Eq, Serialize, Deserialize)]
pub struct SplitCounts {
    /// Training keyframes used (after the label fraction).
    pub train: usize,
    /// Validation keyframes.
    pub val: usize,
    /// Keyframes in the guard gap.
    pub dropped: usize,
}

impl ProbeReport {
    /// The report of a confusion matrix; `names` name the classes (index → name).
    pub fn new(
        matrix: &ConfusionMatrix,
        names: &[String],
        points: PointCounts,
        split: SplitCounts,
    ) -> Self {
        let per_class = (0..matrix.classes)
            .filter_map(|c| {
                let name = names
                    .get(c)
                    .cloned()
                    .unwrap_or_else(|| format!("class_{c:02}"));
                matrix.iou(c).map(|iou| (name, iou))
            })
            .collect();
        Self {
            miou: matrix.miou(),
            per_class,
            accuracy: matrix.accuracy(),
            points,
            split,
        }
    }
}

#[cfg(test)]
#[allow(clippy::unwrap_used)]
mod tests {
    use super::*;

    #[test]
    fn iou_matches_a_hand_computed_confusion_matrix() {
        // labels:      0 0 0 1 1 2 2 2 255
        // predictions: 0 0 1 1 2 2 2 0 1
        let mut m = ConfusionMatrix::new(3, 255);
        m.add(&[0, 0, 0, 1, 1, 2, 2, 2, 255], &[0, 0, 1, 1, 2, 2, 2, 0, 1])
            .unwrap();
        assert_eq!(m.total(), 8, "the ignored point is not counted");
        // class 0: TP 2, FN 1 (0→1), FP 1 (2→0): 2/4
        // class 1: TP 1, FN 1 (1→2), FP 1 (0→1): 1/3
        // class 2: TP 2, FN 1 (2→0), FP 1 (1→2): 2/4
        assert_eq!(m.iou(0), Some(0.5));
        assert!((m.iou(1).unwrap() - 1.0 / 3.0).abs() < 1e-12);
        assert_eq!(m.iou(2), Some(0.5));
        assert!((m.miou() - (0.5 + 1.0 / 3.0 + 0.5) / 3.0).abs() < 1e-12);
        assert!((m.accuracy() - 5.0 / 8.0).abs() < 1e-12);
        let mut absent = ConfusionMatrix::new(4, 255);
        absent.add(&[0, 1], &[0, 1]).unwrap();
        assert_eq!(
            absent.iou(3),
            None,
            "a class absent from labels and predictions"
        );
        assert_eq!(absent.miou(), 1.0);
        assert!(absent.add(&[4], &[0]).is_err());
        assert!(absent.add(&[0], &[]).is_err());
    }

    #[test]
    fn the_split_is_by_time_and_no_keyframe_is_in_both() {
        let keyframes: Vec<KeyframeTime> = (0..2)
            .flat_map(|drive| {
                (0..20).map(move |k| KeyframeTime {
                    drive,
                    stamp_ns: 1_000 + k * 500_000_000,
                })
            })
            .collect();
        let split = split_by_time(&keyframes, 0.25, 1_000_000_000);
        let all: std::collections::BTreeSet<usize> = split
            .train
            .iter()
            .chain(&split.val)
            .chain(&split.dropped)
            .copied()
            .collect();
        assert_eq!(
            all.len(),
            keyframes.len(),
            "every keyframe in exactly one part"
        );
        assert_eq!(
            split.train.len() + split.val.len() + split.dropped.len(),
            keyframes.len()
        );
        for drive in 0..2 {
            let last_train = split
                .train
                .iter()
                .filter(|&&i| keyframes[i].drive == drive)
                .map(|&i| keyframes[i].stamp_ns)
                .max()
                .unwrap();
            let first_val = split
                .val
                .iter()
                .filter(|&&i| keyframes[i].drive == drive)
                .map(|&i| keyframes[i].stamp_ns)
                .min()
                .unwrap();
            assert!(
                first_val - last_train > 1_000_000_000,
                "the gap separates train and val"
            );
        }
        assert_eq!(split.val.len(), 2 * 5, "the last quarter of each drive");
        assert_eq!(label_fraction(&split.train, 0.1).len(), 3);
        assert_eq!(label_fraction(&split.train, 0.001).len(), 1);
        assert_eq!(label_fraction(&split.train, 1.0), split.train);
    }

    /// Points of `classes` classes with a few ignored ones.
    fn labels(n: usize, classes: usize) -> Vec<u16> {
        (0..n)
            .map(|i| {
                if i % 17 == 0 {
                    255
                } else {
                    ((i * 7 + i / 3) % classes) as u16
                }
            })
            .collect()
    }

    #[test]
    fn features_that_encode_the_label_are_probed_perfectly() {
        let (n, classes) = (3000, 6);
        let y = labels(n, classes);
        // One-hot of the label (zeros for ignored points).
        let x: Vec<f32> = y
            .iter()
            .flat_map(|&l| (0..classes).map(move |c| f32::from(u8::from(usize::from(l) == c))))
            .collect();
        let device = Device::flex();
        let settings = ProbeTraining {
            epochs: 30,
            batch: 512,
            ..ProbeTraining::default()
        };
        let probe = LinearProbe::train(&x, &y, classes, classes, 255, &settings, &device).unwrap();
        let mut m = ConfusionMatrix::new(classes, 255);
        m.add(&y, &probe.predict(&x, classes, &device)).unwrap();
        assert!(m.miou() >= 0.99, "mIoU {}", m.miou());
    }

    #[test]
    fn constant_features_score_at_chance() {
        let (n, classes, dim) = (3000, 6, 8);
        let y = labels(n, classes);
        let x = vec![0.5f32; n * dim];
        let device = Device::flex();
        let settings = ProbeTraining {
            epochs: 5,
            batch: 512,
            ..ProbeTraining::default()
        };
        let probe = LinearProbe::train(&x, &y, dim, classes, 255, &settings, &device).unwrap();
        let predictions = probe.predict(&x, dim, &device);
        assert!(
            predictions.windows(2).all(|w| w[0] == w[1]),
            "one class for identical inputs"
        );
        let mut m = ConfusionMatrix::new(classes, 255);
        m.add(&y, &predictions).unwrap();
        // One class predicted everywhere: its IoU is its share, the others 0.
        let labelled = y.iter().filter(|&&l| l != 255).count() as f64;
        let best_share = (0..classes)
            .map(|c| y.iter().filter(|&&l| usize::from(l) == c).count() as f64 / labelled)
            .fold(0.0, f64::max);
        assert!(
            m.miou() <= best_share / classes as f64 + 1e-9,
            "mIoU {}",
            m.miou()
        );
    }
}
