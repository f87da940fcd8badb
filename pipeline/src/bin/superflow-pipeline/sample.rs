//! `sample`: one sample written as `.npy` arrays, `sample.json` and overlay PNGs, and/or
//! as an MCAP file for Foxglove; or a whole drive's keyframes as one such file.

use crate::cli::Args;
use anyhow::Context as _;
use std::path::Path;
use superflow_pipeline::sample::SampleBuilder;
use superflow_pipeline::sample::export::write_sample;
use superflow_pipeline::view::SampleMcap;

/// What `sample` was asked for.
pub struct Request<'a> {
    pub index: usize,
    pub epoch: u64,
    pub no_augment: bool,
    pub out: Option<&'a Path>,
    pub out_mcap: Option<&'a Path>,
    pub drive_mcap: Option<&'a Path>,
}

pub fn run(args: &Args, request: &Request<'_>) -> anyhow::Result<()> {
    let index = request.index;
    let mut config = args.config()?.sample;
    if request.no_augment {
        config.augment.enabled = false;
    }
    let dataset = crate::open::dataset(args)?;
    let builder = SampleBuilder::new(&dataset, config)?;
    let plan = builder.plan();
    let key = plan.keyframes.get(index).with_context(|| {
        format!(
            "keyframe {index} requested; the drives have {} keyframes (0..{})",
            plan.keyframes.len(),
            plan.keyframes.len()
        )
    })?;
    let drive = &dataset.drives[key.drive as usize];
    if request.out.is_some() || request.out_mcap.is_some() {
        let sample = {
            let _span = tracing::info_span!("build sample", keyframe = index).entered();
            builder.build_keyframe(index, request.epoch, index as u64)?
        };
        let frame = &sample.frames[sample.key_frame];
        tracing::info!(
            keyframe = index,
            sweep = key.sweep,
            cameras = %sample.cameras.join(","),
            points = frame.cloud.xyz.len(),
            pairings = frame.cloud.pairings.len(),
            dense_points = sample.dense.xyz.len(),
            voxels = frame.cloud.voxels.coords.len(),
            "sample built"
        );
        if let Some(out) = request.out {
            let written = write_sample(&sample, builder.config(), &drive.file_list(), out)?;
            println!("wrote {} files to {}", written.len(), out.display());
        }
        if let Some(path) = request.out_mcap {
            let mut view = SampleMcap::create(path, builder.config())?;
            view.add(&sample, drive)?;
            let summary = view.finish()?;
            println!(
                "wrote {} ({} messages; open it in Foxglove)",
                path.display(),
                summary.messages
            );
        }
    }
    if let Some(path) = request.drive_mcap {
        let keyframes: Vec<usize> = (0..plan.keyframes.len())
            .filter(|&k| plan.keyframes[k].drive == key.drive)
            .collect();
        let bar = indicatif::ProgressBar::new(keyframes.len() as u64).with_style(
            indicatif::ProgressStyle::with_template(
                "samples {bar:40} {pos}/{len} keyframes ({per_sec}, {eta} left)",
            )
            .unwrap_or_else(|_| indicatif::ProgressStyle::default_bar()),
        );
        let mut view = SampleMcap::create(path, builder.config())?;
        let mut failed = 0usize;
        for k in keyframes {
            match builder.build_keyframe(k, request.epoch, k as u64) {
                Ok(sample) => view.add(&sample, drive)?,
                Err(e) => {
                    failed += 1;
                    tracing::error!(keyframe = k, "sample skipped: {e}");
                }
            }
            bar.inc(1);
        }
        bar.finish_and_clear();
        let summary = view.finish()?;
        println!(
            "wrote {} ({} samples, {} frames, {} messages{}; open it in Foxglove)",
            path.display(),
            summary.samples,
            summary.frames,
            summary.messages,
            if failed > 0 {
                format!(", {failed} keyframes skipped")
            } else {
                String::new()
            }
        );
    }
    Ok(())
}
