//! Opening the `--mcap` drives, with a progress bar while they are indexed.

use crate::cli::Args;
use std::sync::atomic::{AtomicUsize, Ordering};
use superflow_pipeline::drive::Dataset;

/// The drives of `--mcap` and the dataset groups, indexed with the configuration's
/// `[ingest]` choices.
pub fn dataset(args: &Args) -> anyhow::Result<Dataset> {
    let config = args.config()?;
    let groups = args.groups(&config)?;
    let bar = indicatif::ProgressBar::new(0).with_style(
        indicatif::ProgressStyle::with_template(
            "indexing {bar:40} {msg} {bytes}/{total_bytes} ({bytes_per_sec}, {eta} left)",
        )
        .unwrap_or_else(|_| indicatif::ProgressStyle::default_bar()),
    );
    // Drives are indexed on several threads: the message changes only when the count of
    // files done does (the first caller to see it writes it).
    let shown_files = AtomicUsize::new(usize::MAX);
    let dataset = Dataset::open_groups(&groups, &config.ingest, |p| {
        bar.set_length(p.bytes_total);
        if bar.position() < p.bytes_done {
            bar.set_position(p.bytes_done);
        }
        if shown_files.swap(p.files_done, Ordering::Relaxed) != p.files_done {
            bar.set_message(format!("{}/{} files", p.files_done, p.files_total));
        }
    });
    bar.finish_and_clear();
    Ok(dataset?)
}
