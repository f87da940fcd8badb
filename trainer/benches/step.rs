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

#![allow(clippy::unwrap_used, clippy::expect_used)]

use anyhow::Context as _;
use burn::module::{Module, ModuleVisitor, Param};
use burn::tensor::Tensor;
use std::path::{Path, PathBuf};
use std::process::Command;
use std::sync::Arc;
use std::sync::atomic::{AtomicBool, Ordering};
use std::time::{Duration, Instant};
use superflow_pipeline::batch::{BatchShape, batch_bytes};
use superflow_pipeline::config::PipelineConfig;
use superflow_pipeline::drive::Dataset;
use superflow_pipeline::publish::{self, Metrics, Mode, ServiceConfig};
use superflow_pipeline::sample::SampleBuilder;
use superflow_schemas::batch::{BatchHeader, BatchMeta, BatchView};
use superflow_trainer::config::TrainerConfig;
use superflow_trainer::sparse::UNetPreset;
use superflow_trainer::subscribe::{Subscription, Target};
use superflow_trainer::train::{StepPhases, Trainer};
use superflow_trainer::vit::VitPreset;

/// Samples per batch (the paper's per-GPU batch, the service default).
const BATCH_SIZE: usize = 4;
const DRIVE: &str = "recordings/drives/street_ros2.mcap";

/// A benchmarked configuration.
#[derive(Debug, Clone, Copy)]
struct Preset {
    name: &'static str,
    unet: UNetPreset,
    vit: VitPreset,
    pixel_stride: usize,
    /// Default timed compute steps and streamed steps.
    steps: usize,
    stream_steps: usize,
}

const PRESETS: [Preset; 3] = [
    Preset {
        name: "tiny",
        unet: UNetPreset::Tiny,
        vit: VitPreset::Tiny,
        pixel_stride: 4,
        steps: 4,
        stream_steps: 5,
    },
    Preset {
        name: "minkunet18",
        unet: UNetPreset::Minkunet18,
        vit: VitPreset::Small,
        pixel_stride: 1,
        steps: 1,
        stream_steps: 2,
    },
    Preset {
        name: "minkunet34",
        unet: UNetPreset::Minkunet34,
        vit: VitPreset::Small,
        pixel_stride: 1,
        steps: 1,
        stream_steps: 2,
    },
];

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
        let argv: Vec<String> = std::env::args().skip(1).collect();
        let value = |name: &str| -> Option<String> {
            argv.iter()
                .position(|a| a == name)
                .and_then(|i| argv.get(i + 1))
                .cloned()
                .or_else(|| {
                    let prefix = format!("{name}=");
                    argv.iter()
                        .find_map(|a| a.strip_prefix(&prefix).map(str::to_owned))
                })
        };
        let count = |name: &str| -> anyhow::Result<Option<usize>> {
            value(name)
                .map(|v| {
                    v.parse::<usize>()
                        .ok()
                        .filter(|n| *n > 0)
                        .with_context(|| format!("{name} {v}: expected a positive integer"))
                })
                .transpose()
        };
        let presets = value("--presets")
            .unwrap_or_else(|| "tiny,minkunet18".into())
            .split(',')
            .filter(|s| !s.is_empty())
            .map(|name| {
                PRESETS
                    .iter()
                    .find(|p| p.name == name)
                    .copied()
                    .with_context(|| {
                        format!("unknown preset {name:?} (tiny, minkunet18, minkunet34)")
                    })
            })
            .collect::<anyhow::Result<Vec<_>>>()?;
        Ok(Self {
            presets,
            steps: count("--steps")?,
            stream_steps: count("--stream-steps")?,
            batch: value("--batch").map(PathBuf::from),
            torch: value("--torch")
                .or_else(|| std::env::var("SUPERFLOW_TORCH_PYTHON").ok())
                .unwrap_or_else(|| "python3".into()),
        })
    }
}

fn root() -> PathBuf {
    PathBuf::from(env!("CARGO_MANIFEST_DIR")).join("..")
}

/// A batch as it travels: header and payload (8-byte aligned, as in shared memory).
struct BatchFile {
    path: PathBuf,
    header: BatchHeader,
    payload: Vec<u64>,
    len: usize,
}

impl BatchFile {
    fn read(path: &Path) -> anyhow::Result<Self> {
        let bytes = std::fs::read(path).with_context(|| format!("reading {}", path.display()))?;
        let header = BatchHeader::from_bytes(&bytes)
            .with_context(|| format!("{}: shorter than a batch header", path.display()))?;
        let body = &bytes[BatchHeader::SIZE..];
        let mut payload = vec![0u64; body.len().div_ceil(8)];
        bytemuck::cast_slice_mut::<u64, u8>(&mut payload)[..body.len()].copy_from_slice(body);
        let file = Self {
            path: path.to_path_buf(),
            header,
            payload,
            len: body.len(),
        };
        file.view()
            .with_context(|| format!("{} is not a valid batch", path.display()))?;
        Ok(file)
    }

    fn view(&self) -> anyhow::Result<BatchView<'_>> {
        let bytes = &bytemuck::cast_slice::<u64, u8>(&self.payload)[..self.len];
        Ok(BatchView::new(&self.header, bytes)?)
    }
}

/// Builds keyframes 0..4 of the drive at epoch 0 as `superflow-pipeline batch` does and
/// writes the file.
fn build_batch(dataset: &Dataset, config: &PipelineConfig, out: &Path) -> anyhow::Result<()> {
    let builder = SampleBuilder::new(dataset, config.sample.clone())?;
    let keyframes = builder.plan().keyframes.len();
    anyhow::ensure!(
        keyframes >= BATCH_SIZE,
        "{DRIVE} has {keyframes} keyframes, {BATCH_SIZE} needed"
    );
    let samples = (0..BATCH_SIZE)
        .map(|k| builder.build_keyframe(k, 0, k as u64))
        .collect::<Result<Vec<_>, _>>()?;
    let c = builder.config();
    let meta = BatchMeta {
        run: "bench".into(),
        epoch: 0,
        step: 0,
        seed: c.seed,
        sequence: 0,
        created_unix_nanos: 0,
        sample_count: BATCH_SIZE as u32,
        flags: 0,
    };
    let bytes = batch_bytes(&samples, BatchShape::of(c), &meta)?;
    if let Some(dir) = out.parent() {
        std::fs::create_dir_all(dir)?;
    }
    std::fs::write(out, &bytes).with_context(|| format!("writing {}", out.display()))?;
    Ok(())
}

fn median(values: &[f64]) -> f64 {
    if values.is_empty() {
        return f64::NAN;
    }
    let mut v = values.to_vec();
    v.sort_by(f64::total_cmp);
    let n = v.len();
    if n % 2 == 1 {
        v[n / 2]
    } else {
        (v[n / 2 - 1] + v[n / 2]) / 2.0
    }
}

/// Counts trainable parameters: burn's `num_params` also counts the BatchNorm running
/// statistics (module state, not optimized), which PyTorch keeps as buffers.
#[derive(Debug, Default)]
struct Trainable {
    path: Vec<String>,
    count: usize,
}

impl ModuleVisitor for Trainable {
    fn enter_module(&mut self, name: &str, _container_type: &str) {
        self.path.push(name.to_owned());
    }

    fn exit_module(&mut self, _name: &str, _container_type: &str) {
        self.path.pop();
    }

    fn visit_float<const D: usize>(&mut self, param: &Param<Tensor<D>>) {
        let running = matches!(
            self.path.last().map(String::as_str),
            Some("running_mean" | "running_var")
        );
        if !running {
            self.count += param.val().dims().iter().product::<usize>();
        }
    }
}

fn trainable<M: Module>(module: &M) -> usize {
    let mut visitor = Trainable::default();
    module.visit(&mut visitor);
    visitor.count
}

fn trainer_config(preset: &Preset) -> TrainerConfig {
    let mut c = TrainerConfig::default();
    c.model.unet = preset.unet;
    c.model.vit = preset.vit;
    c.loss.pixel_stride = preset.pixel_stride;
    c.optim.steps = 1000;
    c
}

/// Compute-only timing of one preset.
#[derive(Debug)]
struct Compute {
    params_3d: usize,
    params: usize,
    steps: usize,
    ms: f64,
    phases: StepPhases,
    init_s: f64,
    warmup_ms: f64,
}

/// Medians of each phase, in ms.
fn median_phases(all: &[StepPhases]) -> StepPhases {
    let m = |f: fn(&StepPhases) -> f64| median(&all.iter().map(|p| f(p) * 1e3).collect::<Vec<_>>());
    StepPhases {
        inputs: m(|p| p.inputs),
        vit: m(|p| p.vit),
        forward: m(|p| p.forward),
        backward: m(|p| p.backward),
        update: m(|p| p.update),
    }
}

fn compute(
    trainer: &mut Trainer,
    batch: &BatchFile,
    preset: &Preset,
    steps: usize,
    init_s: f64,
) -> anyhow::Result<Compute> {
    let view = batch.view()?;
    let t = Instant::now();
    trainer.step(&view).context("warm-up step")?;
    let warmup_ms = t.elapsed().as_secs_f64() * 1e3;
    eprintln!("{}: burn warm-up step {warmup_ms:.0} ms", preset.name);
    let mut times = Vec::with_capacity(steps);
    let mut phases = Vec::with_capacity(steps);
    for i in 0..steps {
        let outcome = trainer.step(&view)?;
        eprintln!(
            "{}: burn step {}/{steps} {:.0} ms (loss {:.4})",
            preset.name,
            i + 1,
            outcome.seconds * 1e3,
            outcome.losses.total
        );
        times.push(outcome.seconds * 1e3);
        phases.push(outcome.phases);
    }
    Ok(Compute {
        params_3d: trainable(&trainer.model().unet),
        params: trainable(trainer.model()),
        steps,
        ms: median(&times),
        phases: median_phases(&phases),
        init_s,
        warmup_ms,
    })
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
) -> Result<Torch, String> {
    let importable = Command::new(python)
        .args(["-c", "import torch"])
        .output()
        .map(|o| o.status.success())
        .unwrap_or(false);
    if !importable {
        return Err("PyTorch not installed (pip install torch to compare)".into());
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
        .map_err(|e| format!("PyTorch: running {python}: {e}"))?;
    let stderr = String::from_utf8_lossy(&out.stderr);
    for line in stderr
        .lines()
        .filter(|l| l.starts_with("step") || l.starts_with("preset"))
    {
        eprintln!("{}: PyTorch {line}", preset.name);
    }
    if !out.status.success() {
        let last = stderr.lines().last().unwrap_or("no output");
        return Err(format!("PyTorch failed ({}): {last}", out.status));
    }
    let stdout = String::from_utf8_lossy(&out.stdout);
    let line = stdout.lines().last().unwrap_or_default();
    let j: serde_json::Value =
        serde_json::from_str(line).map_err(|e| format!("PyTorch: bad JSON {line:?}: {e}"))?;
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

/// Streaming timing of one preset.
#[derive(Debug)]
struct Stream {
    steps: usize,
    /// From the first batch's arrival to the end of the last step.
    seconds: f64,
    /// Blocked in `receive`, after the first batch.
    waiting: f64,
    computing: f64,
    /// Start-up: from the service's start to the first batch.
    first_batch_s: f64,
    /// Shares of the service's run time its publisher spent blocked on the trainer's
    /// full queue (backpressure) and waiting for the sample builders.
    blocked: f64,
    starved: f64,
    /// Median points, pairings, level-0 voxels of the streamed batches.
    counts: [f64; 3],
}

type Batch = superflow_trainer::subscribe::Received;

fn stream(
    trainer: &mut Trainer,
    builder: &SampleBuilder<'_>,
    preset: &Preset,
    steps: usize,
) -> anyhow::Result<Stream> {
    let prefix = format!("sfbench{}", std::process::id());
    let iox = superflow_schemas::service::iceoryx2_config(Some(&prefix))
        .map_err(|e| anyhow::anyhow!(e))?;
    let run = format!("bench-{}", preset.name);
    let service = ServiceConfig {
        mode: Mode::Broadcast,
        batch_size: BATCH_SIZE as u32,
        epochs: 0,
        ..ServiceConfig::default()
    };
    let stop = Arc::new(AtomicBool::new(false));
    let metrics = Arc::new(Metrics::default());
    let subscription = Subscription::open(&run, Target::Broadcast, &iox, 2)?;
    let service_started = Instant::now();
    let (measured, served, service_s) = std::thread::scope(|scope| {
        let server =
            scope.spawn(|| publish::serve(builder, &run, &service, &iox, (0, 0), &stop, &metrics));
        let receive = || -> anyhow::Result<(Batch, f64)> {
            let t = Instant::now();
            loop {
                if let Some(batch) = subscription.receive(Duration::from_millis(500))? {
                    return Ok((batch, t.elapsed().as_secs_f64()));
                }
                anyhow::ensure!(!server.is_finished(), "the pipeline service ended");
                anyhow::ensure!(
                    t.elapsed() < Duration::from_secs(300),
                    "no batch within 300 s"
                );
            }
        };
        let measured = (|| -> anyhow::Result<Stream> {
            // The first batch's wait is the service's start-up, reported apart; the
            // window starts when it arrives (the trainer is already warm).
            let (mut batch, first_batch_s) = receive()?;
            let started = Instant::now();
            let (mut waiting, mut computing) = (0.0, 0.0);
            let mut counts: [Vec<f64>; 3] = Default::default();
            for i in 0..steps {
                let outcome = trainer.step(&batch.view()?)?;
                drop(batch);
                computing += outcome.seconds;
                for (all, c) in counts.iter_mut().zip(outcome.counts) {
                    all.push(c as f64);
                }
                let [points, pairings, voxels] = outcome.counts;
                eprintln!(
                    "{}: streamed step {}/{steps}: {:.0} ms ({points} points, {pairings} pairings, {voxels} voxels)",
                    preset.name,
                    i + 1,
                    outcome.seconds * 1e3,
                );
                if i + 1 == steps {
                    break;
                }
                let (next, wait) = receive()?;
                waiting += wait;
                eprintln!(
                    "{}: waited {:.0} ms for the next batch",
                    preset.name,
                    wait * 1e3
                );
                batch = next;
            }
            Ok(Stream {
                steps,
                seconds: started.elapsed().as_secs_f64(),
                waiting,
                computing,
                first_batch_s,
                blocked: 0.0,
                starved: 0.0,
                counts: counts.map(|c| median(&c)),
            })
        })();
        // Whatever happened, the service stops (releasing its shared memory) and its
        // thread ends before we return.
        stop.store(true, Ordering::SeqCst);
        let served = server.join();
        (measured, served, service_started.elapsed().as_secs_f64())
    });
    drop(subscription);
    let mut measured = measured?;
    match served {
        Ok(Ok(())) => {}
        Ok(Err(e)) => anyhow::bail!("pipeline service: {e}"),
        Err(_) => anyhow::bail!("the pipeline service panicked"),
    }
    let share = |nanos: &std::sync::atomic::AtomicU64| {
        nanos.load(Ordering::Relaxed) as f64 / 1e9 / service_s
    };
    measured.blocked = share(&metrics.backpressure_nanos);
    measured.starved = share(&metrics.wait_for_build_nanos);
    Ok(measured)
}

fn ms(v: f64) -> String {
    if v.is_finite() {
        format!("{v:.0}")
    } else {
        "—".into()
    }
}

/// The first `n` load averages of `/proc/loadavg`.
fn load_average(n: usize) -> String {
    std::fs::read_to_string("/proc/loadavg")
        .map(|s| s.split_whitespace().take(n).collect::<Vec<_>>().join(", "))
        .unwrap_or_else(|_| "?".into())
}

fn main() -> anyhow::Result<()> {
    let args = Args::parse()?;
    let cores = std::thread::available_parallelism().map_or(1, |c| c.get());
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
            build_batch(&dataset, &config, &out)?;
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
        let images = view.get::<u8>("images")?.shape().to_vec();
        (
            view.meta().sample_count,
            view.get::<u32>("point_to_voxel")?.data.len(),
            view.get::<u32>("pairing_point")?.data.len(),
            view.get::<f32>("voxel_features")?.shape()[0],
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
        BatchHeader::SIZE + batch.len,
        batch.path.display()
    );

    let mut rows = Vec::new();
    let builder = SampleBuilder::new(&dataset, config.sample.clone())?;
    for preset in &args.presets {
        let steps = args.steps.unwrap_or(preset.steps);
        let stream_steps = args.stream_steps.unwrap_or(preset.stream_steps);
        let t = Instant::now();
        let mut trainer = Trainer::new(trainer_config(preset), &burn::tensor::Device::flex())?;
        let init_s = t.elapsed().as_secs_f64();
        let c = compute(&mut trainer, &batch, preset, steps, init_s)?;
        let py = torch(&args.torch, &batch.path, preset, steps, cores);
        let s = stream(&mut trainer, &builder, preset, stream_steps)?;
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
            Err(e) => (e.clone(), "—".into(), "—".into(), "—".into()),
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
            s.steps as f64 / s.seconds,
            1e3 / c.ms,
            s.waiting / s.seconds,
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
