//! One camera image of a sample's frame: the image nearest the sweep, checked against
//! its calibration and decoded, resized (bilinear) and maybe flipped, with its
//! superpixels — the recording's class map (resized nearest, flipped alike) or SLIC on
//! the resized image.

use super::error::SampleError;
use super::frames::{PreparedImage, copy_mirrored};
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

/// A camera image decoded and checked against its calibration, before resizing.
struct RawImage {
    /// Where the image is in the drive.
    frame: FrameRef,
    /// Its stamp minus the moment the LiDAR scanned the camera's direction.
    scan_offset_nanos: i64,
    /// The calibration in force at its stamp.
    calibration: CameraCalibration,
    /// The decoded RGB8 image (at a reduced scale when the recipe allows it).
    image: Image,
    /// Size of the stored image, which the calibration describes.
    native: (u32, u32),
    /// LiDAR (at the sweep stamp) → camera (at the image stamp).
    camera_from_lidar: Isometry3<f64>,
}

impl SampleContext<'_> {
    /// The image of camera `camera_index` of the drive for the sweep at index `sweep`
    /// (the one nearest the LiDAR's scan of it, see `timing.rs`), resized and maybe flipped
    /// (the draw of frame `frame_pos`, camera slot `slot`), with its superpixels; also
    /// the number of superpixel ids it uses and the time spent. With a frame cache the
    /// image is prepared unflipped once and flipped on the way out (the same bytes).
    pub(super) fn load_image(
        &self,
        camera_index: usize,
        sweep: u32,
        frame_pos: u32,
        slot: usize,
    ) -> Result<(SampleImage, u32, StageTimes), SampleError> {
        let cfg = self.config;
        let camera = &self.drive.cameras[camera_index];
        let flipped = self.flip_draw(frame_pos, slot);
        let (prepared, mut times) = match self.frames {
            None => self.prepare_image(camera_index, sweep, flipped)?,
            Some(cache) => {
                let key = (self.id.drive, sweep, camera_index as u32);
                let (held, times) = cache.image(key, self.position, || {
                    self.prepare_image(camera_index, sweep, false)
                })?;
                let width = cfg.image_width as usize;
                let image = PreparedImage {
                    rgb: copy_mirrored(&held.rgb, width, 3, flipped),
                    labels: held
                        .labels
                        .as_ref()
                        .map(|(l, count)| (copy_mirrored(l, width, 1, flipped), *count)),
                    mirrored: flipped,
                    calibration: held.calibration.clone(),
                    ..*held
                };
                (image, times)
            }
        };
        debug_assert_eq!(prepared.mirrored, flipped);
        let (superpixels, count) = match prepared.labels {
            Some(labels) => labels,
            None => {
                let t = Instant::now();
                let seg = slic(
                    &prepared.rgb,
                    cfg.image_width as usize,
                    cfg.image_height as usize,
                    &cfg.slic,
                );
                times.superpixels += elapsed(t);
                (seg.labels, seg.count)
            }
        };
        Ok((
            SampleImage {
                camera: camera.name.clone(),
                topic: camera.image_topic.clone(),
                stamp: prepared.frame.stamp,
                scan_offset_nanos: prepared.scan_offset_nanos,
                native_size: prepared.native,
                flipped,
                rgb: prepared.rgb,
                superpixels,
                camera_from_lidar: prepared.camera_from_lidar,
                calibration: prepared.calibration,
            },
            count,
            times,
        ))
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

    /// The image of camera `camera_index` for sweep `sweep`: read, checked, resized and
    /// mirrored when `mirrored` (in one pass), with the superpixels the recording holds
    /// for it (class map or SLIC sidecar, mirrored alike); computed SLIC is left to the
    /// caller.
    fn prepare_image(
        &self,
        camera_index: usize,
        sweep: u32,
        mirrored: bool,
    ) -> Result<(PreparedImage, StageTimes), SampleError> {
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
        let mut raw = self.read_camera(camera, moments, lidar_stamp, &mut times)?;
        let t = Instant::now();
        let rgb = cfg.resized_rgb(&raw.image, mirrored);
        buffers::give_back(std::mem::take(&mut raw.image.data));
        times.images += elapsed(t);

        let t_sp = Instant::now();
        let mut class_decode = 0;
        let labels = if self.class_superpixels {
            let (map, decode) = self.class_map(camera, &raw, mirrored)?;
            class_decode = decode;
            times.decode += decode;
            Some((map, cfg.num_classes))
        } else if let Some(stream) = camera.slic.as_ref().filter(|_| self.slic_sidecar) {
            let size = (cfg.image_width, cfg.image_height);
            let read = with_cache(|cache| {
                sidecar::read_labels(self.drive, stream, raw.frame.stamp, size, cache)
            });
            let (mut labels, count) = read.map_err(|reason| SampleError::Superpixels {
                files: self.drive.file_list(),
                topic: stream.topic.clone(),
                stamp: raw.frame.stamp,
                reason: Box::new(reason),
            })?;
            if mirrored {
                image_ops::flip_horizontal(&mut labels, cfg.image_width as usize, 1);
            }
            Some((labels, count))
        } else {
            None
        };
        times.superpixels += elapsed(t_sp).saturating_sub(class_decode);
        let image = PreparedImage {
            frame: raw.frame,
            scan_offset_nanos: raw.scan_offset_nanos,
            calibration: raw.calibration,
            native: raw.native,
            camera_from_lidar: raw.camera_from_lidar,
            rgb,
            labels,
            mirrored,
        };
        Ok((image, times))
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
    ) -> Result<RawImage, SampleError> {
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
        Ok(RawImage {
            frame: *frame,
            scan_offset_nanos,
            calibration,
            image,
            native,
            camera_from_lidar,
        })
    }

    /// The class map of `raw` (within [`CLASS_MAP_TOLERANCE_NANOS`] of it) as
    /// superpixels: checked, resized (nearest) and flipped like the image. Also the
    /// time spent decoding it.
    fn class_map(
        &self,
        camera: &CameraStream,
        raw: &RawImage,
        flipped: bool,
    ) -> Result<(Vec<u32>, u64), SampleError> {
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
        // Resized, flipped and widened in one pass.
        let out_size = [cfg.image_width as usize, cfg.image_height as usize];
        let size = [classes.width as usize, classes.height as usize];
        let small = image_ops::resize_nearest(&classes.data, size, out_size, flipped);
        buffers::give_back(classes.data);
        Ok((small, decode))
    }
}
