//! `superflow-trainer`: subscribes to a run's batches and trains the 3D network with the
//! SuperFlow losses (burn); `check` compares backends on one batch, `probe` scores a
//! backbone, `features` shows what it learned. The training itself lives in the library (`superflow_trainer::run`); this
//! file parses, sets up logging, dispatches and turns the outcome into an exit code.

mod check;
mod cli;
#[cfg(feature = "probe")]
mod probe;

use clap::Parser;
use cli::{Args, Sub};

/// mimalloc, keeping the pages it frees: a step allocates and frees the same hundreds of
/// megabytes of tensors every time (`superflow_common::memory`).
#[global_allocator]
static ALLOCATOR: superflow_common::memory::Allocator = superflow_common::memory::Allocator;

fn main() -> std::process::ExitCode {
    superflow_common::memory::keep_freed_pages();
    superflow_common::logging::init();
    let args = Args::parse();
    let outcome = match &args.command {
        Some(Sub::Check(c)) => check::check(&args, c),
        #[cfg(feature = "probe")]
        Some(Sub::Probe(p)) => probe::probe(&args, p),
        #[cfg(feature = "probe")]
        Some(Sub::Features(f)) => probe::features(&args, f),
        #[cfg(not(feature = "probe"))]
        Some(Sub::Probe(_) | Sub::Features(_)) => Err(anyhow::anyhow!(
            "probe and features are not compiled in: build superflow-trainer with its `probe` feature (on by default)"
        )),
        None => args.config().and_then(|config| {
            superflow_trainer::run::train(&args.run_options(), config).map_err(Into::into)
        }),
    };
    match outcome {
        Ok(None) => std::process::ExitCode::SUCCESS,
        // Stopped by a signal after checkpointing: not done, so not success.
        Ok(Some(code)) => std::process::ExitCode::from(code as u8),
        Err(err) => superflow_common::exit::failed("superflow-trainer", err.as_ref()),
    }
}
