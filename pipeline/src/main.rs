//! `superflow-pipeline`: the producer process.
//!
//! * `superflow-pipeline --mcap <drives>... [--run NAME] [--config pipeline.toml]` — the
//!   service: streams SuperFlow batches over iceoryx2 (the streaming itself arrives with
//!   the sample-builder and service issues; today it indexes the drives, checks that they
//!   hold what training needs and says what is not built yet).
//! * `superflow-pipeline inspect --mcap <drives>... [--json]` — what the drives hold.

use anyhow::{Context as _, bail};
use clap::{Parser, Subcommand};
use std::path::PathBuf;
use superflow_pipeline::config::PipelineConfig;
use superflow_pipeline::drive::Dataset;
use superflow_pipeline::inspect::InspectReport;

/// Streams SuperFlow training batches from recorded drives to trainers over shared memory.
#[derive(Debug, Parser)]
#[command(version, about)]
struct Args {
    /// MCAP files or directories of them (searched for `*.mcap`).
    #[arg(long, num_args = 1.., global = true)]
    mcap: Vec<PathBuf>,
    /// Configuration file (TOML); defaults are the paper's.
    #[arg(long, global = true)]
    config: Option<PathBuf>,
    /// Run name: the services are `superflow/<run>/...`.
    #[arg(long, default_value = "default")]
    run: String,
    #[command(subcommand)]
    command: Option<Command>,
}

#[derive(Debug, Subcommand)]
enum Command {
    /// Lists what the drives hold: dialect, channels and roles, cameras, frame tree,
    /// time span, usable keyframes and skipped messages.
    Inspect {
        /// Print the stable JSON report (`superflow.inspect/1`) instead of text.
        #[arg(long)]
        json: bool,
    },
}

fn open(args: &Args) -> anyhow::Result<Dataset> {
    if args.mcap.is_empty() {
        bail!("no input: pass --mcap <file or directory>...");
    }
    let config = match &args.config {
        Some(path) => PipelineConfig::load(path)?,
        None => PipelineConfig::default(),
    };
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

fn run(args: &Args) -> anyhow::Result<()> {
    match &args.command {
        Some(Command::Inspect { json }) => {
            let dataset = open(args)?;
            let report = InspectReport::new(&dataset);
            if *json {
                println!("{}", serde_json::to_string_pretty(&report)?);
            } else {
                print!("{}", report.to_text());
            }
            Ok(())
        }
        None => {
            superflow_schemas::service::batches_service(&args.run)?;
            let dataset = open(args)?;
            dataset
                .check_sensors()
                .context("the drives cannot be trained on")?;
            for drive in InspectReport::new(&dataset).drives {
                tracing::info!(
                    files = drive.files.len(),
                    sweeps = drive.lidar_sweeps,
                    cameras = drive.cameras.len(),
                    keyframes = drive.usable_keyframes,
                    skipped = drive.skipped.total(),
                    "drive indexed"
                );
            }
            bail!(
                "not yet built: building samples and streaming batches on superflow/{}/batches \
                 arrive with the sample-builder and service issues",
                args.run
            )
        }
    }
}

fn main() -> std::process::ExitCode {
    tracing_subscriber::fmt()
        .with_writer(std::io::stderr)
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
