//! The command line: flags, subcommands, and how they become a configuration and the
//! run's options.

use anyhow::Context as _;
use clap::Parser;
use std::path::PathBuf;
use superflow_trainer::config::{Overrides, TrainerConfig};
use superflow_trainer::device::Backend;
use superflow_trainer::run::RunOptions;
use superflow_trainer::unet::UNetPreset;
use superflow_trainer::vit::VitPreset;

/// Trains a 3D network on SuperFlow batches received over shared memory.
#[derive(Debug, Parser)]
#[command(version, about)]
pub struct Args {
    #[command(subcommand)]
    pub command: Option<Sub>,
    /// Run name of the pipeline to subscribe to.
    #[arg(long, default_value = "default")]
    pub run: String,
    /// Data-parallel rank (shard mode) ...
    #[arg(long)]
    pub rank: Option<u32>,
    /// ... out of this many ranks.
    #[arg(long)]
    pub world_size: Option<u32>,
    /// trainer.toml (networks, losses, optimizer, checkpoints); flags override it.
    #[arg(long, global = true)]
    pub config: Option<PathBuf>,
    /// Optimizer steps of the run (also the one-cycle schedule's length) [default: the
    /// config's `optim.steps`].
    #[arg(long, global = true)]
    pub steps: Option<u64>,
    /// 3D network.
    #[arg(long, global = true, value_enum)]
    pub unet: Option<UNetPreset>,
    /// 2D network size without weights.
    #[arg(long, global = true, value_enum)]
    pub vit: Option<VitPreset>,
    /// DINOv2 weights (safetensors) for the frozen 2D network.
    #[arg(long, global = true)]
    pub image_weights: Option<PathBuf>,
    /// Superpixel pooling at every n-th pixel (1 = all, as the official code).
    #[arg(long, global = true)]
    pub pixel_stride: Option<usize>,
    /// Peak learning rate.
    #[arg(long)]
    pub lr: Option<f64>,
    /// Seed of the initial weights.
    #[arg(long, global = true)]
    pub seed: Option<u64>,
    /// Compute backend: flex (CPU), wgpu (build with --features wgpu), cuda (--features cuda).
    #[arg(long, value_enum, default_value_t = Backend::Flex, global = true)]
    pub backend: Backend,
    /// GPU index for cuda (wgpu takes the best adapter; set CUBECL_WGPU_DEFAULT_DEVICE to
    /// choose another).
    #[arg(long, default_value_t = 0, global = true)]
    pub device_index: usize,
    /// Output directory: checkpoints/, metrics.jsonl, losses.svg [default: runs/<run>
    /// or runs/<run>-rank<r>]; with --ddp rank r writes rank-r/metrics.jsonl there and
    /// rank 0 the checkpoints.
    #[arg(long)]
    pub out: Option<PathBuf>,
    /// Save a checkpoint every this many steps (0 = only at the end).
    #[arg(long)]
    pub checkpoint_every: Option<u64>,
    /// Continue from the newest checkpoint in the output directory, asking the pipeline
    /// for the batch that follows it.
    #[arg(long)]
    pub resume: bool,
    /// Write losses.svg (the loss curves) at the end.
    #[arg(long)]
    pub plot: bool,
    /// Give up when no batch arrives for this long, seconds.
    #[arg(long, default_value_t = 300)]
    pub timeout_secs: u64,
    /// Synchronous data parallelism over MPI: run every rank under `mpirun -np W` (or
    /// `srun --mpi=pmix`); rank and world size come from MPI, each rank reads the shard
    /// stream of its rank on its host, gradients are averaged over the ranks every step
    /// (all ranks hold the same model), rank 0 writes the checkpoints.
    #[arg(long, conflicts_with_all = ["rank", "world_size"])]
    pub ddp: bool,
    /// `--ddp`: abort the job when a collective (gradient all-reduce, checkpoint
    /// agreement) waits longer than this for the other ranks (a hung peer), seconds.
    /// Keep it above --timeout-secs: a peer may be waiting that long for its batch.
    #[arg(long, default_value_t = 900)]
    pub collective_timeout_secs: u64,
    /// Isolates this deployment's iceoryx2 resources (also `SUPERFLOW_IOX_PREFIX`).
    #[arg(long, env = "SUPERFLOW_IOX_PREFIX")]
    pub iox_prefix: Option<String>,
}

/// What else the binary does besides training on a stream.
#[derive(Debug, clap::Subcommand)]
pub enum Sub {
    /// Trains a few steps on one batch file on several backends from the same initial
    /// weights and compares their losses (a GPU backend against the CPU's `flex`): the
    /// check before a long run on a new machine. Network flags (--unet, --vit,
    /// --pixel-stride, --config, --seed, --steps [default 3]) apply.
    Check(CheckArgs),
    /// Scores a 3D backbone downstream: per-point semantic segmentation of the labelled
    /// sweeps of DRIVES, split by time into train and validation, a linear classifier on
    /// the frozen backbone's features (or `--finetune`: the whole network), mIoU and
    /// per-class IoU on the validation sweeps.
    Probe(ProbeArgs),
    /// Writes a backbone's per-point features over the keyframe sweeps of DRIVES as an
    /// MCAP file that Foxglove opens: each sweep's points coloured by the features' top
    /// three principal components (fitted once over every sweep), and with --query, by
    /// each point's cosine similarity to the point nearest the query.
    Features(FeaturesArgs),
}

/// `superflow-trainer features`.
#[derive(Debug, clap::Args)]
pub struct FeaturesArgs {
    /// Drives: MCAP files or directories of them.
    #[arg(long, num_args = 1.., required = true)]
    pub mcap: Vec<PathBuf>,
    /// The backbone: a run's checkpoint directory (its newest checkpoint), one `step-N`
    /// directory, or `random` (an untrained network of --unet/--config).
    #[arg(long)]
    pub checkpoint: String,
    /// The MCAP file to write.
    #[arg(long)]
    pub out: PathBuf,
    /// A point `x,y,z` (metres, in the LiDAR frame of the first sweep): every point's
    /// similarity to the feature of the point nearest it, as a heat colour.
    #[arg(long, value_parser = parse_point, allow_hyphen_values = true)]
    pub query: Option<[f32; 3]>,
    /// Also a bird's-eye PNG of the first sweep in its principal-component colours
    /// (80 m across, the LiDAR at the centre, forward up).
    #[arg(long)]
    pub bev: Option<PathBuf>,
    /// Also each camera's image nearest every keyframe sweep, resized as training resizes
    /// it, and the 2D network's patch features coloured by their principal components
    /// (the network of --image-weights, else a random one of --vit).
    #[arg(long)]
    pub images: bool,
    /// The pipeline's configuration (channels, de-skew, voxel grid) [default: the
    /// pipeline's defaults].
    #[arg(long)]
    pub pipeline_config: Option<PathBuf>,
    /// One sweep per this many seconds per drive.
    #[arg(long, default_value_t = superflow_schemas::time::KEYFRAME_INTERVAL_SECS)]
    pub keyframe_interval_secs: f64,
}

/// `x,y,z` as three finite numbers.
fn parse_point(s: &str) -> Result<[f32; 3], String> {
    let values: Vec<f32> = s
        .split(',')
        .map(|v| v.trim().parse::<f32>().map_err(|e| format!("`{v}`: {e}")))
        .collect::<Result<_, _>>()?;
    match values[..] {
        [x, y, z] if values.iter().all(|v| v.is_finite()) => Ok([x, y, z]),
        _ => Err(format!("`{s}`: expected three finite numbers x,y,z")),
    }
}

/// `superflow-trainer probe`.
#[derive(Debug, clap::Args)]
pub struct ProbeArgs {
    /// Labelled drives: MCAP files or directories of them (labels in the LiDAR clouds or
    /// in `<drive>.labels.mcap` sidecars).
    #[arg(long, num_args = 1.., required = true)]
    pub mcap: Vec<PathBuf>,
    /// The backbone: a run's checkpoint directory (its newest checkpoint), one `step-N`
    /// directory, or `random` (an untrained network of --unet/--config, for the
    /// baseline).
    #[arg(long)]
    pub checkpoint: String,
    /// The pipeline's configuration (channels, de-skew, voxel grid, `[labels]`: field,
    /// mapping, classes, ignore index) [default: the pipeline's defaults].
    #[arg(long)]
    pub pipeline_config: Option<PathBuf>,
    /// Train the whole network with a linear classifier instead of a linear classifier on
    /// frozen features.
    #[arg(long)]
    pub finetune: bool,
    /// Share of the training sweeps used (few-label protocols: 0.01, 0.1).
    #[arg(long, default_value_t = 1.0)]
    pub label_fraction: f64,
    /// Passes over the training data [default: 20, fine-tuning 10].
    #[arg(long)]
    pub epochs: Option<usize>,
    /// Learning rate [default: 1e-2 linear probe, 1e-3 fine-tuning].
    #[arg(long = "probe-lr")]
    pub probe_lr: Option<f64>,
    /// Share of each drive's time span, at its end, scored as validation.
    #[arg(long, default_value_t = 0.25)]
    pub val_fraction: f64,
    /// Validation drives of their own (e.g. nuScenes' val scenes): every labelled sweep of
    /// --mcap trains, every one of these is scored (--val-fraction and --gap-secs unused).
    #[arg(long, num_args = 1..)]
    pub val_mcap: Vec<PathBuf>,
    /// Seconds of sweeps left out between the training and validation parts.
    #[arg(long, default_value_t = 1.0)]
    pub gap_secs: f64,
    /// One labelled sweep per this many seconds (nuScenes labels its 2 Hz keyframes).
    #[arg(long, default_value_t = superflow_schemas::time::KEYFRAME_INTERVAL_SECS)]
    pub keyframe_interval_secs: f64,
    /// Most training points of the linear probe (evenly strided beyond).
    #[arg(long, default_value_t = 1_000_000)]
    pub max_train_points: usize,
    /// Print the report as JSON on stdout (`{"miou", "per_class", "points", "split", …}`).
    #[arg(long)]
    pub json: bool,
}

/// `superflow-trainer check`.
#[derive(Debug, clap::Args)]
pub struct CheckArgs {
    /// Batch file written by `superflow-pipeline batch`.
    #[arg(long)]
    pub batch: PathBuf,
    /// Backends to run, comma-separated; the first is the reference.
    #[arg(long, value_enum, value_delimiter = ',', default_values_t = [Backend::Flex, Backend::Wgpu])]
    pub backends: Vec<Backend>,
    /// Largest relative difference of any loss term of any step from the reference.
    #[arg(long, default_value_t = 1e-3)]
    pub tolerance: f64,
    /// Also write the results as JSON to this file.
    #[arg(long)]
    pub json: Option<PathBuf>,
}

impl Args {
    /// The configuration flags. `check --steps` counts the steps to compare, not the
    /// schedule's length, so it overrides nothing there.
    pub fn overrides(&self) -> Overrides {
        Overrides {
            steps: self.steps.filter(|_| self.command.is_none()),
            unet: self.unet,
            vit: self.vit,
            image_weights: self.image_weights.clone(),
            pixel_stride: self.pixel_stride,
            lr: self.lr,
            seed: self.seed,
            checkpoint_every: self.checkpoint_every,
        }
    }

    /// `--config` (or the defaults) with the flags applied, validated.
    pub fn config(&self) -> anyhow::Result<TrainerConfig> {
        TrainerConfig::resolve(self.config.as_deref(), &self.overrides()).context("configuration")
    }

    /// What the flags say about the run besides its configuration.
    pub fn run_options(&self) -> RunOptions {
        RunOptions {
            run: self.run.clone(),
            rank: self.rank,
            world_size: self.world_size,
            out: self.out.clone(),
            resume: self.resume,
            plot: self.plot,
            timeout_secs: self.timeout_secs,
            ddp: self.ddp,
            collective_timeout_secs: self.collective_timeout_secs,
            iox_prefix: self.iox_prefix.clone(),
            backend: self.backend,
            device_index: self.device_index,
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn flags_override_the_file_and_check_steps_do_not_set_the_schedule() {
        let args = Args::parse_from([
            "superflow-trainer",
            "--steps",
            "7",
            "--unet",
            "tiny",
            "--lr",
            "0.5",
        ]);
        let c = args.config().expect("valid");
        assert_eq!(
            (c.optim.steps, c.model.unet, c.optim.lr),
            (7, UNetPreset::Tiny, 0.5)
        );
        let check = Args::parse_from([
            "superflow-trainer",
            "check",
            "--batch",
            "b.bin",
            "--steps",
            "7",
        ]);
        assert_eq!(
            check.config().expect("valid").optim.steps,
            TrainerConfig::default().optim.steps
        );
        let o = Args::parse_from([
            "superflow-trainer",
            "--run",
            "r",
            "--rank",
            "1",
            "--world-size",
            "2",
        ])
        .run_options();
        assert_eq!(
            (o.run.as_str(), o.rank, o.world_size),
            ("r", Some(1), Some(2))
        );
    }
}
