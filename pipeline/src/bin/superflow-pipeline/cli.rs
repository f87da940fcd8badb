//! The command line: global flags, the service's flags and the subcommands.

use anyhow::bail;
use clap::{Parser, Subcommand};
use std::path::PathBuf;
use superflow_pipeline::config::{Overrides, PipelineConfig};
use superflow_pipeline::drive::DatasetGroup;
use superflow_pipeline::drive::groups::validate_groups;
use superflow_pipeline::publish::{Mode, Order, ResumeAt};

/// Streams SuperFlow training batches from recorded drives to trainers over shared memory.
#[derive(Debug, Parser)]
#[command(version, about)]
pub struct Args {
    /// MCAP files or directories of them (searched for `*.mcap`): the dataset group
    /// `default`, served once per epoch.
    #[arg(long, num_args = 1.., global = true)]
    pub mcap: Vec<PathBuf>,
    /// A named group of drives and how many times per epoch each of its keyframes is
    /// served: `NAME=PATH[,PATH...][:REPEAT]` (repeat 1 when left out; 2 serves each
    /// twice, 0.5 half of them, another half each epoch). Repeatable; replaces the
    /// configuration's `[[dataset]]` groups.
    #[arg(long, global = true, value_name = "NAME=PATHS[:REPEAT]", value_parser = parse_group)]
    pub dataset: Vec<DatasetGroup>,
    /// Configuration file (TOML); defaults are the paper's.
    #[arg(long, global = true)]
    pub config: Option<PathBuf>,
    /// Where the index of every file is kept for the next start (overrides `[ingest]
    /// index_cache`; `off` keeps none) [default: the per-user cache directory,
    /// `~/.cache/superflow/index`].
    #[arg(long, global = true, env = "SUPERFLOW_INDEX_CACHE")]
    pub index_cache: Option<PathBuf>,
    /// Run name: the services are `superflow/<run>/...` (`batch` writes it in the
    /// batch's header).
    #[arg(long, global = true, default_value = "default")]
    pub run: String,
    /// Stream mode (overrides `[service] mode`).
    #[arg(long, value_enum)]
    pub mode: Option<Mode>,
    /// Ranks in shard mode (overrides `[service] world_size`).
    #[arg(long)]
    pub world_size: Option<u32>,
    /// This host's rank for multi-host sharding (overrides `[service] host_rank`):
    /// host h of N gets a disjoint share of every epoch's keyframes.
    #[arg(long, env = "SUPERFLOW_HOST_RANK")]
    pub host_rank: Option<u32>,
    /// Hosts sharing each epoch, each running its own pipeline on the same drives and
    /// configuration (overrides `[service] host_count`).
    #[arg(long, env = "SUPERFLOW_HOST_COUNT")]
    pub host_count: Option<u32>,
    /// Samples per batch (overrides `[service] batch_size`; also the size of the batch
    /// `batch` writes).
    #[arg(long, global = true)]
    pub batch_size: Option<u32>,
    /// How each epoch's samples are ordered (overrides `[service] order`): `global`
    /// shuffles them all; `blocks` serves blocks of neighbouring keyframes side by side,
    /// building each shared frame once.
    #[arg(long, value_enum)]
    pub order: Option<Order>,
    /// Epochs to stream, 0 = forever (overrides `[service] epochs`).
    #[arg(long)]
    pub epochs: Option<u64>,
    /// Subscribers to wait for before the first batch of each stream (overrides
    /// `[service] min_subscribers`).
    #[arg(long)]
    pub subscribers: Option<u32>,
    /// Start at this epoch ...
    #[arg(long, default_value_t = 0)]
    pub start_epoch: u64,
    /// ... and this step of every stream (a position of a job of this size: nothing
    /// before it is built). A job resumed with another number of ranks or hosts starts
    /// with --start-sample.
    #[arg(long, default_value_t = 0, conflicts_with = "start_sample")]
    pub start_step: u64,
    /// ... or after this many samples of the epoch, consumed by the whole job that
    /// stopped (every rank and host: a trainer's checkpoint keeps it as `epoch_samples`):
    /// the rest of the epoch is dealt to this job's ranks, whatever their number.
    #[arg(long)]
    pub start_sample: Option<u64>,
    /// Serve Prometheus text metrics on this address (e.g. 127.0.0.1:9464).
    #[arg(long)]
    pub metrics_addr: Option<std::net::SocketAddr>,
    /// Isolates this deployment's iceoryx2 resources (also `SUPERFLOW_IOX_PREFIX`).
    #[arg(long, env = "SUPERFLOW_IOX_PREFIX")]
    pub iox_prefix: Option<String>,
    #[command(subcommand)]
    pub command: Option<Command>,
}

#[derive(Debug, Subcommand)]
pub enum Command {
    /// Indexes the drives into the index cache ahead of training (a Slurm step or a
    /// Kubernetes init job before the pipelines start) and prints what they hold:
    /// drives, files, keyframes, skipped messages, damaged files, seconds, cache hits.
    /// Fails when it could not store what it indexed (a read-only or full cache).
    Index {
        /// Also tidy the cache: remove entries this build cannot use (written by another
        /// build, damaged, misnamed) and temporary files of dead writers, and evict the
        /// least recently used entries beyond `[ingest] index_cache_max_mb`. Without
        /// `--mcap`, only tidies.
        #[arg(long)]
        prune: bool,
    },
    /// Lists what the drives hold: dialect, channels and roles, cameras, frame tree,
    /// time span, usable keyframes, per-point labels (`[labels]` of the configuration)
    /// and skipped messages.
    Inspect {
        /// Print the stable JSON report (`superflow.inspect/1`) instead of text.
        #[arg(long)]
        json: bool,
    },
    /// Builds one sample and writes it as `.npy` arrays, `sample.json` and PNGs of each
    /// chosen image with the projected points coloured by depth and by superpixel
    /// (`--out`), and/or as an MCAP file that Foxglove opens (`--out-mcap`); or every
    /// keyframe of its drive as such a file (`--drive-mcap`).
    #[command(group = clap::ArgGroup::new("outputs").required(true).multiple(true))]
    Sample {
        /// Keyframe number in the plan (drive and time order; `inspect` counts them).
        #[arg(long, default_value_t = 0)]
        index: usize,
        /// Epoch of the random draws (cameras, flips, augmentation).
        #[arg(long, default_value_t = 0)]
        epoch: u64,
        /// Output directory of the `.npy` arrays and PNGs.
        #[arg(long, group = "outputs")]
        out: Option<PathBuf>,
        /// The sample as an MCAP file with Foxglove's schemas (clouds, images as the model
        /// sees them with their calibrations, pairings, transforms).
        #[arg(long, group = "outputs")]
        out_mcap: Option<PathBuf>,
        /// Every keyframe of the drive of `--index`, one sample after the other, as one
        /// such MCAP file, to scrub through the whole drive.
        #[arg(long, group = "outputs")]
        drive_mcap: Option<PathBuf>,
        /// Keep points in their LiDAR frame (no 3D augmentation).
        #[arg(long)]
        no_augment: bool,
    },
    /// Runs SLIC once on every camera image of each drive, with the configuration's
    /// recipe, and writes the labels to `<drive>.slic.mcap` beside it; samples then
    /// read them instead of running SLIC per image and epoch (drives with class maps
    /// do not need this).
    Superpixels {
        /// Rewrite a sidecar that exists (else one written with the same settings is
        /// kept, and one with other settings is an error).
        #[arg(long)]
        force: bool,
    },
    /// Builds one batch (keyframes `index..index + batch-size` of the plan; `--batch-size`,
    /// else `[service] batch_size`, as the service would) and writes it
    /// to a file exactly as it goes on the wire: the `BatchHeader` bytes, then the
    /// payload (`schemas/BATCH_FORMAT.md`). Benchmarks and offline tools read it.
    Batch {
        /// First keyframe of the batch.
        #[arg(long, default_value_t = 0)]
        index: usize,
        /// Epoch of the random draws.
        #[arg(long, default_value_t = 0)]
        epoch: u64,
        /// Output file.
        #[arg(long)]
        out: PathBuf,
    },
}

/// The service's flags a subcommand reads: every other flag of the service means nothing
/// to it, and is refused rather than silently ignored.
fn flags_read_by(command: &Command) -> &'static [&'static str] {
    match command {
        Command::Batch { .. } => &["run", "batch_size"],
        Command::Index { .. }
        | Command::Inspect { .. }
        | Command::Sample { .. }
        | Command::Superpixels { .. } => &[],
    }
}

/// The top-level flags (by clap id) that mean the same to every subcommand; every other
/// top-level flag is the service's, a flag added later included.
const SHARED_FLAGS: &[&str] = &[
    "mcap",
    "dataset",
    "config",
    "index_cache",
    "help",
    "version",
];

/// The command line, parsed; a service flag given on the command line to a subcommand
/// that does not read it is a usage error (exit code 2), as an unknown flag is. Values
/// from the environment (`SUPERFLOW_HOST_RANK`, ...) are a job's settings for the
/// service and pass unremarked.
pub fn parse() -> Args {
    use clap::{CommandFactory as _, FromArgMatches as _};
    let mut cmd = Args::command();
    let matches = cmd.get_matches_mut();
    let args = Args::from_arg_matches(&matches).unwrap_or_else(|e| e.format(&mut cmd).exit());
    let Some(command) = &args.command else {
        return args;
    };
    let name = matches.subcommand_name().unwrap_or_default();
    let sub = matches.subcommand_matches(name).unwrap_or(&matches);
    let read = flags_read_by(command);
    let service_flags: Vec<String> = cmd
        .get_arguments()
        .map(|arg| arg.get_id().as_str().to_owned())
        .filter(|id| !SHARED_FLAGS.contains(&id.as_str()) && !read.contains(&id.as_str()))
        .collect();
    for id in &service_flags {
        // A global flag is known to both; the others to the top level alone.
        let given = [&matches, sub].iter().any(|m| {
            m.ids().any(|known| known.as_str() == *id)
                && m.value_source(id) == Some(clap::parser::ValueSource::CommandLine)
        });
        if given {
            let flag = format!("--{}", id.replace('_', "-"));
            cmd.error(
                clap::error::ErrorKind::ArgumentConflict,
                format!(
                    "{flag} is a setting of the service (no subcommand); `{name}` does not \
                     read it"
                ),
            )
            .exit();
        }
    }
    args
}

/// `--dataset NAME=PATH[,PATH...][:REPEAT]`.
fn parse_group(text: &str) -> Result<DatasetGroup, String> {
    DatasetGroup::parse(text).map_err(|e| e.to_string())
}

impl Args {
    /// The dataset groups to open: `--dataset` (else the configuration's `[[dataset]]`),
    /// after a `default` group of `--mcap` when given.
    pub fn groups(&self, config: &PipelineConfig) -> anyhow::Result<Vec<DatasetGroup>> {
        let mut groups = Vec::new();
        if !self.mcap.is_empty() {
            groups.push(DatasetGroup::default_of(self.mcap.clone()));
        }
        if self.dataset.is_empty() {
            groups.extend(config.dataset.iter().cloned());
        } else {
            groups.extend(self.dataset.iter().cloned());
        }
        if groups.is_empty() {
            bail!(
                "no input: pass --mcap <file or directory>..., --dataset NAME=PATH[:REPEAT], \
                 or [[dataset]] groups in --config"
            );
        }
        validate_groups(&groups)?;
        Ok(groups)
    }

    /// Where the service starts: `--start-epoch` with `--start-step` or `--start-sample`.
    pub fn start(&self) -> ResumeAt {
        match self.start_sample {
            Some(sample) => ResumeAt::Sample {
                epoch: self.start_epoch,
                sample,
                global_batch: superflow_schemas::service::UNKNOWN,
            },
            None => ResumeAt::Step {
                epoch: self.start_epoch,
                step: self.start_step,
            },
        }
    }

    /// The `--config` file, or the defaults without one, with `--index-cache` laid over.
    pub fn config(&self) -> anyhow::Result<PipelineConfig> {
        let mut config = match &self.config {
            Some(path) => PipelineConfig::load(path)?,
            None => PipelineConfig::default(),
        };
        if let Some(dir) = &self.index_cache {
            config.ingest.index_cache = Some(dir.clone());
        }
        Ok(config)
    }

    /// The service's flags, to lay over the configuration ([`PipelineConfig::apply`]).
    pub fn overrides(&self) -> anyhow::Result<Overrides> {
        Ok(Overrides {
            mode: self.mode,
            world_size: self.world_size,
            host_rank: self.host_rank,
            host_count: self.host_count,
            batch_size: self.batch_size,
            epochs: self.epochs,
            min_subscribers: self.subscribers,
            order: self.order,
        })
    }
}
