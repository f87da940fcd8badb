//! `superflow-trainer features`: a backbone's per-point features over a drive's keyframe
//! sweeps, written as Foxglove point clouds coloured by the features' top three principal
//! components (fitted once over every sweep written), and optionally by the cosine
//! similarity to one query point; a bird's-eye PNG of the first sweep beside it; with a
//! 2D network, each camera's image and its ViT patch features in their own principal
//! components' colours.

use super::images::{CameraView, Grid, camera_views, patch_colours};
use super::pca::{Pca, PcaError, cosine_similarity};
use crate::sweep_input::SweepInput;
use crate::unet::SparseUNet;
use crate::vit::DinoVit;
use burn::tensor::Device;
use std::path::{Path, PathBuf};
use superflow_pipeline::config::PipelineConfig;
use superflow_pipeline::drive::{Dataset, ReadError, TfError};
use superflow_pipeline::sample::deskew::deskew;
use superflow_pipeline::sample::export::ramp;
use superflow_pipeline::source::ChunkCache;
use superflow_pipeline::view::{
    Column, ViewError, ViewWriter, camera_topic, frame_transform, resized_calibration,
};
use superflow_schemas::Stamp;

/// What to write.
#[derive(Debug, Clone, PartialEq)]
pub struct FeatureSettings {
    /// The MCAP file.
    pub out: PathBuf,
    /// A point of the first sweep, in its LiDAR frame: the nearest point's feature is
    /// the query of the similarity clouds.
    pub query: Option<[f32; 3]>,
    /// One sweep per this many nanoseconds per drive (the keyframes).
    pub interval_ns: i64,
    /// A bird's-eye PNG of the first sweep in its principal-component colours.
    pub bev: Option<PathBuf>,
    /// What the backbone is, for the file's metadata.
    pub backbone: String,
}

/// The 2D network and the image size it sees (the recipe's `image_width × image_height`).
#[derive(Debug)]
pub struct ImageSettings<'a> {
    /// The frozen ViT.
    pub vit: &'a DinoVit,
    /// Images are resized to this, a multiple of the ViT's patch.
    pub size: (u32, u32),
}

/// What was written.
#[derive(Debug, Clone, PartialEq)]
pub struct FeatureReport {
    /// Sweeps written.
    pub sweeps: usize,
    /// Points written.
    pub points: usize,
    /// Feature width.
    pub dim: usize,
    /// Messages in the file.
    pub messages: u64,
    /// The share of the features' variance along each of the three components.
    pub explained: [f64; 3],
    /// The query's nearest point in the first sweep: its index and its distance to the
    /// query, metres.
    pub query_point: Option<(usize, f32)>,
    /// Camera images written with their ViT features.
    pub images: usize,
}

/// Why the features could not be written.
#[derive(Debug, thiserror::Error)]
pub enum FeaturesError {
    /// A sweep could not be read.
    #[error(transparent)]
    Read(#[from] ReadError),
    /// A sweep could not be de-skewed (no pose at its points' times).
    #[error("{drive}: {topic} at {stamp}: de-skew: {source}")]
    Deskew {
        /// The drive's files.
        drive: String,
        /// The LiDAR topic.
        topic: String,
        /// The sweep's stamp.
        stamp: Stamp,
        /// What failed (boxed: the error stays small).
        #[source]
        source: Box<TfError>,
    },
    /// The file could not be written.
    #[error(transparent)]
    View(#[from] ViewError),
    /// The principal components could not be fitted.
    #[error("the features' principal components: {0}")]
    Pca(#[from] PcaError),
    /// The backbone gave features of another shape than one row per point.
    #[error("the sweep at {stamp}: {got} feature values for {points} points of width {dim}")]
    Shape {
        /// The sweep's stamp.
        stamp: Stamp,
        /// Values read back.
        got: usize,
        /// Points of the sweep.
        points: usize,
        /// Feature width.
        dim: usize,
    },
    /// The image size is not a multiple of the ViT's patch.
    #[error("images of {width}×{height} are not a whole number of the ViT's {patch}-pixel patches")]
    PatchGrid {
        /// Image width.
        width: u32,
        /// Image height.
        height: u32,
        /// The patch side.
        patch: usize,
    },
    /// No drive has a LiDAR sweep.
    #[error("no LiDAR sweep in the drives")]
    NoSweeps,
    /// The bird's-eye picture could not be written.
    #[error("{path}: {source}")]
    Picture {
        /// The file.
        path: PathBuf,
        /// What failed.
        #[source]
        source: std::io::Error,
    },
}

/// One sweep and its features.
struct SweepFeatures {
    /// The cameras' images of the keyframe, with the ViT's patch features.
    cameras: Vec<CameraView>,
    stamp: Stamp,
    frame_id: String,
    /// The map frame and the LiDAR's pose in it at the sweep's stamp, when known.
    pose: Option<(String, nalgebra::Isometry3<f64>)>,
    xyz: Vec<[f32; 3]>,
    features: Vec<f32>,
}

/// The keyframe sweeps of `dataset` through `unet`, written to `settings.out`.
pub fn write_features(
    dataset: &Dataset,
    config: &PipelineConfig,
    unet: &SparseUNet,
    images: Option<&ImageSettings<'_>>,
    device: &Device,
    settings: &FeatureSettings,
) -> Result<FeatureReport, FeaturesError> {
    let dim = unet.backbone_dim();
    let grid = match images {
        Some(i) => {
            let patch = i.vit.config().patch;
            let (w, h) = i.size;
            if patch == 0
                || !(w as usize).is_multiple_of(patch)
                || !(h as usize).is_multiple_of(patch)
            {
                return Err(FeaturesError::PatchGrid {
                    width: w,
                    height: h,
                    patch,
                });
            }
            Some((
                i.vit,
                Grid {
                    size: i.size,
                    patch,
                },
            ))
        }
        None => None,
    };
    let sweeps = sweep_features(dataset, config, unet, grid, device, settings.interval_ns)?;
    let Some(first) = sweeps.first() else {
        return Err(FeaturesError::NoSweeps);
    };
    let all: Vec<f32> = sweeps
        .iter()
        .flat_map(|s| s.features.iter().copied())
        .collect();
    let pca = Pca::fit(&all, dim)?;
    drop(all);
    let image_pca = match grid {
        Some((vit, _)) if sweeps.iter().any(|s| !s.cameras.is_empty()) => {
            let patches: Vec<f32> = sweeps
                .iter()
                .flat_map(|s| s.cameras.iter().flat_map(|c| c.patches.iter().copied()))
                .collect();
            Some(Pca::fit(&patches, vit.config().dim)?)
        }
        _ => None,
    };
    let query = settings.query.map(|q| {
        let (i, d2) = first
            .xyz
            .iter()
            .map(|p| (0..3).map(|k| (p[k] - q[k]).powi(2)).sum::<f32>())
            .enumerate()
            .min_by(|a, b| a.1.total_cmp(&b.1))
            .unwrap_or((0, f32::INFINITY));
        (
            i,
            d2.sqrt(),
            first.features[i * dim..(i + 1) * dim].to_vec(),
        )
    });
    let mut out = ViewWriter::create(
        &settings.out,
        &format!("superflow-trainer/{}", env!("CARGO_PKG_VERSION")),
    )?;
    let mut points = 0;
    let mut images_written = 0;
    for (s, sweep) in sweeps.iter().enumerate() {
        let projected: Vec<[f32; 3]> = sweep
            .features
            .chunks_exact(dim)
            .map(|r| pca.project(r))
            .collect();
        let colours: Vec<[u8; 3]> = projected.iter().map(|p| pca.colour_of(*p)).collect();
        let channel = |k: usize| -> Vec<u8> { colours.iter().map(|c| c[k]).collect() };
        let component = |k: usize| -> Vec<f32> { projected.iter().map(|c| c[k]).collect() };
        let (red, green, blue) = (channel(0), channel(1), channel(2));
        let alpha = vec![255u8; sweep.xyz.len()];
        let (pc1, pc2, pc3) = (component(0), component(1), component(2));
        let mut columns = vec![
            Column::U8("red", &red),
            Column::U8("green", &green),
            Column::U8("blue", &blue),
            Column::U8("alpha", &alpha),
            Column::F32("pc1", &pc1),
            Column::F32("pc2", &pc2),
            Column::F32("pc3", &pc3),
        ];
        let similarity = query
            .as_ref()
            .map(|(_, _, q)| cosine_similarity(&sweep.features, dim, q));
        if let Some(sim) = &similarity {
            columns.push(Column::F32("similarity", sim));
        }
        out.write_cloud(
            "/superflow/features",
            sweep.stamp,
            &sweep.frame_id,
            &sweep.xyz,
            &columns,
        )?;
        if let Some(sim) = &similarity {
            let heat: Vec<[u8; 3]> = sim.iter().map(|v| ramp((v + 1.0) / 2.0)).collect();
            let channel = |k: usize| -> Vec<u8> { heat.iter().map(|c| c[k]).collect() };
            let (red, green, blue) = (channel(0), channel(1), channel(2));
            out.write_cloud(
                "/superflow/similarity",
                sweep.stamp,
                &sweep.frame_id,
                &sweep.xyz,
                &[
                    Column::U8("red", &red),
                    Column::U8("green", &green),
                    Column::U8("blue", &blue),
                    Column::U8("alpha", &alpha),
                    Column::F32("similarity", sim),
                ],
            )?;
        }
        let ts = out.timestamp(sweep.stamp)?;
        let mut transforms = Vec::new();
        if let Some((map, pose)) = &sweep.pose {
            transforms.push(frame_transform(ts, map, &sweep.frame_id, pose));
        }
        if let (Some((_, grid)), Some(image_pca)) = (grid, &image_pca) {
            for view in &sweep.cameras {
                let frame_id = view.calibration.frame_id.as_str();
                if let Some(pose) = &view.lidar_from_camera {
                    transforms.push(frame_transform(ts, &sweep.frame_id, frame_id, pose));
                }
                write_camera(&mut out, sweep.stamp, ts, view, image_pca, grid)?;
                images_written += 1;
            }
        }
        if !transforms.is_empty() {
            out.write(
                "/tf",
                sweep.stamp,
                &foxglove::messages::FrameTransforms { transforms },
            )?;
        }
        if s == 0
            && let Some(path) = &settings.bev
        {
            bird_eye_png(path, &sweep.xyz, &colours)?;
        }
        points += sweep.xyz.len();
    }
    let explained = pca
        .variances
        .map(|v| v / pca.total_variance.max(f64::MIN_POSITIVE));
    let meta = serde_json::json!({
        "backbone": settings.backbone,
        "dim": dim,
        "pca": "covariance of up to 200 000 evenly strided points, top 3 eigenvectors; colours: 1st–99th percentile → 0–255",
        "explained_variance": explained,
        "query": settings.query,
    });
    out.metadata(
        "superflow.features",
        std::collections::BTreeMap::from([("settings".to_string(), meta.to_string())]),
    )?;
    let messages = out.finish()?;
    Ok(FeatureReport {
        sweeps: sweeps.len(),
        points,
        dim,
        messages,
        explained,
        query_point: query.map(|(i, d, _)| (i, d)),
        images: images_written,
    })
}

/// One camera of a keyframe: the image as the ViT saw it, its patch features' colours,
/// and the calibration of that image size, on `/superflow/<camera>/…`.
fn write_camera(
    out: &mut ViewWriter,
    stamp: Stamp,
    ts: foxglove::messages::Timestamp,
    view: &CameraView,
    pca: &Pca,
    grid: Grid,
) -> Result<(), FeaturesError> {
    let (width, height) = grid.size;
    let camera = view.camera.as_str();
    let frame_id = view.calibration.frame_id.as_str();
    out.write_png(camera, "image", frame_id, stamp, grid.size, &view.rgb)?;
    let colours = patch_colours(view, pca, grid);
    out.write_png(camera, "vit_pca", frame_id, stamp, grid.size, &colours)?;
    out.write(
        &camera_topic(camera, "calibration"),
        stamp,
        &resized_calibration(ts, &view.calibration, false, width, height),
    )?;
    Ok(())
}

/// Every drive's keyframe sweeps (one per `interval_ns`), decoded and de-skewed as the
/// pipeline prepares a pretraining sweep, through the frozen backbone.
fn sweep_features(
    dataset: &Dataset,
    config: &PipelineConfig,
    unet: &SparseUNet,
    images: Option<(&DinoVit, Grid)>,
    device: &Device,
    interval_ns: i64,
) -> Result<Vec<SweepFeatures>, FeaturesError> {
    let recipe = &config.sample;
    let mut out = Vec::new();
    for drive in &dataset.drives {
        let Some(lidar) = &drive.lidar else {
            tracing::warn!(drive = %drive.file_list(), "no LiDAR: skipped");
            continue;
        };
        let map = drive.map_frame.as_deref().unwrap_or_default();
        let mut cache = ChunkCache::new(4);
        let mut last: Option<i64> = None;
        for frame in &lidar.sweeps {
            let stamp = frame.stamp.nanos();
            if last.is_some_and(|t| stamp - t < interval_ns) {
                continue;
            }
            last = Some(stamp);
            let mut cloud = drive.read_sweep(frame, &mut cache)?.cloud;
            if cloud.is_empty() {
                continue;
            }
            if recipe.deskew && cloud.time_offset_secs.is_some() {
                cloud = deskew(&cloud, &drive.tf, map).map_err(|source| FeaturesError::Deskew {
                    drive: drive.file_list(),
                    topic: lidar.topic.clone(),
                    stamp: frame.stamp,
                    source: Box::new(source),
                })?;
            }
            let input = SweepInput::prepare(&cloud.xyz, &cloud.intensity, recipe);
            let features = input
                .point_features(unet, device)
                .into_data()
                .convert::<f32>()
                .try_into_vec::<f32>()
                .unwrap_or_default();
            if features.len() != cloud.xyz.len() * unet.backbone_dim() {
                return Err(FeaturesError::Shape {
                    stamp: frame.stamp,
                    got: features.len(),
                    points: cloud.xyz.len(),
                    dim: unet.backbone_dim(),
                });
            }
            let pose = drive.map_frame.as_ref().and_then(|m| {
                drive
                    .tf
                    .lookup(m, &lidar.frame_id, frame.stamp)
                    .ok()
                    .map(|p| (m.clone(), p))
            });
            let cameras = match images {
                Some((vit, grid)) => camera_views(
                    drive,
                    &lidar.frame_id,
                    frame.stamp,
                    grid,
                    vit,
                    device,
                    &mut cache,
                )?,
                None => Vec::new(),
            };
            out.push(SweepFeatures {
                cameras,
                stamp: frame.stamp,
                frame_id: lidar.frame_id.clone(),
                pose,
                xyz: cloud.xyz,
                features,
            });
        }
    }
    Ok(out)
}

/// Pixels of the bird's-eye picture a side, and metres it spans.
const BEV_PIXELS: usize = 800;
const BEV_METRES: f32 = 80.0;

/// `xyz` seen from above (x up, y left, the LiDAR at the centre), each point a 2×2 dot
/// of its colour, higher points over lower ones, on black.
fn bird_eye_png(path: &Path, xyz: &[[f32; 3]], colours: &[[u8; 3]]) -> Result<(), FeaturesError> {
    let n = BEV_PIXELS;
    let scale = n as f32 / BEV_METRES;
    let mut order: Vec<usize> = (0..xyz.len()).collect();
    order.sort_by(|&a, &b| xyz[a][2].total_cmp(&xyz[b][2]));
    let mut rgb = vec![0u8; n * n * 3];
    for i in order {
        let [x, y, _] = xyz[i];
        let (row, col) = (n as f32 / 2.0 - x * scale, n as f32 / 2.0 - y * scale);
        if !(0.0..(n - 1) as f32).contains(&row) || !(0.0..(n - 1) as f32).contains(&col) {
            continue;
        }
        let (row, col) = (row as usize, col as usize);
        for (r, c) in [
            (row, col),
            (row + 1, col),
            (row, col + 1),
            (row + 1, col + 1),
        ] {
            rgb[(r * n + c) * 3..][..3].copy_from_slice(&colours[i]);
        }
    }
    let io = |source: std::io::Error| FeaturesError::Picture {
        path: path.to_path_buf(),
        source,
    };
    let file = std::fs::File::create(path).map_err(io)?;
    let mut encoder = png::Encoder::new(std::io::BufWriter::new(file), n as u32, n as u32);
    encoder.set_color(png::ColorType::Rgb);
    encoder.set_depth(png::BitDepth::Eight);
    encoder
        .write_header()
        .and_then(|mut w| w.write_image_data(&rgb).and_then(|()| w.finish()))
        .map_err(|e| io(std::io::Error::other(e)))
}
