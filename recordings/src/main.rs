//! `superflow-recordings --out DIR`: writes the sample drives and their ground truth.

use anyhow::Context as _;
use clap::Parser;
use std::path::PathBuf;
use superflow_recordings::{Dialect, generate};

/// Generates the sample drives of `recordings/` (deterministic: same bytes every run).
#[derive(Debug, Parser)]
#[command(version, about)]
struct Args {
    /// Directory to write `<drive>.mcap` and `<drive>.truth.json` into.
    #[arg(long, default_value = "recordings/drives")]
    out: PathBuf,
    /// Only this dialect (`foxglove` or `ros2`); both by default.
    #[arg(long)]
    dialect: Option<String>,
}

fn main() -> anyhow::Result<()> {
    tracing_subscriber::fmt()
        .with_env_filter(
            tracing_subscriber::EnvFilter::try_from_default_env().unwrap_or_else(|_| "info".into()),
        )
        .init();
    let args = Args::parse();
    std::fs::create_dir_all(&args.out)
        .with_context(|| format!("creating {}", args.out.display()))?;
    for dialect in Dialect::ALL {
        if args.dialect.as_deref().is_some_and(|d| d != dialect.name()) {
            continue;
        }
        let started = std::time::Instant::now();
        let drive = generate(dialect)?;
        let mcap_path = args.out.join(format!("{}.mcap", dialect.drive_name()));
        let truth_path = args
            .out
            .join(format!("{}.truth.json", dialect.drive_name()));
        std::fs::write(&mcap_path, &drive.mcap)
            .with_context(|| format!("writing {}", mcap_path.display()))?;
        std::fs::write(&truth_path, drive.truth_json()?)
            .with_context(|| format!("writing {}", truth_path.display()))?;
        tracing::info!(
            drive = %mcap_path.display(),
            bytes = drive.mcap.len(),
            sweeps = drive.truth.lidar.sweeps.len(),
            landmarks = drive.truth.landmarks.len(),
            secs = started.elapsed().as_secs_f64(),
            "wrote drive"
        );
    }
    Ok(())
}
