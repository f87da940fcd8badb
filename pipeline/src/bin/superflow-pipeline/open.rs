//! Opening the `--mcap` drives, with a progress bar while they are indexed.

use crate::cli::Args;
use anyhow::bail;
use superflow_pipeline::drive::Dataset;

/// The drives of `--mcap`, indexed with the configuration's `[ingest]` choices.
pub fn dataset(args: &Args) -> anyhow::Result<Dataset> {
    if args.mcap.is_empty() {
        bail!("no input: pass --mcap <file or directory>...");
    }
    let config = args.config()?;
    let bar = indicatif::ProgressBar::new(0).with_style(
        indicatif::ProgressStyle::with_template(
            "indexing {bar:40} {bytes}/{total_bytes} ({bytes_per_sec})",
        )
        .unwrap_or_else(|_| indicatif::ProgressStyle::default_bar()),
    );
    let dataset = Dataset::open_with_progress(&args.mcap, &config.ingest, |done, total| {
        bar.set_length(total);
        bar.set_position(done);
    });
    bar.finish_and_clear();
    Ok(dataset?)
}
