//! `superflow-recordings --out DIR`: writes the sample drives and their ground truth;
//! `superflow-recordings --damaged DIR`: writes the damaged recordings;
//! `superflow-recordings --preset nuscenes --image-size 1600x900`: a nuScenes-sized drive
//! for benchmarks, under its own file stem;
//! `superflow-recordings --out DIR --keyframes 120`: a longer labelled street drive (60 s)
//! for evaluating a probe, named `street_<dialect>_60s`;
//! `superflow-recordings --out DIR --cameras 2 --image-size 640x360 --beams 32`: a drive
//! of another rig (a fleet's 2-camera car), named `street_<dialect>_2cam_640x360_32beams`.

use clap::Parser as _;
use superflow_recordings::cli::{self, Args};

fn main() -> std::process::ExitCode {
    tracing_subscriber::fmt()
        .with_env_filter(
            tracing_subscriber::EnvFilter::try_from_default_env().unwrap_or_else(|_| "info".into()),
        )
        .init();
    let args = Args::parse();
    match cli::run(&args) {
        Ok(()) => std::process::ExitCode::SUCCESS,
        Err(err) => superflow_common::exit::failed("superflow-recordings", err.as_ref()),
    }
}
