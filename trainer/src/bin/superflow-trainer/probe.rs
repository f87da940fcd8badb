//! `superflow-trainer probe`: scores a 3D backbone on labelled drives; `features`:
//! writes what it learned for Foxglove.

use crate::cli::{Args, FeaturesArgs, ProbeArgs};
use anyhow::Context as _;
use superflow_trainer::device;
use superflow_trainer::probe as evaluate;

/// `superflow-trainer probe`.
pub fn probe(args: &Args, p: &ProbeArgs) -> anyhow::Result<Option<i32>> {
    let pipeline = match &p.pipeline_config {
        Some(path) => superflow_pipeline::config::PipelineConfig::load(path)?,
        None => superflow_pipeline::config::PipelineConfig::default(),
    };
    let device = device::select(args.backend, args.device_index)?;
    let (unet, what) = evaluate::load_backbone(&p.checkpoint, &args.config()?, &device)?;
    tracing::info!(backbone = %what, "probing");
    let dataset = superflow_pipeline::drive::Dataset::open(&p.mcap, &pipeline.ingest)
        .context("opening the drives")?;
    let interval = (p.keyframe_interval_secs * 1e9) as i64;
    let mut data = evaluate::labelled_clouds(&dataset, &pipeline, interval)?;
    let val_from = if p.val_mcap.is_empty() {
        None
    } else {
        let val = superflow_pipeline::drive::Dataset::open(&p.val_mcap, &pipeline.ingest)
            .context("opening the validation drives")?;
        let val = evaluate::labelled_clouds(&val, &pipeline, interval)?;
        let first = data.clouds.len();
        let drives = dataset.drives.len();
        data.clouds.extend(val.clouds.into_iter().map(|mut c| {
            c.time.drive += drives;
            c
        }));
        data.classes = data.classes.max(val.classes);
        Some(first)
    };
    tracing::info!(
        clouds = data.clouds.len(),
        classes = data.classes,
        unlabelled_drives = data.unlabelled_drives,
        "labelled sweeps"
    );
    let settings = evaluate::ProbeSettings {
        classes: data.classes,
        ignore: data.ignore,
        names: data.names,
        val_fraction: p.val_fraction,
        val_from,
        gap_ns: (p.gap_secs * 1e9) as i64,
        label_fraction: p.label_fraction,
        finetune: p.finetune,
        epochs: p.epochs.unwrap_or(if p.finetune { 10 } else { 20 }),
        lr: p.probe_lr.unwrap_or(if p.finetune { 1e-3 } else { 1e-2 }),
        max_train_points: p.max_train_points,
        seed: args.seed.unwrap_or(0),
    };
    let report = evaluate::probe(unet, &data.clouds, &settings, &device);
    device::settle(&device);
    let report = report?;
    if p.json {
        let mut value = serde_json::to_value(&report)?;
        value["backbone"] = serde_json::Value::String(what);
        value["protocol"] =
            serde_json::Value::String(if p.finetune { "finetune" } else { "linear" }.into());
        value["label_fraction"] = serde_json::json!(p.label_fraction);
        println!("{}", serde_json::to_string(&value)?);
    } else {
        println!("backbone: {what}");
        println!(
            "mIoU {:.2} % (accuracy {:.2} %) on {} validation points of {} sweeps; trained on {} points of {} sweeps",
            report.miou * 100.0,
            report.accuracy * 100.0,
            report.points.val,
            report.split.val,
            report.points.train,
            report.split.train
        );
        for (name, iou) in &report.per_class {
            println!("  {name:<24} {:6.2} %", iou * 100.0);
        }
    }
    Ok(None)
}

/// `superflow-trainer features`.
pub fn features(args: &Args, f: &FeaturesArgs) -> anyhow::Result<Option<i32>> {
    use superflow_trainer::features::{FeatureSettings, ImageSettings, write_features};
    let pipeline = match &f.pipeline_config {
        Some(path) => superflow_pipeline::config::PipelineConfig::load(path)?,
        None => superflow_pipeline::config::PipelineConfig::default(),
    };
    let device = device::select(args.backend, args.device_index)?;
    let config = args.config()?;
    let (unet, what) = evaluate::load_backbone(&f.checkpoint, &config, &device)?;
    tracing::info!(backbone = %what, "features");
    let vit = if f.images {
        let model = &config.model;
        if model.image_weights.is_none() {
            tracing::warn!(preset = ?model.vit, "2D network: RANDOM ViT weights (no --image-weights): its image features mean nothing");
        }
        Some(superflow_trainer::vit::DinoVit::frozen(
            model.image_weights.as_deref(),
            model.vit,
            model.seed,
            &device,
        )?)
    } else {
        None
    };
    let images = vit.as_ref().map(|vit| ImageSettings {
        vit,
        size: (pipeline.sample.image_width, pipeline.sample.image_height),
    });
    let dataset = superflow_pipeline::drive::Dataset::open(&f.mcap, &pipeline.ingest)
        .context("opening the drives")?;
    let settings = FeatureSettings {
        out: f.out.clone(),
        query: f.query,
        interval_ns: (f.keyframe_interval_secs * 1e9) as i64,
        bev: f.bev.clone(),
        backbone: what.clone(),
    };
    let report = write_features(
        &dataset,
        &pipeline,
        &unet,
        images.as_ref(),
        &device,
        &settings,
    );
    device::settle(&device);
    let report = report?;
    println!("backbone: {what}");
    println!(
        "wrote {}: {} sweeps, {} points, features of width {}; the 3 components explain {:.1} %, {:.1} %, {:.1} % of their variance",
        f.out.display(),
        report.sweeps,
        report.points,
        report.dim,
        report.explained[0] * 100.0,
        report.explained[1] * 100.0,
        report.explained[2] * 100.0,
    );
    if let Some((point, distance)) = report.query_point {
        println!("query: point {point} of the first sweep, {distance:.2} m from --query");
    }
    if f.images {
        println!(
            "images: {} camera images with the 2D network's features",
            report.images
        );
    }
    if let Some(bev) = &f.bev {
        println!("wrote {}", bev.display());
    }
    Ok(None)
}
