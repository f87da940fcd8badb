//! The 2D network's view of a keyframe: each camera's image nearest the sweep, resized as
//! training resizes it, through the frozen ViT; its patch features coloured by their own
//! principal components (fitted over every image written), as images beside the cameras.

use super::pca::Pca;
use crate::vit::{DinoVit, imagenet_normalize};
use burn::tensor::{Device, Tensor, TensorData};
use nalgebra::Isometry3;
use superflow_pipeline::decode::image::Target;
use superflow_pipeline::drive::{Drive, ReadError, nearest};
use superflow_pipeline::sample::image_ops::resize_bilinear;
use superflow_pipeline::sample::project::camera_from_lidar;
use superflow_pipeline::source::ChunkCache;
use superflow_schemas::Stamp;
use superflow_schemas::sensor::CameraCalibration;

/// One camera's image of a keyframe, resized for the 2D network, with its patch features.
#[derive(Debug, Clone)]
pub struct CameraView {
    /// The camera.
    pub camera: String,
    /// Its stored (raw) calibration.
    pub calibration: CameraCalibration,
    /// The camera's pose in the LiDAR frame: the camera at its image's stamp, the LiDAR
    /// at the sweep's (as pairing uses them); `None` without a pose for one of them.
    pub lidar_from_camera: Option<Isometry3<f64>>,
    /// RGB, `height × width × 3`.
    pub rgb: Vec<u8>,
    /// Patch features, `rows × cols` rows of the ViT's width, row-major.
    pub patches: Vec<f32>,
}

/// The size images are resized to and the ViT's patch grid over it.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub struct Grid {
    /// Image width and height.
    pub size: (u32, u32),
    /// Patch side, pixels.
    pub patch: usize,
}

impl Grid {
    /// Patch rows and columns.
    pub fn cells(&self) -> (usize, usize) {
        (
            self.size.1 as usize / self.patch,
            self.size.0 as usize / self.patch,
        )
    }
}

/// Every camera's image nearest `stamp` (the sweep's), resized to `grid.size`, through
/// `vit` on `device`.
pub fn camera_views(
    drive: &Drive,
    lidar_frame: &str,
    stamp: Stamp,
    grid: Grid,
    vit: &DinoVit,
    device: &Device,
    cache: &mut ChunkCache,
) -> Result<Vec<CameraView>, ReadError> {
    let (width, height) = (grid.size.0 as usize, grid.size.1 as usize);
    let mut views = Vec::new();
    for camera in &drive.cameras {
        let (Some(frame), Some(calibration)) = (
            nearest(&camera.frames, stamp),
            camera.calibration_at(stamp).cloned(),
        ) else {
            continue;
        };
        let image = drive.read_image(camera, frame, Target::Rgb, cache)?;
        let rgb = resize_bilinear(
            &image.data,
            image.width as usize,
            image.height as usize,
            3,
            width,
            height,
        );
        let lidar_from_camera = drive.map_frame.as_deref().and_then(|map| {
            camera_from_lidar(
                &drive.tf,
                map,
                lidar_frame,
                stamp,
                &calibration.frame_id,
                frame.stamp,
            )
            .ok()
            .map(|c| c.inverse())
        });
        views.push(CameraView {
            camera: camera.name.clone(),
            calibration,
            lidar_from_camera,
            rgb,
            patches: Vec::new(),
        });
    }
    if views.is_empty() {
        return Ok(views);
    }
    let pixels: Vec<f32> = views
        .iter()
        .flat_map(|v| v.rgb.iter().map(|&b| f32::from(b)))
        .collect();
    let images = Tensor::<4>::from_data(
        TensorData::new(pixels, [views.len(), height, width, 3]),
        device,
    );
    let features = vit.forward(imagenet_normalize(images)); // [I, D, rows, cols]
    let [_, dim, rows, cols] = features.dims();
    let per_image: Vec<f32> = features
        .permute([0, 2, 3, 1]) // [I, rows, cols, D]
        .into_data()
        .convert::<f32>()
        .try_into_vec::<f32>()
        .unwrap_or_default();
    let stride = rows * cols * dim;
    for (i, view) in views.iter_mut().enumerate() {
        view.patches = per_image
            .get(i * stride..(i + 1) * stride)
            .unwrap_or_default()
            .to_vec();
    }
    Ok(views)
}

/// `view`'s patch features as an RGB image of `grid.size`: each patch's colour from
/// `pca`, over the patch's pixels.
pub fn patch_colours(view: &CameraView, pca: &Pca, grid: Grid) -> Vec<u8> {
    let (width, height) = (grid.size.0 as usize, grid.size.1 as usize);
    let (rows, cols) = grid.cells();
    let colours: Vec<[u8; 3]> = view
        .patches
        .chunks_exact(pca.dim)
        .map(|p| pca.colour(p))
        .collect();
    let mut rgb = vec![0u8; width * height * 3];
    for y in 0..height {
        let row = (y / grid.patch).min(rows.saturating_sub(1));
        for x in 0..width {
            let col = (x / grid.patch).min(cols.saturating_sub(1));
            if let Some(c) = colours.get(row * cols + col) {
                rgb[(y * width + x) * 3..][..3].copy_from_slice(c);
            }
        }
    }
    rgb
}

#[cfg(test)]
mod tests {
    use super::*;

    /// Two patches of opposite features: each colours its own block of pixels.
    #[test]
    fn each_patch_colours_its_own_pixels() {
        let grid = Grid {
            size: (4, 2),
            patch: 2,
        };
        let rows: Vec<f32> = (0..30)
            .flat_map(|i| {
                let s = if i % 2 == 0 { 1.0 } else { -1.0 };
                [s, 0.1 * i as f32, 0.05 * (i % 3) as f32]
            })
            .collect();
        let pca = Pca::fit(&rows, 3).unwrap();
        let view = CameraView {
            camera: "c".into(),
            calibration: CameraCalibration {
                stamp: Stamp::from_nanos(0),
                frame_id: "c".into(),
                width: 4,
                height: 2,
                k: nalgebra::Matrix3::identity(),
                distortion: superflow_schemas::sensor::Distortion::None,
            },
            lidar_from_camera: None,
            rgb: vec![0; 24],
            patches: vec![1.0, 0.0, 0.0, -1.0, 0.0, 0.0],
        };
        let rgb = patch_colours(&view, &pca, grid);
        let px = |x: usize, y: usize| &rgb[(y * 4 + x) * 3..][..3];
        assert_eq!(px(0, 0), px(1, 1));
        assert_eq!(px(2, 0), px(3, 1));
        assert_ne!(px(0, 0), px(2, 0));
    }
}
