//! `batch`: one batch written to a file exactly as it goes on the wire.

use crate::cli::Args;
use anyhow::{Context as _, bail};
use std::path::Path;
use superflow_pipeline::batch::{BatchShape, batch_bytes};
use superflow_pipeline::sample::SampleBuilder;
use superflow_schemas::batch::BatchMeta;

pub fn run(args: &Args, index: usize, epoch: u64, out: &Path) -> anyhow::Result<()> {
    // The service's settings, read the way the service reads them.
    let mut config = args.config()?;
    config.apply(&args.overrides()?);
    config.service.validate()?;
    let size = config.service.batch_size as usize;
    let dataset = crate::open::dataset(args)?;
    let builder = SampleBuilder::new(&dataset, config.sample)?;
    let keyframes = builder.plan().keyframes.len();
    if index + size > keyframes {
        bail!(
            "keyframes {index}..{} requested; the drives have {keyframes}",
            index + size
        );
    }
    let samples = (index..index + size)
        .map(|k| builder.build_keyframe(k, epoch, k as u64))
        .collect::<Result<Vec<_>, _>>()?;
    let c = builder.config();
    let meta = BatchMeta {
        run: args.run.clone(),
        epoch,
        step: 0,
        seed: c.seed,
        sequence: 0,
        created_unix_nanos: 0,
        sample_count: size as u32,
        flags: 0,
    };
    let bytes = batch_bytes(&samples, BatchShape::of(c), &meta)?;
    std::fs::write(out, &bytes).with_context(|| format!("writing {}", out.display()))?;
    println!(
        "wrote a batch of {size} samples ({} bytes) to {}",
        bytes.len(),
        out.display()
    );
    Ok(())
}
