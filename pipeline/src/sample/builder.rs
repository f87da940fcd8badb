//! From a dataset to samples: [`SampleBuilder::new`] checks the recipe against the
//! dataset and makes its [`Plan`]; [`SampleBuilder::build`] turns `(epoch, index)` into a
//! [`Sample`] — decoded and de-skewed sweeps, the dense cloud, chosen cameras with
//! resized (and maybe flipped) images and superpixels, point↔pixel pairings, augmented
//! clouds, voxels and the UNet's sparse-convolution maps. Work inside a sample runs on
//! rayon; every random choice comes from a [`SampleRng`] stream keyed by
//! `(seed, epoch, index)`.

use super::cloud::DenseCloud;
use super::epochs::{EpochMix, EpochOrder};
use super::error::SampleError;
use super::frames::{FrameCache, FrameKey, LastUses};
use super::load::{FrameInputs, SampleContext};
use super::plan::{KeyframeRef, Plan};
use super::recipe::{SampleConfig, SuperpixelSource};
use super::rng::{Purpose, SampleRng};
use super::types::{Cloud, Frame, Pair, Sample, SampleId, StageTimes};
use crate::drive::{Dataset, Drive};
use rayon::prelude::*;
use std::sync::OnceLock;

/// Builds samples of a dataset.
#[derive(Debug)]
pub struct SampleBuilder<'d> {
    dataset: &'d Dataset,
    config: SampleConfig,
    plan: Plan,
    mix: EpochMix,
    class_superpixels: Vec<bool>,
    slic_sidecar: Vec<bool>,
    /// Frames shared by neighbouring samples (the `blocks` order only).
    frames: Option<FrameCache>,
}

/// Whether `drive`'s superpixels come from its class maps under `source`.
fn class_superpixels(drive: &Drive, source: SuperpixelSource) -> Result<bool, SampleError> {
    let all_have = drive.cameras.iter().all(|c| !c.superpixels.is_empty());
    Ok(match source {
        SuperpixelSource::Auto => all_have,
        SuperpixelSource::Slic => false,
        SuperpixelSource::Channel if all_have => true,
        SuperpixelSource::Channel => {
            let missing: Vec<&str> = drive
                .cameras
                .iter()
                .filter(|c| c.superpixels.is_empty())
                .map(|c| c.name.as_str())
                .collect();
            return Err(SampleError::NoClassMaps {
                files: drive.file_list(),
                cameras: missing.join(", "),
            });
        }
    })
}

/// Whether the SLIC superpixels of `drive` come from its `.slic.mcap` sidecar: when every
/// camera has one computed with `config`'s settings. A sidecar for other settings is
/// left unused, and said so.
fn slic_sidecar(drive: &Drive, config: &SampleConfig) -> bool {
    if super::sidecar::sidecar_matches(drive, config) {
        return true;
    }
    if drive.cameras.iter().any(|c| c.slic.is_some()) {
        tracing::warn!(
            "{}: the SLIC sidecar was written for other settings (image size, SLIC \
             parameters or reduced decoding) or lacks cameras; SLIC runs per sample. \
             Rewrite it: superflow-pipeline superpixels --force",
            drive.file_list()
        );
    }
    false
}

impl<'d> SampleBuilder<'d> {
    /// Checks the recipe against the dataset and plans its keyframes.
    pub fn new(dataset: &'d Dataset, config: SampleConfig) -> Result<Self, SampleError> {
        config.validate()?;
        dataset.check_sensors()?;
        let class_superpixels: Vec<bool> = dataset
            .drives
            .iter()
            .map(|drive| class_superpixels(drive, config.superpixels))
            .collect::<Result<_, _>>()?;
        let slic_sidecar = dataset
            .drives
            .iter()
            .zip(&class_superpixels)
            .map(|(drive, &classes)| !classes && slic_sidecar(drive, &config))
            .collect();
        let plan = Plan::new(dataset, &config);
        let mix = EpochMix::new(&plan, &dataset.groups);
        Ok(Self {
            dataset,
            config,
            plan,
            mix,
            class_superpixels,
            slic_sidecar,
            frames: None,
        })
    }

    /// This builder with epochs in `order` (`global` unless told). Under `blocks` it
    /// keeps the frames that the samples of open blocks share ([`FrameCache`]) for
    /// `open + 1` positions after their last use: a block's next keyframe comes `open`
    /// positions after the one before. A caller that builds positions out of order
    /// (several streams, batches built ahead) widens that with
    /// [`Self::keep_frames_for`].
    pub fn with_order(mut self, order: EpochOrder) -> Self {
        self.mix = self.mix.ordered(order);
        self.frames = match order {
            EpochOrder::Global => None,
            EpochOrder::Blocks { open, .. } => {
                crate::source::keep_chunks_for_blocks(open as usize);
                Some(FrameCache::new(u64::from(open) + 1))
            }
        };
        self
    }

    /// Keeps shared frames `positions` more positions after their last use (samples
    /// built up to that far apart in the run's order).
    pub fn keep_frames_for(mut self, positions: u64) -> Self {
        if let Some(cache) = &self.frames {
            self.frames = Some(FrameCache::new(cache.keep() + positions));
        }
        self
    }

    /// The frames shared by neighbouring samples, when kept (the `blocks` order).
    pub fn frame_cache(&self) -> Option<&FrameCache> {
        self.frames.as_ref()
    }

    /// The dataset the samples come from.
    pub fn dataset(&self) -> &'d Dataset {
        self.dataset
    }

    /// The plan.
    pub fn plan(&self) -> &Plan {
        &self.plan
    }

    /// The recipe.
    pub fn config(&self) -> &SampleConfig {
        &self.config
    }

    /// How the keyframes make up each epoch (the dataset groups' repeats).
    pub fn mix(&self) -> &EpochMix {
        &self.mix
    }

    /// Samples per epoch: every group's keyframes times its repeat.
    pub fn epoch_len(&self) -> usize {
        self.mix.len
    }

    /// The plan keyframe of each position of `epoch`, in the order they are served.
    pub fn epoch_order(&self, epoch: u64) -> Vec<u32> {
        self.mix.order(self.config.seed, epoch)
    }

    /// Where drive `drive`'s superpixels come from: its class maps, its SLIC sidecar
    /// (else SLIC runs per image).
    pub(super) fn superpixel_sources(&self, drive: usize) -> (bool, bool) {
        (self.class_superpixels[drive], self.slic_sidecar[drive])
    }

    /// Sample `index` of `epoch` (the epoch's shuffled keyframe order).
    pub fn build(&self, epoch: u64, index: u64) -> Result<Sample, SampleError> {
        let len = self.epoch_len();
        if index as usize >= len {
            return Err(SampleError::OutOfRange {
                index: index as usize,
                len,
            });
        }
        let order = self.epoch_order(epoch);
        self.build_keyframe(order[index as usize] as usize, epoch, index)
    }

    /// The cameras of `drive` that sample `index` of `epoch` uses, in slot order.
    fn chosen_cameras(&self, drive: &Drive, epoch: u64, index: u64) -> Vec<usize> {
        let m = drive.cameras.len();
        let k = (self.config.cameras as usize).min(m);
        SampleRng::new(self.config.seed, epoch, index, Purpose::Cameras).choose(m, k)
    }

    /// The last run position of `epoch` that asks for each frame: every position's
    /// temporal frames (sweep and chosen cameras' images) and dense-cloud sweeps.
    fn frame_uses(&self, epoch: u64) -> LastUses {
        let mut uses = LastUses::new();
        let base = epoch * self.epoch_len() as u64;
        for (index, &keyframe) in self.epoch_order(epoch).iter().enumerate() {
            let position = base + index as u64;
            let key = &self.plan.keyframes[keyframe as usize];
            let drive = key.drive;
            let chosen =
                self.chosen_cameras(&self.dataset.drives[drive as usize], epoch, index as u64);
            for &sweep in &key.frame_sweeps {
                uses.insert(FrameKey::Sweep { drive, sweep }, position);
                for &camera in &chosen {
                    let camera = camera as u32;
                    uses.insert(
                        FrameKey::Image {
                            drive,
                            sweep,
                            camera,
                        },
                        position,
                    );
                }
            }
            for sweep in earlier_sweeps(key, self.config.dense_sweeps) {
                uses.insert(FrameKey::Sweep { drive, sweep }, position);
            }
        }
        uses
    }

    /// The sample of plan keyframe `keyframe` with the draws of `(epoch, index)`.
    pub fn build_keyframe(
        &self,
        keyframe: usize,
        epoch: u64,
        index: u64,
    ) -> Result<Sample, SampleError> {
        let key = self
            .plan
            .keyframes
            .get(keyframe)
            .ok_or(SampleError::OutOfRange {
                index: keyframe,
                len: self.plan.keyframes.len(),
            })?;
        let drive = &self.dataset.drives[key.drive as usize];
        let cfg = &self.config;
        let id = SampleId {
            epoch,
            index,
            keyframe: keyframe as u32,
            drive: key.drive,
            sweep: key.sweep,
        };
        let chosen = self.chosen_cameras(drive, epoch, index);
        let last_uses = self
            .frames
            .as_ref()
            .map(|cache| cache.last_uses(epoch, || self.frame_uses(epoch)));
        let ctx = SampleContext {
            config: cfg,
            drive,
            id,
            class_superpixels: self.class_superpixels[key.drive as usize],
            slic_sidecar: self.slic_sidecar[key.drive as usize],
            chosen: &chosen,
            scan: &self.plan.scans[key.drive as usize],
            frames: self.frames.as_ref(),
            position: epoch * self.epoch_len() as u64 + index,
            last_uses: last_uses.as_deref().and_then(OnceLock::get),
        };
        let key_frame = cfg
            .frame_offsets()
            .iter()
            .position(|o| *o == 0)
            .unwrap_or(0);
        let (frames, mut dense) = load_keyframe(&ctx, key, key_frame)?;
        let (frames, dense_cloud, times) = finish_frames(&ctx, key, frames, &mut dense, key_frame);
        Ok(Sample {
            id,
            seed: cfg.seed,
            camera_indices: chosen.iter().map(|&c| c as u32).collect(),
            cameras: chosen
                .iter()
                .map(|&c| drive.cameras[c].name.clone())
                .collect(),
            frames,
            key_frame,
            dense: dense_cloud,
            dense_stamps: dense.stamps,
            dense_missing: dense.missing,
            dense_dropped_non_finite: dense.dropped_non_finite,
            class_superpixels: ctx.class_superpixels,
            times,
        })
    }
}

/// The sweeps before `key`'s that its dense cloud adds, nearest first (fewer at the
/// start of a drive).
fn earlier_sweeps(key: &KeyframeRef, dense_sweeps: u32) -> impl Iterator<Item = u32> + '_ {
    (1..=dense_sweeps).filter_map(|j| key.sweep.checked_sub(j))
}

/// The temporal frames of `key` (sweep and images each) and the earlier sweeps of its
/// dense cloud, all loaded in parallel; `key_frame` is the keyframe's position among
/// the frames.
fn load_keyframe(
    ctx: &SampleContext<'_>,
    key: &KeyframeRef,
    key_frame: usize,
) -> Result<(Vec<FrameInputs>, DenseCloud), SampleError> {
    let dense_sweeps = ctx.config.dense_sweeps;
    let earlier: Vec<u32> = earlier_sweeps(key, dense_sweeps).collect();
    let (frames, dense_parts) = rayon::join(
        || {
            key.frame_sweeps
                .par_iter()
                .enumerate()
                .map(|(f, &sweep)| ctx.load_frame(f as u32, sweep))
                .collect::<Result<Vec<_>, _>>()
        },
        || {
            earlier
                .par_iter()
                .map(|&s| ctx.load_into_key_frame(s, key.sweep))
                .collect::<Vec<_>>()
        },
    );
    let frames = frames?;
    let missing = dense_sweeps - earlier.len() as u32;
    let keyframe = ctx.id.keyframe as usize;
    let dense = DenseCloud::assemble(&frames[key_frame].sweep, dense_parts, missing, keyframe);
    Ok((frames, dense))
}

/// Pairing, augmentation, voxels and maps of every cloud: the frames' in order, then
/// the dense one (paired with the keyframe's images; its source sweeps move into the
/// result). Returns the frames, the dense cloud and the time of it all, loading
/// included.
fn finish_frames(
    ctx: &SampleContext<'_>,
    key: &KeyframeRef,
    frames: Vec<FrameInputs>,
    dense: &mut DenseCloud,
    key_frame: usize,
) -> (Vec<Frame>, Cloud, StageTimes) {
    let n_frames = frames.len() as u32;
    let dense_source = std::mem::take(&mut dense.source_sweep);
    let key_inputs = &frames[key_frame];
    let finish_frame = |f: usize, fr: &FrameInputs, known: Option<(&[Pair], usize)>| {
        let source = vec![0u8; fr.sweep.cloud.len()];
        ctx.finish_cloud(f as u32, &fr.sweep.cloud, source, &fr.images, known)
    };
    // The dense cloud starts with the keyframe's points, paired with the same images:
    // it reuses the keyframe cloud's pairings and projects only the earlier sweeps.
    let (other_clouds, (key_cloud, (dense_cloud, dense_times))) = rayon::join(
        || {
            frames
                .par_iter()
                .enumerate()
                .filter(|(f, _)| *f != key_frame)
                .map(|(f, fr)| finish_frame(f, fr, None))
                .collect::<Vec<_>>()
        },
        || {
            let key_cloud = finish_frame(key_frame, key_inputs, None);
            let dense = ctx.finish_cloud(
                n_frames,
                &dense.cloud,
                dense_source,
                &key_inputs.images,
                Some((&key_cloud.0.pairings, key_inputs.sweep.cloud.len())),
            );
            (key_cloud, dense)
        },
    );
    let mut frame_clouds = other_clouds;
    frame_clouds.insert(key_frame, key_cloud);
    let mut times = dense.times;
    times.add(&dense_times);
    let offsets = ctx.config.frame_offsets();
    let frames = frames
        .into_iter()
        .zip(frame_clouds)
        .enumerate()
        .map(|(f, (inputs, (cloud, t)))| {
            times.add(&t);
            times.add(&inputs.times);
            times.add(&inputs.sweep.times);
            Frame {
                offset: offsets[f],
                sweep: key.frame_sweeps[f],
                lidar_stamp: inputs.sweep.cloud.stamp,
                images: inputs.images,
                num_superpixels: inputs.num_superpixels,
                cloud,
                dropped_non_finite: inputs.sweep.dropped,
            }
        })
        .collect();
    (frames, dense_cloud, times)
}
