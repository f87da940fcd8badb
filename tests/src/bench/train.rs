//! Training-step measurements of `superflow-trainer` on the CPU (burn `flex`): the
//! benchmark presets, one real batch built from a sample drive, compute-only steps on
//! it, and steps streamed from the real pipeline service in this process (the
//! data-stall fraction).
//!
//! Used by `cargo bench -p superflow-trainer --bench step` (through `#[path]`, next to
//! `common.rs` as `super::common`) and by the summary bench of `superflow-tests`.

use super::common::median;
use anyhow::Context as _;
use burn::module::{Module, ModuleVisitor, Param};
use burn::tensor::Tensor;
use std::path::Path;
use std::sync::Arc;
use std::sync::atomic::{AtomicBool, Ordering};
use std::time::{Duration, Instant};
use superflow_pipeline::batch::{BatchShape, batch_bytes};
use superflow_pipeline::config::PipelineConfig;
use superflow_pipeline::drive::Dataset;
use superflow_pipeline::publish::{self, Metrics, Mode, ServiceConfig};
use superflow_pipeline::sample::SampleBuilder;
use superflow_schemas::batch::BatchMeta;
use superflow_trainer::config::TrainerConfig;
use superflow_trainer::subscribe::{Subscription, Target};
use superflow_trainer::train::{StepPhases, Trainer};
use superflow_trainer::unet::UNetPreset;
use superflow_trainer::vit::VitPreset;

/// Samples per batch (the paper's per-GPU batch, the service default).
pub const BATCH_SIZE: usize = 4;
/// The drive the benchmark batch comes from.
pub const DRIVE: &str = "recordings/drives/street_ros2.mcap";

/// A benchmarked configuration.
#[derive(Debug, Clone, Copy)]
pub struct Preset {
    /// `tiny`, `minkunet18`, `minkunet34`.
    pub name: &'static str,
    /// The 3D network.
    pub unet: UNetPreset,
    /// The frozen 2D network.
    pub vit: VitPreset,
    /// Pixel stride of the superpixel pooling.
    pub pixel_stride: usize,
    /// Default timed compute steps.
    pub steps: usize,
    /// Default streamed steps.
    pub stream_steps: usize,
}

/// `tiny` (UNet tiny, ViT tiny, pixel stride 4), `minkunet18` (UNet minkunet18, random
/// ViT-S/14, pixel stride 1: the official full-resolution superpixel pooling),
/// `minkunet34` (as minkunet18 with the default UNet). Default step counts: tiny 4 timed
/// and 5 streamed, the others (about a minute a step on 2 cores) 1 timed and 2 streamed
/// (two, so that one wait between batches is measured).
pub const PRESETS: [Preset; 3] = [
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

/// The presets named in a comma-separated list.
pub fn presets(names: &str) -> anyhow::Result<Vec<Preset>> {
    names
        .split(',')
        .filter(|s| !s.is_empty())
        .map(|name| {
            PRESETS
                .iter()
                .find(|p| p.name == name)
                .copied()
                .with_context(|| format!("unknown preset {name:?} (tiny, minkunet18, minkunet34)"))
        })
        .collect()
}

/// A batch file as it travels (`superflow-pipeline batch`, [`build_batch`]): the
/// trainer's reader, the one `superflow-trainer check` uses.
pub use superflow_trainer::check::BatchFile;

/// Builds keyframes 0..4 of the drive at epoch 0 as `superflow-pipeline batch` does and
/// writes the file.
pub fn build_batch(dataset: &Dataset, config: &PipelineConfig, out: &Path) -> anyhow::Result<()> {
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

/// Trainable parameters of a module.
pub fn trainable<M: Module>(module: &M) -> usize {
    let mut visitor = Trainable::default();
    module.visit(&mut visitor);
    visitor.count
}

/// The trainer configuration of a preset.
pub fn trainer_config(preset: &Preset) -> TrainerConfig {
    let mut c = TrainerConfig::default();
    c.model.unet = preset.unet;
    c.model.vit = preset.vit;
    c.loss.pixel_stride = preset.pixel_stride;
    c.optim.steps = 1000;
    c
}

/// A trainer of a preset on the CPU, and the seconds `Trainer::new` took.
pub fn new_trainer(preset: &Preset) -> anyhow::Result<(Trainer, f64)> {
    let t = Instant::now();
    let trainer = Trainer::new(trainer_config(preset), &burn::tensor::Device::flex())?;
    Ok((trainer, t.elapsed().as_secs_f64()))
}

/// Compute-only timing of one preset.
#[derive(Debug)]
pub struct Compute {
    /// Trainable parameters of the 3D network.
    pub params_3d: usize,
    /// Trainable parameters of the whole model.
    pub params: usize,
    /// Timed steps.
    pub steps: usize,
    /// Median ms per step.
    pub ms: f64,
    /// Median ms per phase.
    pub phases: StepPhases,
    /// Seconds of `Trainer::new`.
    pub init_s: f64,
    /// The warm-up step, ms.
    pub warmup_ms: f64,
}

/// Medians of each phase, in ms.
fn median_phases(all: &[StepPhases]) -> StepPhases {
    let m = |f: fn(&StepPhases) -> f64| median(&all.iter().map(|p| f(p) * 1e3).collect::<Vec<_>>());
    StepPhases {
        inputs: m(|p| p.inputs),
        vit: m(|p| p.vit),
        forward: m(|p| p.forward),
        backward: m(|p| p.backward),
        reduce: m(|p| p.reduce),
        update: m(|p| p.update),
    }
}

/// One warm-up step, then `steps` timed steps on the same batch.
pub fn compute(
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

/// Streaming timing of one preset.
#[derive(Debug)]
pub struct Stream {
    /// Streamed steps.
    pub steps: usize,
    /// From the first batch's arrival to the end of the last step.
    pub seconds: f64,
    /// Blocked in `receive`, after the first batch.
    pub waiting: f64,
    /// In `Trainer::step`.
    pub computing: f64,
    /// Start-up: from the service's start to the first batch.
    pub first_batch_s: f64,
    /// Share of the service's run time its publisher spent blocked on the trainer's
    /// full queue (backpressure).
    pub blocked: f64,
    /// Share of the service's run time its publisher spent waiting for the sample
    /// builders.
    pub starved: f64,
    /// Median points, pairings, level-0 voxels of the streamed batches.
    pub counts: [f64; 3],
}

impl Stream {
    /// Streamed steps per second.
    pub fn steps_per_second(&self) -> f64 {
        self.steps as f64 / self.seconds
    }

    /// Time blocked in `receive` over the wall time of the window.
    pub fn stall_fraction(&self) -> f64 {
        self.waiting / self.seconds
    }
}

type Batch = superflow_trainer::subscribe::Received;

/// The pipeline service (`publish::serve`, broadcast, batch size 4, endless, iceoryx2
/// prefix `sfbench<pid>`) in a thread of this process, a `Subscription`, and `steps`
/// steps of the (already warm) trainer on the received batches. The first batch's wait
/// is the service's start-up, reported apart; the service is stopped and joined (shared
/// memory released) before this returns.
pub fn stream(
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
        let server = scope.spawn(|| {
            publish::serve(
                builder,
                &run,
                &service,
                &iox,
                publish::ResumeAt::Step { epoch: 0, step: 0 },
                &stop,
                &metrics,
            )
        });
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
