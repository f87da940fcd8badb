//! `superflow-trainer`: subscribes to a run's batches and trains with the SuperFlow
//! losses (burn). Not built yet: it arrives with the trainer issue. The command line is
//! the one that will stay.

use clap::Parser;

/// Trains a 3D network on SuperFlow batches received over shared memory.
#[derive(Debug, Parser)]
#[command(version, about)]
struct Args {
    /// Run name of the pipeline to subscribe to.
    #[arg(long, default_value = "default")]
    run: String,
    /// Data-parallel rank (shard mode) ...
    #[arg(long)]
    rank: Option<u32>,
    /// ... out of this many ranks.
    #[arg(long)]
    world_size: Option<u32>,
}

fn main() -> std::process::ExitCode {
    let args = Args::parse();
    let service = match args.rank {
        Some(rank) => superflow_schemas::service::rank_service(&args.run, rank),
        None => superflow_schemas::service::batches_service(&args.run),
    };
    match service {
        Ok(service) => eprintln!(
            "superflow-trainer: not yet built: subscribing to {service} (world size {}) and \
             running the SuperFlow losses arrive with the trainer issue",
            args.world_size.unwrap_or(1)
        ),
        Err(err) => eprintln!("superflow-trainer: {err}"),
    }
    std::process::ExitCode::from(2)
}
