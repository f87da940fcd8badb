//! `sample`: one sample written as `.npy` arrays, `sample.json` and overlay PNGs.

use crate::cli::Args;
use anyhow::Context as _;
use std::path::Path;
use superflow_pipeline::sample::SampleBuilder;
use superflow_pipeline::sample::export::write_sample;

pub fn run(
    args: &Args,
    index: usize,
    epoch: u64,
    out: &Path,
    no_augment: bool,
) -> anyhow::Result<()> {
    let mut config = args.config()?.sample;
    if no_augment {
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
    let files = dataset.drives[key.drive as usize].file_list();
    let sample = {
        let _span = tracing::info_span!("build sample", keyframe = index).entered();
        builder.build_keyframe(index, epoch, index as u64)?
    };
    let written = write_sample(&sample, builder.config(), &files, out)?;
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
    println!("wrote {} files to {}", written.len(), out.display());
    Ok(())
}
