//! `superflow-pipeline`: the producer process.
//!
//! * `superflow-pipeline --mcap <drives>... [--run NAME] [--config pipeline.toml]` — the
//!   service: streams SuperFlow batches over iceoryx2 (the streaming itself arrives with
//!   the sample-builder and service issues; today it indexes the drives, checks that they
//!   hold what training needs and says what is not built yet).
//! * `superflow-pipeline inspect --mcap <drives>... [--json]` — what the drives hold.
//! * `superflow-pipeline sample --mcap <drive> --index K --out DIR [--no-augment]` — one
//!   sample written as `.npy` arrays, `sample.json` and overlay PNGs.

use anyhow::{Context as _, bail};
use clap::{Parser, Subcommand};
use std::path::PathBuf;
use superflow_pipeline::config::PipelineConfig;
use superflow_pipeline::drive::Dataset;
use superflow_pipeline::inspect::InspectReport;
use superflow_pipeline::sample::SampleBuilder;
use superflow_pipeline::sample::export::write_sample;

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
    /// Builds one sample and writes it as `.npy` arrays, `sample.json` and PNGs of each
    /// chosen image with the projected points coloured by depth and by superpixel.
    Sample {
        /// Keyframe number in the plan (drive and time order; `inspect` counts them).
        #[arg(long, default_value_t = 0)]
        index: usize,
        /// Epoch of the random draws (cameras, flips, augmentation).
        #[arg(long, default_value_t = 0)]
        epoch: u64,
        /// Output directory.
        #[arg(long)]
        out: PathBuf,
        /// Keep points in their LiDAR frame (no 3D augmentation).
        #[arg(long)]
        no_augment: bool,
    },
}

fn load_config(args: &Args) -> anyhow::Result<PipelineConfig> {
    Ok(match &args.config {
        Some(path) => PipelineConfig::load(path)?,
        None => PipelineConfig::default(),
    })
}

fn open(args: &Args) -> anyhow::Result<Dataset> {
    if args.mcap.is_empty() {
        bail!("no input: pass --mcap <file or directory>...");
    }
    let config = load_config(args)?;
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
        Some(Command::Sample {
            index,
            epoch,
            out,
            no_augment,
        }) => {
            let mut config = load_config(args)?.sample;
            if *no_augment {
                config.augment.enabled = false;
            }
            let dataset = open(args)?;
            let builder = SampleBuilder::new(&dataset, config)?;
            let plan = builder.plan();
            let key = plan.keyframes.get(*index).with_context(|| {
                format!(
                    "keyframe {index} requested; the drives have {} keyframes (0..{})",
                    plan.keyframes.len(),
                    plan.keyframes.len()
                )
            })?;
            let files = dataset.drives[key.drive as usize].file_list();
            let sample = {
                let _span = tracing::info_span!("build sample", keyframe = index).entered();
                builder.build_keyframe(*index, *epoch, *index as u64)?
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
