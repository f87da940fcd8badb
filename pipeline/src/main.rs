//! `superflow-pipeline`: the producer process.
//!
//! `superflow-pipeline --mcap <drives>... [--run NAME]` will stream SuperFlow batches over
//! iceoryx2 (not built yet: it arrives with the ingest, sample-builder and service
//! issues). Today it opens every drive and reports what its summary holds, so the
//! command a user types already checks the inputs.

use anyhow::{Context as _, bail};
use clap::Parser;
use std::path::PathBuf;

/// Streams SuperFlow training batches from recorded drives to trainers over shared memory.
#[derive(Debug, Parser)]
#[command(version, about)]
struct Args {
    /// MCAP files or directories of them (searched for `*.mcap`).
    #[arg(long, required = true, num_args = 1..)]
    mcap: Vec<PathBuf>,
    /// Run name: the services are `superflow/<run>/...`.
    #[arg(long, default_value = "default")]
    run: String,
}

fn drive_files(inputs: &[PathBuf]) -> anyhow::Result<Vec<PathBuf>> {
    let mut files = Vec::new();
    for input in inputs {
        if input.is_dir() {
            let entries =
                std::fs::read_dir(input).with_context(|| format!("listing {}", input.display()))?;
            let mut found: Vec<PathBuf> = entries
                .filter_map(|e| e.ok().map(|e| e.path()))
                .filter(|p| p.extension().is_some_and(|e| e == "mcap"))
                .collect();
            found.sort();
            files.extend(found);
        } else {
            files.push(input.clone());
        }
    }
    if files.is_empty() {
        bail!("no .mcap files in {inputs:?}");
    }
    Ok(files)
}

fn run(args: &Args) -> anyhow::Result<()> {
    superflow_schemas::service::batches_service(&args.run)?;
    for path in drive_files(&args.mcap)? {
        let bytes = std::fs::read(&path).with_context(|| format!("reading {}", path.display()))?;
        let summary = mcap::Summary::read(&bytes)
            .with_context(|| format!("reading the MCAP summary of {}", path.display()))?
            .with_context(|| format!("{} has no summary section", path.display()))?;
        let messages = summary.stats.as_ref().map_or(0, |s| s.message_count);
        tracing::info!(
            drive = %path.display(),
            channels = summary.channels.len(),
            messages,
            "drive opened"
        );
    }
    bail!(
        "not yet built: decoding drives into samples and streaming batches on \
         superflow/{}/batches arrive with the ingest, sample-builder and service issues",
        args.run
    )
}

fn main() -> std::process::ExitCode {
    tracing_subscriber::fmt()
        .with_env_filter(
            tracing_subscriber::EnvFilter::try_from_default_env().unwrap_or_else(|_| "info".into()),
        )
        .init();
    match run(&Args::parse()) {
        Ok(()) => std::process::ExitCode::SUCCESS,
        Err(err) => {
            eprintln!("superflow-pipeline: {err:#}");
            std::process::ExitCode::from(2)
        }
    }
}
