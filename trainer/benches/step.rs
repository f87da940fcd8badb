//! Training-step throughput of `superflow-trainer` on the CPU (burn `flex`), next to the
//! PyTorch CPU implementation of the same model on the same batch, and the data-stall
//! fraction when the batches stream from the real pipeline service.
//!
//! 1. The batch: `--batch FILE` (written by `superflow-pipeline batch`), else keyframes
//!    0..4 of `recordings/drives/street_ros2.mcap` at epoch 0 with the default recipe,
//!    built in-process and saved to `target/superflow-bench-batch.bin` so that the PyTorch
//!    side reads the same bytes.
//! 2. Compute only: `Trainer::new` on `Device::flex()`, one warm-up step, then N timed
//!    steps on that batch: median ms/step, steps/s, samples/s and the phase split.
//! 3. PyTorch: `trainer/reference/bench_torch.py` on the batch file, same preset and
//!    pixel stride, one warm-up step, N timed steps, as many threads as cores.
//! 4. Streaming: the pipeline service (`publish::serve`, broadcast, batch size 4, endless,
//!    its own iceoryx2 prefix `sfbench<pid>`) in a thread of this process, a
//!    `Subscription`, and `--stream-steps` steps of the (already warm) trainer on the
//!    received batches: time blocked in `receive` between batches over the wall time from
//!    the first batch's arrival = the data-stall fraction (the first batch's wait is the
//!    service's start-up, reported apart). The service is stopped and joined (shared
//!    memory released) before the next preset. The pipeline's sample building shares
//!    the cores (and here the rayon pool) with training.
//!
//! Presets: `tiny` (UNet tiny, ViT tiny, pixel stride 4), `minkunet18` (UNet minkunet18,
//! random ViT-S/14, pixel stride 1: the official full-resolution superpixel pooling),
//! `minkunet34` (as minkunet18 with the default UNet; not run by default).
//!
//! Default step counts keep the whole bench near 6-7 minutes on 2 cores, where one
//! minkunet18 step takes about a minute: tiny 4 timed + 5 streamed, minkunet18 (and
//! minkunet34) 1 timed + 2 streamed (two, so that one wait between batches is measured).
//! `--steps` / `--stream-steps` override them for every preset.
//!
//! `cargo bench -p superflow-trainer --bench step [-- --presets tiny,minkunet18 --steps N
//! --stream-steps N --batch FILE --torch PYTHON]` (PYTHON: also `SUPERFLOW_TORCH_PYTHON`,
//! default `python3`; without PyTorch that column says so).
//!
//! The batch, compute-only and streaming code is `tests/src/bench/train.rs`, shared with
//! `cargo bench -p superflow-tests --bench summary` (the one-table summary of all benches).

#![allow(clippy::unwrap_used, clippy::expect_used)]

#[allow(dead_code)]
#[path = "../../tests/src/bench/common.rs"]
mod common;
#[allow(dead_code)]
#[path = "../../tests/src/bench/train.rs"]
mod train;

use anyhow::Context as _;
use common::{arg_count, arg_value, cores, load_average, root};
use std::path::{Path, PathBuf};
use std::process::Command;
use std::time::Instant;
use superflow_pipeline::config::PipelineConfig;
use superflow_pipeline::drive::Dataset;
use superflow_pipeline::sample::SampleBuilder;
use superflow_schemas::batch::Section;
use train::{BATCH_SIZE, BatchFile, DRIVE, Preset};

#[derive(Debug)]
struct Args {
    presets: Vec<Preset>,
    steps: Option<usize>,
    stream_steps: Option<usize>,
    batch: Option<PathBuf>,
    torch: String,
}

impl Args {
    fn parse() -> anyhow::Result<Self> {
        Ok(Self {
            presets: train::presets(
                &arg_value("--presets").unwrap_or_else(|| "tiny,minkunet18".into()),
            )?,
            steps: arg_count("--steps")?,
            stream_steps: arg_count("--stream-steps")?,
            batch: arg_value("--batch").map(PathBuf::from),
            torch: arg_value("--torch")
                .or_else(|| std::env::var("SUPERFLOW_TORCH_PYTHON").ok())
                .unwrap_or_else(|| "python3".into()),
        })
    }
}

/// What `bench_torch.py --json` reports.
#[derive(Debug, Default)]
struct Torch {
    ms: f64,
    params: usize,
    params_3d: usize,
    prep_ms: f64,
    sampled_pixels: usize,
    phases: [f64; 4],
}

fn torch(
    python: &str,
    batch: &Path,
    preset: &Preset,
    steps: usize,
    threads: usize,
) -> anyhow::Result<Torch> {
    let importable = Command::new(python)
        .args(["-c", "import torch"])
        .output()
        .map(|o| o.status.success())
        .unwrap_or(false);
    if !importable {
        anyhow::bail!("PyTorch not installed (pip install torch to compare)");
    }
    let script = root().join("trainer/reference/bench_torch.py");
    eprintln!("{}: PyTorch ({python}, {threads} threads) ...", preset.name);
    let out = Command::new(python)
        .arg(&script)
        .arg("--batch")
        .arg(batch)
        .args(["--preset", preset.name])
        .args(["--pixel-stride", &preset.pixel_stride.to_string()])
        .args(["--steps", &steps.to_string(), "--warmup", "1"])
        .args(["--threads", &threads.to_string(), "--json"])
        .output()
        .map_err(|e| anyhow::anyhow!("PyTorch: running {python}: {e}"))?;
    let stderr = String::from_utf8_lossy(&out.stderr);
    for line in stderr
        .lines()
        .filter(|l| l.starts_with("step") || l.starts_with("preset"))
    {
        eprintln!("{}: PyTorch {line}", preset.name);
    }
    if !out.status.success() {
        let last = stderr.lines().last().unwrap_or("no output");
        anyhow::bail!("PyTorch failed ({}): {last}", out.status);
    }
    let stdout = String::from_utf8_lossy(&out.stdout);
    let line = stdout.lines().last().unwrap_or_default();
    let j: serde_json::Value = serde_json::from_str(line)
        .map_err(|e| anyhow::anyhow!("PyTorch: bad JSON {line:?}: {e}"))?;
    let f = |v: &serde_json::Value| v.as_f64().unwrap_or(f64::NAN);
    let u = |v: &serde_json::Value| v.as_u64().unwrap_or(0) as usize;
    let ph = &j["phases_ms"];
    Ok(Torch {
        ms: f(&j["ms_per_step_median"]),
        params: u(&j["params"]),
        params_3d: u(&j["params_3d"]),
        prep_ms: f(&j["prep_ms"]),
        sampled_pixels: u(&j["sampled_pixels"]),
        phases: [
            f(&ph["vit"]),
            f(&ph["forward"]),
            f(&ph["backward"]),
            f(&ph["update"]),
        ],
    })
}

fn ms(v: f64) -> String {
    if v.is_finite() {
        format!("{v:.0}")
    } else {
        "—".into()
    }
}

/// The `superflow-trainer` binary's allocator (mimalloc keeping freed pages).
#[global_allocator]
static ALLOCATOR: superflow_common::memory::Allocator = superflow_common::memory::Allocator;

fn main() -> anyhow::Result<()> {
    superflow_common::memory::keep_freed_pages();
    let args = Args::parse()?;
    let cores = cores();
    let load = load_average(1);
    let bench_started = Instant::now();

    let config = PipelineConfig::default();
    let drive = root().join(DRIVE);
    let dataset = Dataset::open(std::slice::from_ref(&drive), &config.ingest)
        .with_context(|| format!("opening {}", drive.display()))?;
    let (batch_path, source) = match &args.batch {
        Some(path) => (path.clone(), format!("{}", path.display())),
        None => {
            let out = root().join("target/superflow-bench-batch.bin");
            let t = Instant::now();
            train::build_batch(&dataset, &config, &out)?;
            eprintln!(
                "built the batch in {:.1} s: {}",
                t.elapsed().as_secs_f64(),
                out.display()
            );
            (
                out,
                format!("{DRIVE} keyframes 0..{BATCH_SIZE}, epoch 0, default recipe"),
            )
        }
    };
    let batch = BatchFile::read(&batch_path)?;
    let (samples, points, pairings, voxels, images) = {
        let view = batch.view()?;
        let images = view.section::<u8>(Section::Images)?.shape().to_vec();
        (
            view.meta().sample_count,
            view.section::<u32>(Section::PointToVoxel)?.data.len(),
            view.section::<u32>(Section::PairingPoint)?.data.len(),
            view.section::<f32>(Section::VoxelFeatures)?.shape()[0],
            images,
        )
    };
    println!("# superflow-trainer step bench");
    println!();
    println!(
        "machine: {cores} cores (load average {load} at start), burn flex (CPU); PyTorch: `{}`",
        args.torch
    );
    println!(
        "batch: {samples} samples, {points} points, {pairings} pairings, {voxels} level-0 voxels, {} images {}×{} ({source}; {} bytes at {})",
        images.first().copied().unwrap_or(0),
        images.get(1).copied().unwrap_or(0),
        images.get(2).copied().unwrap_or(0),
        batch.bytes(),
        batch.path.display()
    );

    let mut rows = Vec::new();
    let builder = SampleBuilder::new(&dataset, config.sample.clone())?;
    for preset in &args.presets {
        let steps = args.steps.unwrap_or(preset.steps);
        let stream_steps = args.stream_steps.unwrap_or(preset.stream_steps);
        let (mut trainer, init_s) = train::new_trainer(preset)?;
        let c = train::compute(&mut trainer, &batch, preset, steps, init_s)?;
        let py = torch(&args.torch, &batch.path, preset, steps, cores);
        let s = train::stream(&mut trainer, &builder, preset, stream_steps)?;
        rows.push((*preset, c, py, s));
    }

    println!();
    println!(
        "## Compute only (same batch every step; median of the timed steps after 1 warm-up; burn and PyTorch use all {cores} cores, one after the other)"
    );
    println!();
    println!(
        "| preset | pixel stride | params 3D | burn ms/step | burn steps/s | burn samples/s | PyTorch ms/step | PyTorch steps/s | burn/PyTorch | burn/PyTorch w/o inputs |"
    );
    println!("|---|---:|---:|---:|---:|---:|---:|---:|---:|---:|");
    for (p, c, py, _) in &rows {
        let burn_sps = 1e3 / c.ms;
        let (py_ms, py_sps, ratio, ratio_compute) = match py {
            Ok(t) => (
                ms(t.ms),
                format!("{:.3}", 1e3 / t.ms),
                format!("{:.2}×", c.ms / t.ms),
                format!("{:.2}×", (c.ms - c.phases.inputs) / t.ms),
            ),
            Err(e) => (e.to_string(), "—".into(), "—".into(), "—".into()),
        };
        println!(
            "| {} | {} | {} | {} | {burn_sps:.3} | {:.2} | {py_ms} | {py_sps} | {ratio} | {ratio_compute} |",
            p.name,
            p.pixel_stride,
            c.params_3d,
            ms(c.ms),
            burn_sps * f64::from(samples),
        );
    }
    println!();
    println!(
        "burn/PyTorch > 1: burn is slower. The burn step includes its `inputs` phase (batch → tensors, loss plan, pixel sampler), redone for every batch; PyTorch prepares its index tensors once, before the timed steps (\"prep\" below), so the last column compares the rest. Parameter counts are trainable ones (burn's `num_params` also counts the BatchNorm running statistics)."
    );
    for (p, c, py, _) in &rows {
        let check = match py {
            Ok(t) => format!(
                "PyTorch {} trainable ({} 3D){}, {} sampled pixels, prep {:.0} ms once",
                t.params,
                t.params_3d,
                if t.params == c.params && t.params_3d == c.params_3d {
                    ", same model"
                } else {
                    ", MODEL MISMATCH"
                },
                t.sampled_pixels,
                t.prep_ms
            ),
            Err(_) => "no PyTorch".into(),
        };
        println!(
            "- {}: {} steps timed; burn {} trainable parameters ({} 3D), Trainer::new {:.1} s, warm-up step {} ms; {check}",
            p.name,
            c.steps,
            c.params,
            c.params_3d,
            c.init_s,
            ms(c.warmup_ms)
        );
    }

    println!();
    println!("## Phase split (median ms per step)");
    println!();
    println!("| preset | implementation | inputs | ViT | forward | backward | update | step |");
    println!("|---|---|---:|---:|---:|---:|---:|---:|");
    for (p, c, py, _) in &rows {
        let ph = &c.phases;
        println!(
            "| {} | burn | {} | {} | {} | {} | {} | {} |",
            p.name,
            ms(ph.inputs),
            ms(ph.vit),
            ms(ph.forward),
            ms(ph.backward),
            ms(ph.update),
            ms(c.ms)
        );
        if let Ok(t) = py {
            println!(
                "| {} | PyTorch | (prep {} once) | {} | {} | {} | {} | {} |",
                p.name,
                ms(t.prep_ms),
                ms(t.phases[0]),
                ms(t.phases[1]),
                ms(t.phases[2]),
                ms(t.phases[3]),
                ms(t.ms)
            );
        }
    }
    println!();
    println!(
        "inputs: batch → tensors and loss plan; ViT: the frozen 2D network on every image; forward: 3D UNet, 2D head at the sampled pixels, losses; backward; update: AdamW."
    );

    println!();
    println!(
        "## Streaming from the pipeline service (in-process thread, broadcast, batch size {BATCH_SIZE}, endless)"
    );
    println!();
    println!(
        "The pipeline's sample building (rayon) shares the {cores} cores with training, as in the real deployment on this machine (here in one process: one rayon pool for both)."
    );
    println!();
    println!(
        "| preset | streamed steps | streamed steps/s | compute-only steps/s | data-stall fraction | mean wait ms | pipeline blocked on trainer | pipeline waiting for samples |"
    );
    println!("|---|---:|---:|---:|---:|---:|---:|---:|");
    for (p, c, _, s) in &rows {
        let waits = s.steps.saturating_sub(1).max(1) as f64;
        println!(
            "| {} | {} | {:.3} | {:.3} | {:.3} | {} | {:.2} | {:.2} |",
            p.name,
            s.steps,
            s.steps_per_second(),
            1e3 / c.ms,
            s.stall_fraction(),
            ms(s.waiting / waits * 1e3),
            s.blocked,
            s.starved
        );
    }
    println!();
    println!(
        "data-stall fraction: time blocked in `receive` / wall time, from the first batch's arrival to the end of the last step. The pipeline columns: shares of the service's run time its publisher was blocked on the trainer's full queue (trainer-bound) or waiting for sample building (pipeline-bound). Streamed batches are the epoch's shuffled keyframes, not the compute-only batch, so their step times differ."
    );
    for (p, _, _, s) in &rows {
        println!(
            "- {}: first batch {:.2} s after the service started (start-up, not in the fraction); window {:.1} s: {:.1} s computing, {:.2} s waiting; median streamed batch {:.0} points, {:.0} pairings, {:.0} voxels",
            p.name,
            s.first_batch_s,
            s.seconds,
            s.computing,
            s.waiting,
            s.counts[0],
            s.counts[1],
            s.counts[2]
        );
    }
    println!();
    let peak = std::fs::read_to_string("/proc/self/status")
        .ok()
        .and_then(|s| {
            s.lines()
                .find_map(|l| l.strip_prefix("VmHWM:"))
                .and_then(|v| v.trim().trim_end_matches("kB").trim().parse::<f64>().ok())
        })
        .map_or_else(|| "?".into(), |kb| format!("{:.1} GiB", kb / 1048576.0));
    println!(
        "bench wall time {:.0} s; peak memory of the burn process {peak} (PyTorch runs in its own process); load average {} at the end (1, 5, 15 min)",
        bench_started.elapsed().as_secs_f64(),
        load_average(3)
    );
    Ok(())
}
