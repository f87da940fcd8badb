//! `superpixels`: a SLIC sidecar for every drive that lacks a current one.

use crate::cli::Args;
use anyhow::{Context as _, bail};
use superflow_pipeline::drive::Dataset;
use superflow_pipeline::sample::SampleConfig;
use superflow_pipeline::sample::recipe::SuperpixelSource;
use superflow_pipeline::sample::sidecar;

pub fn run(args: &Args, force: bool) -> anyhow::Result<()> {
    let config = args.config()?.sample;
    let dataset = crate::open::dataset(args)?;
    write_slic_sidecars(&dataset, &config, force)
}

fn write_slic_sidecars(
    dataset: &Dataset,
    config: &SampleConfig,
    force: bool,
) -> anyhow::Result<()> {
    for drive in &dataset.drives {
        let path = sidecar::sidecar_path(drive)
            .with_context(|| format!("{}: no file to put a sidecar beside", drive.file_list()))?;
        if path.exists() && !force {
            if sidecar::sidecar_matches(drive, config) {
                println!("{}: up to date", path.display());
                continue;
            }
            bail!(
                "{} exists with other settings (or other cameras); rerun with --force to rewrite it",
                path.display()
            );
        }
        let has_class_maps = drive.cameras.iter().all(|c| !c.superpixels.is_empty());
        if has_class_maps && config.superpixels != SuperpixelSource::Slic {
            println!(
                "{}: note: every camera has class maps, which samples use under superpixels = {}; \
                 the SLIC sidecar serves superpixels = \"slic\"",
                drive.file_list(),
                serde_json::to_string(&config.superpixels)?
            );
        }
        let images: usize = drive.cameras.iter().map(|c| c.frames.len()).sum();
        let bar = indicatif::ProgressBar::new(images as u64).with_style(
            indicatif::ProgressStyle::with_template(
                "SLIC {bar:40} {pos}/{len} images ({per_sec}, {eta} left)",
            )
            .unwrap_or_else(|_| indicatif::ProgressStyle::default_bar()),
        );
        let started = std::time::Instant::now();
        let summary = sidecar::write_sidecar(drive, config, &path, &|| bar.inc(1))?;
        bar.finish_and_clear();
        let secs = started.elapsed().as_secs_f64();
        println!(
            "{}: {} label maps ({:.1} MB) in {secs:.1} s ({:.1} ms an image)",
            summary.path.display(),
            summary.images,
            summary.bytes as f64 / 1e6,
            1e3 * secs / summary.images.max(1) as f64
        );
        if let Some(first) = summary.skipped.first() {
            println!(
                "  {} images skipped (they do not decode; a sample that needs one fails as it \
                 would without the sidecar); first: {first}",
                summary.skipped.len()
            );
        }
    }
    Ok(())
}
