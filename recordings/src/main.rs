//! `superflow-recordings --out DIR`: writes the sample drives and their ground truth;
//! `superflow-recordings --damaged DIR`: writes the damaged recordings.

use anyhow::Context as _;
use clap::Parser;
use std::path::PathBuf;
use superflow_recordings::{Dialect, DriveOptions, damaged, generate_with};

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
    /// Length of the drive in seconds (the sample drives: 3).
    #[arg(long)]
    duration_secs: Option<f64>,
    /// Cameras of the rig, the first N in nuScenes order (the sample drives: 6).
    #[arg(long)]
    cameras: Option<usize>,
    /// Write the damaged recordings (`recordings/damaged/`, from a short drive) into this
    /// directory instead of the sample drives.
    #[arg(long, value_name = "DIR")]
    damaged: Option<PathBuf>,
}

fn main() -> anyhow::Result<()> {
    tracing_subscriber::fmt()
        .with_env_filter(
            tracing_subscriber::EnvFilter::try_from_default_env().unwrap_or_else(|_| "info".into()),
        )
        .init();
    let args = Args::parse();
    if let Some(dir) = &args.damaged {
        for file in damaged::write_damaged(dir)? {
            tracing::info!(
                file = %dir.join(&file.name).display(),
                bytes = file.bytes.len(),
                damage = %file.damage,
                "wrote damaged recording"
            );
        }
        return Ok(());
    }
    let mut options = DriveOptions::default();
    if let Some(secs) = args.duration_secs {
        anyhow::ensure!(secs > 0.0, "--duration-secs must be positive");
        options.duration_nanos = (secs * 1e9).round() as i64;
    }
    if let Some(cameras) = args.cameras {
        anyhow::ensure!((1..=6).contains(&cameras), "--cameras must be 1..=6");
        options.cameras = cameras;
    }
    std::fs::create_dir_all(&args.out)
        .with_context(|| format!("creating {}", args.out.display()))?;
    for dialect in Dialect::ALL {
        if args.dialect.as_deref().is_some_and(|d| d != dialect.name()) {
            continue;
        }
        let started = std::time::Instant::now();
        let drive = generate_with(dialect, &options)?;
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
