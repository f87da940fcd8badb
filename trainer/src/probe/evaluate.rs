//! The pipeline-fed half of the probe: labelled clouds decoded by the pipeline's own
//! code, the protocols that train on them, and the backbone they score.

use crate::checkpoint;
use crate::config::TrainerConfig;
use crate::error::TrainerError;
use crate::model::SuperFlowModel;
use crate::probe::linear::{
    self as probe, ConfusionMatrix, KeyframeTime, LinearProbe, PointCounts, ProbeReport,
    ProbeTraining, SplitCounts,
};
use crate::probe_error::ProbeError;
use crate::rows::RowOps;
use crate::sweep_input::SweepInput;
use crate::unet::SparseUNet;
use crate::vit::VitConfig;
use burn::module::Module;
use burn::nn::loss::CrossEntropyLossConfig;
use burn::nn::{Initializer, Linear, LinearConfig};
use burn::optim::{AdamWConfig, GradientsParams};
use burn::tensor::{Device, Int, Tensor, TensorData};
use std::path::Path;
use superflow_pipeline::config::PipelineConfig;
use superflow_pipeline::drive::Dataset;
use superflow_pipeline::drive::labels::DriveLabels;
use superflow_pipeline::sample::SampleConfig;
use superflow_pipeline::sample::deskew::deskew;
use superflow_pipeline::source::ChunkCache;
use superflow_schemas::sensor::PointCloud;

/// One labelled sweep, ready for the backbone.
#[derive(Debug, Clone)]
pub struct ProbeCloud {
    /// Where and when.
    pub time: KeyframeTime,
    /// Sweep index in its drive's LiDAR stream.
    pub sweep: usize,
    /// Its voxels and maps.
    pub input: SweepInput,
    /// The training class of each point (the ignore index where unlabelled).
    pub labels: Vec<u16>,
}

/// What the labelled drives hold, beside the clouds.
#[derive(Debug, Clone)]
pub struct LabelledData {
    /// The labelled sweeps kept (one per keyframe interval).
    pub clouds: Vec<ProbeCloud>,
    /// Drives without labels (skipped).
    pub unlabelled_drives: usize,
    /// Training classes: `[labels] classes` when given, else one past the largest class
    /// seen.
    pub classes: usize,
    /// Class names (from `[labels] classes`; empty: numbered).
    pub names: Vec<String>,
    /// The label of unlabelled points.
    pub ignore: u16,
}

/// The labelled sweeps of `dataset` (`[labels]` of `config` says where labels are and how
/// raw ids map to classes), one per `interval_ns` per drive, each prepared as the
/// pipeline prepares a pretraining sweep (`config.sample`: de-skew, voxel grid, levels).
pub fn labelled_clouds(
    dataset: &Dataset,
    config: &PipelineConfig,
    interval_ns: i64,
) -> Result<LabelledData, TrainerError> {
    let recipe = &config.sample;
    let mut data = LabelledData {
        clouds: Vec::new(),
        unlabelled_drives: 0,
        classes: config.labels.classes.len(),
        names: config.labels.classes.clone(),
        ignore: 0,
    };
    let label_error = |drive: &superflow_pipeline::drive::Drive, error| ProbeError::Labels {
        drive: drive.file_list(),
        error,
    };
    let mut largest = None::<u16>;
    for (d, drive) in dataset.drives.iter().enumerate() {
        let (Some(lidar), Some(labels)) = (
            &drive.lidar,
            DriveLabels::open(drive, &config.labels).map_err(|e| label_error(drive, e))?,
        ) else {
            tracing::warn!(drive = %drive.file_list(), "no LiDAR labels (neither a label field nor a labels sidecar): skipped");
            data.unlabelled_drives += 1;
            continue;
        };
        tracing::info!(drive = %drive.file_list(), form = ?labels.form(), "labels");
        data.ignore = u16::from(labels.map().ignore_index());
        let mut cache = ChunkCache::new(4);
        let mut last: Option<i64> = None;
        for (s, frame) in lidar.sweeps.iter().enumerate() {
            let stamp = frame.stamp.nanos();
            if last.is_some_and(|t| stamp - t < interval_ns) {
                continue;
            }
            let sweep = labels
                .read(s, &mut cache)
                .map_err(|e| label_error(drive, e))?;
            let point_labels: Vec<u16> = sweep.labels.iter().map(|&l| u16::from(l)).collect();
            for &l in point_labels.iter().filter(|&&l| l != data.ignore) {
                largest = Some(largest.map_or(l, |m| m.max(l)));
            }
            let mut cloud = sweep.decoded.cloud;
            if cloud.is_empty() {
                continue;
            }
            if recipe.deskew && cloud.time_offset_secs.is_some() {
                let map = drive.map_frame.as_deref().unwrap_or_default();
                cloud = deskew(&cloud, &drive.tf, map).map_err(|error| ProbeError::Deskew {
                    drive: drive.file_list(),
                    topic: lidar.topic.clone(),
                    stamp: frame.stamp,
                    error,
                })?;
            }
            last = Some(stamp);
            let time = KeyframeTime {
                drive: d,
                stamp_ns: stamp,
            };
            data.clouds
                .push(prepare(cloud, point_labels, recipe, time, s));
        }
    }
    if data.classes == 0 {
        data.classes = largest.map_or(0, |l| usize::from(l) + 1);
    }
    Ok(data)
}

/// One labelled sweep, its voxels and maps made.
fn prepare(
    cloud: PointCloud,
    labels: Vec<u16>,
    recipe: &SampleConfig,
    time: KeyframeTime,
    sweep: usize,
) -> ProbeCloud {
    ProbeCloud {
        time,
        sweep,
        input: SweepInput::prepare(&cloud.xyz, &cloud.intensity, recipe),
        labels,
    }
}

/// How to probe.
#[derive(Debug, Clone, PartialEq)]
pub struct ProbeSettings {
    /// Classes of the labels (training ids `0..classes`).
    pub classes: usize,
    /// Label of unlabelled points.
    pub ignore: u16,
    /// Class names for the report.
    pub names: Vec<String>,
    /// Share of each drive's span (its end) that is validation.
    pub val_fraction: f64,
    /// Clouds from this index on are the validation set (drives of their own); `None`:
    /// split every drive by time.
    pub val_from: Option<usize>,
    /// Keyframes dropped before the validation part, nanoseconds.
    pub gap_ns: i64,
    /// Share of the training clouds used (few-label protocols).
    pub label_fraction: f64,
    /// Train the whole network instead of a linear classifier on frozen features.
    pub finetune: bool,
    /// Passes over the training data.
    pub epochs: usize,
    /// Learning rate (linear probe: AdamW on the classifier; fine-tuning: the network).
    pub lr: f64,
    /// Most training points the linear probe keeps (evenly strided).
    pub max_train_points: usize,
    /// Seed of the classifier and the shuffles.
    pub seed: u64,
}

/// Probes `unet` (an autodiff-device module, as trained) on `clouds`.
pub fn probe(
    unet: SparseUNet,
    clouds: &[ProbeCloud],
    settings: &ProbeSettings,
    device: &Device,
) -> Result<ProbeReport, TrainerError> {
    let split = match settings.val_from {
        // Validation drives of their own (the official val scenes).
        Some(first) => probe::Split {
            train: (0..first.min(clouds.len())).collect(),
            val: (first.min(clouds.len())..clouds.len()).collect(),
            dropped: Vec::new(),
        },
        None => {
            let times: Vec<KeyframeTime> = clouds.iter().map(|c| c.time).collect();
            probe::split_by_time(&times, settings.val_fraction, settings.gap_ns)
        }
    };
    let train = probe::label_fraction(&split.train, settings.label_fraction);
    if train.is_empty() || split.val.is_empty() {
        return Err(ProbeError::EmptySplit {
            clouds: clouds.len(),
            train: train.len(),
            val: split.val.len(),
        }
        .into());
    }
    let counts = SplitCounts {
        train: train.len(),
        val: split.val.len(),
        dropped: split.dropped.len() + split.train.len() - train.len(),
    };
    tracing::info!(
        train = counts.train,
        val = counts.val,
        dropped = counts.dropped,
        finetune = settings.finetune,
        "probing"
    );
    let mut matrix = ConfusionMatrix::new(settings.classes, settings.ignore);
    let mut points = PointCounts::default();
    let inner = device.clone().inner();
    if settings.finetune {
        let (unet, classifier) = finetune(unet, clouds, &train, settings, device, &mut points)?;
        let (unet, classifier) = (unet.valid(), classifier.valid());
        for &i in &split.val {
            let features = clouds[i].input.point_features(&unet, &inner);
            let logits = RowOps::of(&inner).linear(&classifier, features);
            let predicted = classes_of(logits.argmax(1));
            matrix.add(&clouds[i].labels, &predicted)?;
        }
    } else {
        let frozen = unet.valid();
        let dim = frozen.backbone_dim();
        let features_of = |c: &ProbeCloud| -> Vec<f32> {
            let f = c.input.point_features(&frozen, &inner).into_data();
            f.convert::<f32>().try_into_vec::<f32>().unwrap_or_default()
        };
        let (mut x, mut y) = (Vec::new(), Vec::new());
        for &i in &train {
            x.extend(features_of(&clouds[i]));
            y.extend_from_slice(&clouds[i].labels);
        }
        let (x, y) = stride_points(x, y, dim, settings.max_train_points);
        points.train = y.iter().filter(|&&l| l != settings.ignore).count() as u64;
        let training = ProbeTraining {
            epochs: settings.epochs,
            lr: settings.lr,
            seed: settings.seed,
            ..ProbeTraining::default()
        };
        let classifier = LinearProbe::train(
            &x,
            &y,
            dim,
            settings.classes,
            settings.ignore,
            &training,
            &inner,
        )?;
        for &i in &split.val {
            let predicted = classifier.predict(&features_of(&clouds[i]), dim, &inner);
            matrix.add(&clouds[i].labels, &predicted)?;
        }
    }
    points.val = matrix.total();
    Ok(ProbeReport::new(&matrix, &settings.names, points, counts))
}

/// Every `n / max`-th point of `(x, y)` when there are more than `max`.
fn stride_points(x: Vec<f32>, y: Vec<u16>, dim: usize, max: usize) -> (Vec<f32>, Vec<u16>) {
    if y.len() <= max || max == 0 {
        return (x, y);
    }
    let step = y.len().div_ceil(max);
    let keep: Vec<usize> = (0..y.len()).step_by(step).collect();
    let xs = keep
        .iter()
        .flat_map(|&i| x[i * dim..(i + 1) * dim].iter().copied())
        .collect();
    let ys = keep.iter().map(|&i| y[i]).collect();
    (xs, ys)
}

/// The class of each row of an argmax.
fn classes_of(argmax: Tensor<2, Int>) -> Vec<u16> {
    argmax
        .into_data()
        .convert::<i64>()
        .try_into_vec::<i64>()
        .unwrap_or_default()
        .into_iter()
        .map(|c| c as u16)
        .collect()
}

/// The backbone and a linear classifier trained together on the `train` clouds.
#[derive(Module, Debug)]
struct Segmenter {
    unet: SparseUNet,
    classifier: Linear,
}

fn finetune(
    unet: SparseUNet,
    clouds: &[ProbeCloud],
    train: &[usize],
    settings: &ProbeSettings,
    device: &Device,
    points: &mut PointCounts,
) -> Result<(SparseUNet, Linear), TrainerError> {
    let device = device.clone().autodiff();
    let classifier = LinearConfig::new(unet.backbone_dim(), settings.classes)
        .with_initializer(Initializer::Zeros)
        .init(&device);
    let mut model = Segmenter { unet, classifier };
    let mut optim = AdamWConfig::new().with_weight_decay(1e-4).init();
    let loss = CrossEntropyLossConfig::new().init(&device);
    points.train = train
        .iter()
        .map(|&i| {
            clouds[i]
                .labels
                .iter()
                .filter(|&&l| l != settings.ignore)
                .count() as u64
        })
        .sum();
    for epoch in 0..settings.epochs {
        let mut total = 0.0;
        for &i in train {
            let cloud = &clouds[i];
            let kept: Vec<usize> = (0..cloud.labels.len())
                .filter(|&p| cloud.labels[p] != settings.ignore)
                .collect();
            if kept.is_empty() {
                continue;
            }
            let (features, levels) = cloud.input.inputs(&device);
            let voxel: Vec<i64> = kept
                .iter()
                .map(|&p| i64::from(cloud.input.point_to_voxel[p]))
                .collect();
            let target: Vec<i64> = kept.iter().map(|&p| i64::from(cloud.labels[p])).collect();
            let n = kept.len();
            let index = Tensor::<1, Int>::from_data(TensorData::new(voxel, [n]), &device);
            let target = Tensor::<1, Int>::from_data(TensorData::new(target, [n]), &device);
            // Every labelled point of the cloud is a row: the gather's backward (a
            // scatter-add) and the classifier's bias gradient sum over all of them.
            let ops = RowOps::of(&device);
            let points = ops.gather(model.unet.backbone(features, &levels), &index);
            let logits = ops.linear(&model.classifier, points);
            let l = loss.forward(logits, target);
            total += l.clone().into_scalar::<f32>() as f64;
            let grads = GradientsParams::from_grads(l.backward(), &model);
            model = optim.step(settings.lr, model, grads);
        }
        tracing::info!(
            epoch = epoch + 1,
            loss = format_args!("{:.4}", total / train.len() as f64),
            "fine-tuning"
        );
    }
    Ok((model.unet, model.classifier))
}

/// The 3D network to probe and where it came from: `checkpoint` is a run's checkpoint
/// directory (its newest checkpoint), one `step-N` directory, or `random` (a fresh
/// network of `fresh`'s configuration and seed).
pub fn load_backbone(
    checkpoint: &str,
    fresh: &TrainerConfig,
    device: &Device,
) -> Result<(SparseUNet, String), TrainerError> {
    let device = device.clone().autodiff();
    let build = |config: &TrainerConfig| {
        SuperFlowModel::new(
            &config.model.unet_config(),
            VitConfig::preset(config.model.vit).dim,
            config.model.seed,
            &device,
        )
    };
    if checkpoint == "random" {
        let model = build(fresh);
        let what = format!("random {:?} (seed {})", fresh.model.unet, fresh.model.seed);
        return Ok((model.unet, what));
    }
    let path = Path::new(checkpoint);
    let ckpt = if path.join("state.json").is_file() {
        checkpoint::read(path)?
    } else {
        checkpoint::latest(path)?.ok_or_else(|| ProbeError::NoCheckpoint {
            checkpoint: checkpoint.to_string(),
        })?
    };
    let config: TrainerConfig =
        toml::from_str(&ckpt.state.config).map_err(|error| TrainerError::Toml {
            path: ckpt.dir.join("state.json"),
            error,
        })?;
    let model = build(&config).load_record(ckpt.model_record()?);
    let what = format!(
        "{} ({:?}, step {})",
        ckpt.dir.display(),
        config.model.unet,
        ckpt.state.step
    );
    Ok((model.unet, what))
}
