//! `superflow-pipeline`: the producer process.
//!
//! * `superflow-pipeline --mcap <drives>... [--run NAME] [--config pipeline.toml]` — the
//!   service: streams SuperFlow batches over iceoryx2 (broadcast or shard), with
//!   backpressure, dead-subscriber cleanup, resume requests and Prometheus metrics.
//! * `superflow-pipeline index --mcap <drives>... [--index-cache DIR]` — indexes the
//!   drives into the index cache ahead of training, with a summary.
//! * `superflow-pipeline inspect --mcap <drives>... [--json]` — what the drives hold.
//! * `superflow-pipeline sample --mcap <drive> --index K --out DIR [--no-augment]` — one
//!   sample written as `.npy` arrays, `sample.json` and overlay PNGs.
//!
//! This file parses the command line, sets up logging, hands the command to its module
//! and maps an error to the exit code; the flags are in [`cli`].

mod batch;
mod cli;
mod index;
mod inspect;
mod open;
mod sample;
mod serve;
mod superpixels;

use cli::{Args, Command};

/// mimalloc, keeping freed pages for the next sample (see `superflow_pipeline::memory`).
#[global_allocator]
static ALLOCATOR: superflow_common::memory::Allocator = superflow_common::memory::Allocator;

fn run(args: &Args) -> anyhow::Result<()> {
    match &args.command {
        Some(Command::Index { prune }) => index::run(args, *prune),
        Some(Command::Inspect { json }) => inspect::run(args, *json),
        Some(Command::Superpixels { force }) => superpixels::run(args, *force),
        Some(Command::Sample {
            index,
            epoch,
            out,
            out_mcap,
            drive_mcap,
            no_augment,
        }) => sample::run(
            args,
            &sample::Request {
                index: *index,
                epoch: *epoch,
                no_augment: *no_augment,
                out: out.as_deref(),
                out_mcap: out_mcap.as_deref(),
                drive_mcap: drive_mcap.as_deref(),
            },
        ),
        Some(Command::Batch { index, epoch, out }) => batch::run(args, *index, *epoch, out),
        None => serve::run(args),
    }
}

fn main() -> std::process::ExitCode {
    superflow_common::memory::keep_freed_pages();
    superflow_common::memory::small_pages_only();
    superflow_common::logging::init();
    superflow_pipeline::source::raise_open_file_limit();
    match run(&cli::parse()) {
        Ok(()) => std::process::ExitCode::SUCCESS,
        Err(err) => superflow_common::exit::failed("superflow-pipeline", err.as_ref()),
    }
}
