//! One camera image of a sample's frame: the image nearest the sweep, checked against
//! its calibration and decoded, resized (bilinear) and maybe flipped, with its
//! superpixels — the recording's class map (resized nearest, flipped alike) or SLIC on
//! the resized image.

use super::error::SampleError;
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
    /// The image of camera `camera_index` of the drive for the sweep at `lidar_stamp`
    /// (the one nearest the LiDAR's scan of it, see `timing.rs`), resized and maybe flipped
    /// (the draw of frame `frame_pos`, camera slot `slot`), with its superpixels; also
    /// the number of superpixel ids it uses and the time spent.
    pub(super) fn load_image(
        &self,
        camera_index: usize,
        lidar_stamp: Stamp,
        frame_pos: u32,
        slot: usize,
    ) -> Result<(SampleImage, u32, StageTimes), SampleError> {
        let cfg = self.config;
        let mut times = StageTimes::default();
        let camera = &self.drive.cameras[camera_index];
        let moments = &self.scan.offsets_nanos[camera_index];
        let mut raw = self.read_camera(camera, moments, lidar_stamp, &mut times)?;
        let t = Instant::now();
        let (rgb, flipped) = self.resize_and_flip(&raw.image, frame_pos, slot);
        buffers::give_back(std::mem::take(&mut raw.image.data));
        times.images += elapsed(t);

        let t_sp = Instant::now();
        let mut class_decode = 0;
        let (superpixels, count) = if self.class_superpixels {
            let (map, decode) = self.class_map(camera, &raw, flipped)?;
            class_decode = decode;
            times.decode += decode;
            (map, cfg.num_classes)
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
            if flipped {
                image_ops::flip_horizontal(&mut labels, cfg.image_width as usize, 1);
            }
            (labels, count)
        } else {
            let seg = slic(
                &rgb,
                cfg.image_width as usize,
                cfg.image_height as usize,
                &cfg.slic,
            );
            (seg.labels, seg.count)
        };
        times.superpixels += elapsed(t_sp).saturating_sub(class_decode);
        Ok((
            SampleImage {
                camera: camera.name.clone(),
                topic: camera.image_topic.clone(),
                stamp: raw.frame.stamp,
                scan_offset_nanos: raw.scan_offset_nanos,
                native_size: raw.native,
                flipped,
                rgb,
                superpixels,
                camera_from_lidar: raw.camera_from_lidar,
                calibration: raw.calibration,
            },
            count,
            times,
        ))
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

    /// `image` resized to the recipe's size and flipped (in the same pass) when the draw
    /// of frame `frame_pos`, slot `slot` says so; also whether it was.
    fn resize_and_flip(&self, image: &Image, frame_pos: u32, slot: usize) -> (Vec<u8>, bool) {
        let cfg = self.config;
        let flipped = SampleRng::new(
            cfg.seed,
            self.id.epoch,
            self.id.index,
            Purpose::ImageFlip {
                frame: frame_pos,
                slot: slot as u32,
            },
        )
        .bernoulli(cfg.image_flip_probability);
        (cfg.resized_rgb(image, flipped), flipped)
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
