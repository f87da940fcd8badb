//! Data-parallel training over MPI (`superflow-trainer --ddp`): step time with 1 and 2
//! ranks on the same batch, and the gradient all-reduce's cost per MB.
//!
//! `cargo bench -p superflow-tests --bench ddp [-- --presets tiny,minkunet18 --steps N
//! --ranks 1,2 --reps N]`; the table goes to stdout, progress to stderr. Needs Open MPI's
//! `mpirun`. This bench runs itself under `mpirun -np R` (worker mode) for every rank
//! count:
//!
//! * **steps**: every rank builds the preset's trainer on the CPU (burn `flex`, rank 0's
//!   parameters broadcast), takes one warm-up step, then N timed `Trainer::step_synced`
//!   steps on the same real batch of 4 samples (keyframes 0..4 of `street_ros2`; each
//!   rank holds a batch of 4, so 2 ranks train 8 samples a step): median ms per step,
//!   the all-reduce's part (flatten, `MPI_Allreduce`, unflatten) and the job's samples/s.
//!   On one machine the ranks share its cores: the rows show the cost of the exchange,
//!   not a speed-up.
//! * **all-reduce**: `MPI_Allreduce` (sum) of f32 buffers of 1, 16 MB and the size of
//!   the MinkUNet-34 + head gradient buffer, median of `--reps` (default 5) after one
//!   warm-up: ms and ms per MB.

#![allow(clippy::unwrap_used, clippy::expect_used)]

use anyhow::Context as _;
use burn::module::Module;
use std::time::{Duration, Instant};
use superflow_pipeline::config::PipelineConfig;
use superflow_pipeline::drive::Dataset;
use superflow_tests::bench::common::{self, arg_count, arg_value, cores, load_average, median};
use superflow_tests::bench::train::{self, BATCH_SIZE, BatchFile, DRIVE, Preset};
use superflow_tests::process::mpirun;
use superflow_trainer::ddp::Ddp;
use superflow_trainer::model::SuperFlowModel;
use superflow_trainer::unet::UNetPreset;

const WORKER: &str = "SUPERFLOW_DDP_BENCH_WORKER";
const MB: usize = 1 << 20;

/// The worker's result line: `RESULT <kind> <fields…>`, printed by rank 0.
fn worker() -> anyhow::Result<()> {
    let ddp = Ddp::init(Duration::from_secs(1800))?;
    let steps = arg_count("--steps")?.unwrap_or(4);
    let reps = arg_count("--reps")?.unwrap_or(5);
    let batch = BatchFile::read(&common::root().join("target/superflow-bench-batch.bin"))?;
    for preset in train::presets(&arg_value("--presets").unwrap_or_else(|| "tiny".into()))? {
        step_times(&ddp, &preset, &batch, steps)?;
    }
    all_reduce_times(&ddp, reps);
    Ok(())
}

fn step_times(ddp: &Ddp, preset: &Preset, batch: &BatchFile, steps: usize) -> anyhow::Result<()> {
    let (mut trainer, _) = train::new_trainer(preset)?;
    let model = ddp.broadcast_bytes(trainer.model_bytes()?, "parameters");
    trainer.restore_bytes(model, Vec::new(), 0, std::path::Path::new("rank 0"))?;
    let view = batch.view()?;
    let mut times = Vec::new();
    let mut reduce = Vec::new();
    let mut bytes = 0;
    for i in 0..=steps {
        let what = format!("step {i}");
        let mut sum = |values: &mut [f32]| ddp.all_reduce_sum(values, &what);
        let outcome = trainer.step_synced(Some(&view), Some(&mut sum))?;
        if i > 0 {
            times.push(outcome.seconds * 1e3);
            reduce.push(outcome.phases.reduce * 1e3);
        }
        bytes = outcome.global.as_ref().map_or(0, |g| g.bytes);
        if ddp.rank() == 0 {
            eprintln!(
                "{} ranks, {}: step {i}/{steps} {:.0} ms (all-reduce {:.1} ms)",
                ddp.size(),
                preset.name,
                outcome.seconds * 1e3,
                outcome.phases.reduce * 1e3
            );
        }
    }
    // The slowest rank sets the pace.
    let slowest = ddp.all_gather(&[(median(&times) * 1e3) as u64], "times");
    let ms = *slowest.iter().max().unwrap() as f64 / 1e3;
    if ddp.rank() == 0 {
        println!(
            "RESULT step {} {} {ms:.1} {:.1} {:.1}",
            preset.name,
            ddp.size(),
            median(&reduce),
            bytes as f64 / MB as f64
        );
    }
    Ok(())
}

fn all_reduce_times(ddp: &Ddp, reps: usize) {
    let device = burn::tensor::Device::flex();
    let model = SuperFlowModel::new(
        &superflow_trainer::unet::UNetConfig::preset(UNetPreset::Minkunet34),
        384,
        0,
        &device,
    );
    let minkunet34 = model.num_params() * 4;
    for (label, len) in [
        ("1 MB", MB),
        ("16 MB", 16 * MB),
        ("MinkUNet-34", minkunet34),
    ] {
        let mut values = vec![1.0f32; len / 4];
        let mut times = Vec::new();
        for i in 0..=reps {
            ddp.barrier("before the all-reduce");
            let t = Instant::now();
            ddp.all_reduce_sum(&mut values, "bench all-reduce");
            if i > 0 {
                times.push(t.elapsed().as_secs_f64() * 1e3);
            }
        }
        let slowest = ddp.all_gather(&[(median(&times) * 1e3) as u64], "times");
        let ms = *slowest.iter().max().unwrap() as f64 / 1e3;
        if ddp.rank() == 0 {
            println!(
                "RESULT reduce {} {} {:.1} {ms:.2}",
                label.replace(' ', "_"),
                ddp.size(),
                len as f64 / MB as f64
            );
        }
    }
}

fn main() -> anyhow::Result<()> {
    if std::env::var_os(WORKER).is_some() {
        return worker();
    }
    let ranks: Vec<usize> = arg_value("--ranks")
        .unwrap_or_else(|| "1,2".into())
        .split(',')
        .map(|r| r.parse().context("--ranks: a list of counts"))
        .collect::<anyhow::Result<_>>()?;
    let config = PipelineConfig::default();
    let drive = common::root().join(DRIVE);
    let dataset = Dataset::open(std::slice::from_ref(&drive), &config.ingest)
        .with_context(|| format!("opening {}", drive.display()))?;
    train::build_batch(
        &dataset,
        &config,
        &common::root().join("target/superflow-bench-batch.bin"),
    )?;
    let exe = std::env::current_exe()?;
    let forwarded: Vec<String> = std::env::args()
        .skip(1)
        .filter(|a| a != "--bench")
        .collect();
    let mut steps = Vec::new();
    let mut reduces = Vec::new();
    for &n in &ranks {
        eprintln!("mpirun -np {n} …");
        let out = mpirun(n)
            .arg(&exe)
            .args(&forwarded)
            .env(WORKER, "1")
            .stderr(std::process::Stdio::inherit())
            .output()
            .context("mpirun (install openmpi-bin)")?;
        anyhow::ensure!(out.status.success(), "mpirun -np {n} failed");
        for line in String::from_utf8_lossy(&out.stdout).lines() {
            let fields: Vec<&str> = line.split_whitespace().collect();
            match fields.as_slice() {
                ["RESULT", "step", rest @ ..] => steps.push(rest.join(" ")),
                ["RESULT", "reduce", rest @ ..] => reduces.push(rest.join(" ")),
                _ => {}
            }
        }
    }
    println!(
        "\nMachine: {} cores, load {}; Open MPI on one host (shared memory); burn flex (CPU).\n",
        cores(),
        load_average(1)
    );
    println!(
        "| preset | ranks | ms / step | all-reduce ms | gradient buffer MB | samples/s (job) |"
    );
    println!("|---|---:|---:|---:|---:|---:|");
    for row in &steps {
        let f: Vec<&str> = row.split(' ').collect();
        let (ranks, ms): (f64, f64) = (f[1].parse()?, f[2].parse()?);
        let rate = ranks * BATCH_SIZE as f64 / (ms / 1e3);
        println!(
            "| {} | {} | {} | {} | {} | {rate:.2} |",
            f[0], f[1], f[2], f[3], f[4]
        );
    }
    println!("\n| all-reduce (sum, f32) | ranks | MB | ms | ms per MB |");
    println!("|---|---:|---:|---:|---:|");
    for row in &reduces {
        let f: Vec<&str> = row.split(' ').collect();
        let (mb, ms): (f64, f64) = (f[2].parse()?, f[3].parse()?);
        println!(
            "| {} | {} | {mb:.1} | {ms:.2} | {:.3} |",
            f[0].replace('_', " "),
            f[1],
            ms / mb
        );
    }
    Ok(())
}
