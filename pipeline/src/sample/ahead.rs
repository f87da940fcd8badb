//! What a sample will read, known before it is built: the producer asks for the next
//! batches' messages while it builds this one ([`SampleBuilder::will_read`]), so that
//! drives in an object store have their chunks on the way (and local ones in the page
//! cache) by the time a sample needs them. Only the draws that pick what is read are
//! made here (the cameras); the sample's bytes never depend on it.

use super::builder::SampleBuilder;
use super::plan::camera_frame_for;
use super::rng::{Purpose, SampleRng};
use crate::drive::nearest;
use crate::source::MessageLoc;

impl SampleBuilder<'_> {
    /// Starts reading what the sample of plan keyframe `keyframe` with the draws of
    /// `(epoch, index)` will read: the sweeps of its temporal frames and dense cloud, and
    /// the chosen cameras' images and superpixel labels at each frame.
    pub fn will_read(&self, keyframe: usize, epoch: u64, index: u64) {
        let Some(key) = self.plan().keyframes.get(keyframe) else {
            return;
        };
        let drive = &self.dataset().drives[key.drive as usize];
        let Some(lidar) = &drive.lidar else {
            return;
        };
        let cfg = self.config();
        let m = drive.cameras.len();
        let k = (cfg.cameras as usize).min(m);
        let chosen = SampleRng::new(cfg.seed, epoch, index, Purpose::Cameras).choose(m, k);
        let scan = &self.plan().scans[key.drive as usize];
        let (class_maps, slic_sidecar) = self.superpixel_sources(key.drive as usize);
        let mut reads: Vec<Vec<MessageLoc>> = vec![Vec::new(); drive.files.len()];
        let mut add = |file: u32, loc: MessageLoc| {
            if let Some(locs) = reads.get_mut(file as usize) {
                locs.push(loc);
            }
        };
        let earlier = (1..=cfg.dense_sweeps).filter_map(|j| key.sweep.checked_sub(j));
        for sweep in key.frame_sweeps.iter().copied().chain(earlier) {
            let Some(frame) = lidar.sweeps.get(sweep as usize) else {
                continue;
            };
            add(frame.file, frame.loc);
            if !key.frame_sweeps.contains(&sweep) {
                continue; // a sweep of the dense cloud only: no images
            }
            for &c in &chosen {
                let camera = &drive.cameras[c];
                let moments = scan.offsets_nanos.get(c).map_or(&[][..], Vec::as_slice);
                let Some((image, _)) = camera_frame_for(camera, frame.stamp, moments) else {
                    continue;
                };
                add(image.file, image.loc);
                let labels = match (&camera.slic, class_maps, slic_sidecar) {
                    (_, true, _) => nearest(&camera.superpixels, image.stamp),
                    (Some(slic), false, true) => nearest(&slic.frames, image.stamp),
                    _ => None,
                };
                if let Some(labels) = labels {
                    add(labels.file, labels.loc);
                }
            }
        }
        for (file, locs) in drive.files.iter().zip(reads) {
            if !locs.is_empty() {
                file.will_read(locs);
            }
        }
    }
}
