//! One camera image of a sample's frame: the image nearest the sweep, checked against
//! its calibration and decoded, resized (bilinear) and maybe flipped, with its
//! superpixels — the recording's class map (resized nearest, flipped alike), a SLIC
//! sidecar's labels, or SLIC on the resized image.
//!
//! Reading ([`CameraRead`]: the decoded image and its class map or sidecar labels, as
//! stored) and finishing (resize, flip, superpixels) are apart: under the `blocks` order
//! the read is kept in the frame cache at the recipe's size, unflipped
//! ([`CameraRead::resized`]), and every sample that uses it flips its own copy — the
//! bytes of the one-pass resize-and-flip of a cold build.

use super::error::SampleError;
use super::frames::{FrameKey, copy_mirrored, widen_mirrored};
use super::image_ops;
use super::load::{SampleContext, elapsed, with_cache};
use super::plan::camera_frame_for;
use super::project::camera_from_lidar;
use super::rng::{Purpose, SampleRng};
use super::sidecar;
use super::slic::slic;
use super::types::{SampleImage, StageTimes};
use crate::decode::image::{ScaledImage, Target, buffers};
use crate::drive::{CameraStream, FrameRef, nearest};
use nalgebra::Isometry3;
use std::time::Instant;
use superflow_schemas::Stamp;
use superflow_schemas::sensor::{CameraCalibration, Image, PixelFormat};

/// Class maps are matched to images by stamp within this tolerance.
pub const CLASS_MAP_TOLERANCE_NANOS: i64 = 1_000_000;

/// A camera image decoded and checked against its calibration, before resizing, with
/// what the recording holds of its superpixels.
#[derive(Debug, Clone)]
pub(super) struct CameraRead {
    /// Where the image is in the drive.
    pub frame: FrameRef,
    /// Its stamp minus the moment the LiDAR scanned the camera's direction.
    pub scan_offset_nanos: i64,
    /// The calibration in force at its stamp.
    pub calibration: CameraCalibration,
    /// Its pixels.
    pub pixels: Pixels,
    /// Size of the stored image, which the calibration describes.
    pub native: (u32, u32),
    /// LiDAR (at the sweep stamp) → camera (at the image stamp).
    pub camera_from_lidar: Isometry3<f64>,
    /// Its superpixels as recorded.
    pub superpixels: RecordedSuperpixels,
}

/// An image's pixels.
#[derive(Debug, Clone)]
pub(super) enum Pixels {
    /// RGB8 as decoded (at a reduced scale when the recipe allows it).
    Decoded(Image),
    /// RGB8 resized to the recipe's size, not flipped.
    Resized(Vec<u8>),
}

/// The superpixels a recording holds for an image.
#[derive(Debug, Clone)]
pub(super) enum RecordedSuperpixels {
    /// A class map at the image's stored size, checked against the classes.
    ClassMap(Image),
    /// The class map resized (nearest) to the recipe's size, not flipped.
    ClassIds(Vec<u8>),
    /// SLIC labels from the sidecar at the recipe's size, and their count.
    Sidecar(Vec<u32>, u32),
    /// None: SLIC runs on the resized image.
    Computed,
}

impl CameraRead {
    /// Bytes held.
    pub fn bytes(&self) -> u64 {
        let pixels = match &self.pixels {
            Pixels::Decoded(image) => image.data.len(),
            Pixels::Resized(rgb) => rgb.len(),
        };
        let sp = match &self.superpixels {
            RecordedSuperpixels::ClassMap(map) => map.data.len(),
            RecordedSuperpixels::ClassIds(ids) => ids.len(),
            RecordedSuperpixels::Sidecar(labels, _) => labels.len() * 4,
            RecordedSuperpixels::Computed => 0,
        };
        (pixels + sp) as u64
    }

    /// This read at `config`'s size, not flipped (what the frame cache keeps: the
    /// recipe's size is usually far below the camera's); the decode buffers go back to
    /// their pool.
    fn resized(mut self, config: &super::recipe::SampleConfig) -> Self {
        let out = [config.image_width as usize, config.image_height as usize];
        if let Pixels::Decoded(image) = &mut self.pixels {
            let rgb = config.resized_rgb(image, false);
            buffers::give_back(std::mem::take(&mut image.data));
            self.pixels = Pixels::Resized(rgb);
        }
        if let RecordedSuperpixels::ClassMap(map) = &mut self.superpixels {
            let size = [map.width as usize, map.height as usize];
            let ids = image_ops::resize_nearest::<u8, u8>(&map.data, size, out, false);
            buffers::give_back(std::mem::take(&mut map.data));
            self.superpixels = RecordedSuperpixels::ClassIds(ids);
        }
        self
    }

    /// Gives the decode buffers back to their pool.
    fn give_back(self) {
        if let Pixels::Decoded(image) = self.pixels {
            buffers::give_back(image.data);
        }
        if let RecordedSuperpixels::ClassMap(map) = self.superpixels {
            buffers::give_back(map.data);
        }
    }
}

impl SampleContext<'_> {
    /// The image of camera `camera_index` of the drive for the sweep at index `sweep`
    /// (the one nearest the LiDAR's scan of it, see `timing.rs`), resized and maybe flipped
    /// (the draw of frame `frame_pos`, camera slot `slot`), with its superpixels; also
    /// the number of superpixel ids it uses and the time spent. With a frame cache the
    /// read is shared with the other samples of the frame.
    pub(super) fn load_image(
        &self,
        camera_index: usize,
        sweep: u32,
        frame_pos: u32,
        slot: usize,
    ) -> Result<(SampleImage, u32, StageTimes), SampleError> {
        let flipped = self.flip_draw(frame_pos, slot);
        match self.frames {
            None => {
                let (read, mut times) = self.read_camera_frame(camera_index, sweep)?;
                let (image, count) = self.finish_image(camera_index, &read, flipped, &mut times);
                read.give_back();
                Ok((image, count, times))
            }
            Some(cache) => {
                let key = (self.id.drive, sweep, camera_index as u32);
                let used = self.use_of(FrameKey::Image {
                    drive: key.0,
                    sweep,
                    camera: key.2,
                });
                let (read, mut times) = cache.image(key, used, || {
                    let (read, mut times) = self.read_camera_frame(camera_index, sweep)?;
                    let t = Instant::now();
                    let read = read.resized(self.config);
                    times.images += elapsed(t);
                    Ok::<_, SampleError>((read, times))
                })?;
                let (image, count) = self.finish_image(camera_index, &read, flipped, &mut times);
                Ok((image, count, times))
            }
        }
    }

    /// Whether image slot `slot` of frame `frame_pos` is flipped (the sample's draw).
    fn flip_draw(&self, frame_pos: u32, slot: usize) -> bool {
        SampleRng::new(
            self.config.seed,
            self.id.epoch,
            self.id.index,
            Purpose::ImageFlip {
                frame: frame_pos,
                slot: slot as u32,
            },
        )
        .bernoulli(self.config.image_flip_probability)
    }

    /// Reads camera `camera_index`'s image for sweep `sweep` with its recorded
    /// superpixels (class map checked, sidecar labels as stored).
    pub(super) fn read_camera_frame(
        &self,
        camera_index: usize,
        sweep: u32,
    ) -> Result<(CameraRead, StageTimes), SampleError> {
        let cfg = self.config;
        let mut times = StageTimes::default();
        let camera = &self.drive.cameras[camera_index];
        let moments = &self.scan.offsets_nanos[camera_index];
        let lidar_stamp = self
            .drive
            .lidar
            .as_ref()
            .map(|l| l.sweeps[sweep as usize].stamp)
            .unwrap_or_default();
        let mut read = self.read_camera(camera, moments, lidar_stamp, &mut times)?;
        let t_sp = Instant::now();
        let mut class_decode = 0;
        read.superpixels = if self.class_superpixels {
            let (map, decode) = self.class_map(camera, &read)?;
            class_decode = decode;
            times.decode += decode;
            RecordedSuperpixels::ClassMap(map)
        } else if let Some(stream) = camera.slic.as_ref().filter(|_| self.slic_sidecar) {
            let size = (cfg.image_width, cfg.image_height);
            let labels = with_cache(|cache| {
                sidecar::read_labels(self.drive, stream, read.frame.stamp, size, cache)
            });
            let (labels, count) = labels.map_err(|reason| SampleError::Superpixels {
                files: self.drive.file_list(),
                topic: stream.topic.clone(),
                stamp: read.frame.stamp,
                reason: Box::new(reason),
            })?;
            RecordedSuperpixels::Sidecar(labels, count)
        } else {
            RecordedSuperpixels::Computed
        };
        times.superpixels += elapsed(t_sp).saturating_sub(class_decode);
        Ok((read, times))
    }

    /// `read` at the recipe's size, flipped when `flipped` (resize and flip in one
    /// pass), with its superpixels alike; also their count. Adds the time to `times`.
    fn finish_image(
        &self,
        camera_index: usize,
        read: &CameraRead,
        flipped: bool,
        times: &mut StageTimes,
    ) -> (SampleImage, u32) {
        let cfg = self.config;
        let camera = &self.drive.cameras[camera_index];
        let (width, height) = (cfg.image_width as usize, cfg.image_height as usize);
        let t = Instant::now();
        let rgb = match &read.pixels {
            Pixels::Decoded(image) => cfg.resized_rgb(image, flipped),
            Pixels::Resized(rgb) => copy_mirrored::<u8, 3>(rgb, width, flipped),
        };
        times.images += elapsed(t);
        let t = Instant::now();
        let (superpixels, count) = match &read.superpixels {
            RecordedSuperpixels::ClassMap(map) => {
                // Resized, flipped and widened in one pass.
                let size = [map.width as usize, map.height as usize];
                let ids = image_ops::resize_nearest(&map.data, size, [width, height], flipped);
                (ids, cfg.num_classes)
            }
            RecordedSuperpixels::ClassIds(ids) => {
                (widen_mirrored(ids, width, flipped), cfg.num_classes)
            }
            RecordedSuperpixels::Sidecar(labels, count) => {
                (copy_mirrored::<u32, 1>(labels, width, flipped), *count)
            }
            RecordedSuperpixels::Computed => {
                let seg = slic(&rgb, width, height, &cfg.slic);
                (seg.labels, seg.count)
            }
        };
        times.superpixels += elapsed(t);
        let image = SampleImage {
            camera: camera.name.clone(),
            topic: camera.image_topic.clone(),
            stamp: read.frame.stamp,
            scan_offset_nanos: read.scan_offset_nanos,
            native_size: read.native,
            flipped,
            rgb,
            superpixels,
            camera_from_lidar: read.camera_from_lidar,
            calibration: read.calibration.clone(),
        };
        (image, count)
    }

    /// An image of `camera` that is wrong, naming the drive's files, topic and stamp.
    fn image_error(&self, camera: &CameraStream, stamp: Stamp, reason: String) -> SampleError {
        SampleError::Image {
            files: self.drive.file_list(),
            topic: camera.image_topic.clone(),
            stamp,
            reason,
        }
    }

    /// Finds (nearest `lidar_stamp + m` for one of its scan `moments`), decodes and
    /// checks the image of `camera` for the sweep at `lidar_stamp`, and looks up its
    /// `camera_from_lidar`. Adds the decoding time to `times`.
    fn read_camera(
        &self,
        camera: &CameraStream,
        moments: &[i64],
        lidar_stamp: Stamp,
        times: &mut StageTimes,
    ) -> Result<CameraRead, SampleError> {
        let drive = self.drive;
        let (frame, scan_offset_nanos) = camera_frame_for(camera, lidar_stamp, moments)
            .ok_or_else(|| {
                let reason = format!(
                    "{}: no image within half a period of the sweep",
                    camera.name
                );
                self.image_error(camera, lidar_stamp, reason)
            })?;
        let calibration = camera
            .calibration_at(frame.stamp)
            .ok_or_else(|| {
                let reason = format!("{}: no calibration", camera.name);
                self.image_error(camera, frame.stamp, reason)
            })?
            .clone();
        let scale = self.config.decode_scale();
        let t = Instant::now();
        let ScaledImage { image, native } =
            with_cache(|cache| drive.read_image_scaled(camera, frame, Target::Rgb, scale, cache))?;
        times.decode += elapsed(t);
        if native != (calibration.width, calibration.height) || image.format != PixelFormat::Rgb8 {
            let reason = format!(
                "{}: image is {}x{} but its calibration is for {}x{}",
                camera.name, native.0, native.1, calibration.width, calibration.height
            );
            return Err(self.image_error(camera, frame.stamp, reason));
        }
        let map = drive.map_frame.as_deref().unwrap_or_default();
        let lidar_frame = drive
            .lidar
            .as_ref()
            .map(|l| l.frame_id.as_str())
            .unwrap_or_default();
        let camera_from_lidar = camera_from_lidar(
            &drive.tf,
            map,
            lidar_frame,
            lidar_stamp,
            &camera.frame_id,
            frame.stamp,
        )
        .map_err(|e| self.transform_error(format!("{} from LiDAR", camera.name), frame.stamp, e))?;
        Ok(CameraRead {
            frame: *frame,
            scan_offset_nanos,
            calibration,
            pixels: Pixels::Decoded(image),
            native,
            camera_from_lidar,
            superpixels: RecordedSuperpixels::Computed,
        })
    }

    /// The class map of `raw` (within [`CLASS_MAP_TOLERANCE_NANOS`] of it), decoded and
    /// checked against the image's size and the classes. Also the time spent decoding
    /// it.
    fn class_map(
        &self,
        camera: &CameraStream,
        raw: &CameraRead,
    ) -> Result<(Image, u64), SampleError> {
        let cfg = self.config;
        let stamp = raw.frame.stamp;
        let topic = camera.superpixel_topic.clone().unwrap_or_default();
        let sp_error = |reason: String| SampleError::Superpixels {
            files: self.drive.file_list(),
            topic: topic.clone(),
            stamp,
            reason: Box::new(reason.into()),
        };
        let class_frame = nearest(&camera.superpixels, stamp)
            .filter(|f| f.stamp.nanos_since(stamp).abs() <= CLASS_MAP_TOLERANCE_NANOS)
            .ok_or_else(|| {
                sp_error(format!(
                    "no class map within 1 ms of image {}",
                    camera.image_topic
                ))
            })?;
        let t = Instant::now();
        let classes = with_cache(|cache| {
            self.drive
                .read_image(camera, class_frame, Target::Mono, cache)
        })?;
        let decode = elapsed(t);
        if (classes.width, classes.height) != raw.native {
            return Err(sp_error(format!(
                "class map is {}x{}, its image {}x{}",
                classes.width, classes.height, raw.native.0, raw.native.1
            )));
        }
        // The largest id (a reduction in vector lanes) is checked; the first offending
        // one is looked for only when there is one.
        let largest = classes.data.iter().copied().fold(0u8, u8::max);
        if u32::from(largest) >= cfg.num_classes {
            return Err(sp_error(format!(
                "class id {largest} is outside the configured {} classes",
                cfg.num_classes
            )));
        }
        Ok((classes, decode))
    }
}
