//! All the benchmarks in one table: pipeline samples/s per core, iceoryx2 delivery
//! latency against payload size, the producer's cost of fan-out, trainer steps/s and the
//! data-stall fraction — with the machine above it, ready to paste into
//! pipeline/docs/BENCHMARKS.md.
//!
//! `cargo bench -p superflow-tests --bench summary [-- OPTIONS]`; the table goes to
//! stdout and to `target/bench-summary.md`, progress to stderr. About 2 minutes on 2
//! cores with the defaults. Options:
//!
//! * `--quick`: fewer samples, messages and steps (a smoke run, ~1 minute);
//! * `--only pipeline,latency,fanout,trainer` (`transport` = latency and fan-out);
//! * `--samples N`: samples per pipeline run (default 48);
//! * `--reps N`: messages per latency size and per fan-out run (default 300 for ≤ 1 MiB
//!   down to 20 for 64 MiB; fan-out 40);
//! * `--minkunet18`: also the minkunet18 preset (~75 s a step on 2 cores, ~6 more
//!   minutes); `--presets tiny,minkunet18,minkunet34` names them all;
//! * `--steps N`, `--stream-steps N`: timed and streamed training steps per preset
//!   (defaults: tiny 4 and 5, the others 1 and 2).
//!
//! The measurements are those of the per-area benches, shared through
//! `superflow_tests::bench`: `sample` (samples/s of the default recipe on a rayon pool
//! of 1 and of all cores, after a warm-up epoch), `transport` (one message in flight,
//! subscriber threads blocked on the ready event; the producer loans, writes every byte,
//! sends and notifies), `train` (compute-only steps on one real batch of 4 samples of
//! `street_ros2` after a warm-up step; then the real pipeline service in a thread of
//! this process, streaming to the warm trainer). Every iceoryx2 run uses the prefix
//! `sfbench<pid>…`; the bench checks that nothing of it is left in /dev/shm.

use anyhow::Context as _;
use std::fmt::Write as _;
use std::time::Instant;
use superflow_pipeline::config::PipelineConfig;
use superflow_pipeline::drive::Dataset;
use superflow_pipeline::sample::{SampleBuilder, SampleConfig};
use superflow_tests::bench::common::{
    self, DRIVES, arg_count, arg_value, cores, cpu_model, drive_path, flag, load_average, now_utc,
    percentile,
};
use superflow_tests::bench::train::{self, BATCH_SIZE, BatchFile, DRIVE};
use superflow_tests::bench::transport::{self, KIB, MIB};

/// The parts of the bench.
const SECTIONS: [&str; 4] = ["pipeline", "latency", "fanout", "trainer"];

/// Payload sizes of the latency rows.
const LATENCY_SIZES: [usize; 4] = [KIB, MIB, 16 * MIB, 64 * MIB];

/// Subscriber counts of the fan-out rows.
const FANOUT: [usize; 3] = [1, 2, 4];

#[derive(Debug)]
struct Args {
    quick: bool,
    sections: Vec<&'static str>,
    samples: usize,
    reps: Option<usize>,
    presets: Vec<train::Preset>,
    steps: Option<usize>,
    stream_steps: Option<usize>,
}

impl Args {
    fn parse() -> anyhow::Result<Self> {
        let quick = flag("--quick");
        let sections = match arg_value("--only") {
            None => SECTIONS.to_vec(),
            Some(list) => {
                let mut sections = Vec::new();
                for name in list.split(',').filter(|s| !s.is_empty()) {
                    match name {
                        "transport" => sections.extend(["latency", "fanout"]),
                        _ => sections.push(
                            SECTIONS
                                .iter()
                                .find(|s| **s == name)
                                .copied()
                                .with_context(|| {
                                    format!(
                                        "--only {name}: one of {} or transport",
                                        SECTIONS.join(", ")
                                    )
                                })?,
                        ),
                    }
                }
                sections
            }
        };
        let presets = match arg_value("--presets") {
            Some(list) => train::presets(&list)?,
            None if flag("--minkunet18") => train::presets("tiny,minkunet18")?,
            None => train::presets("tiny")?,
        };
        Ok(Self {
            quick,
            sections,
            samples: arg_count("--samples")?.unwrap_or(if quick { 16 } else { 48 }),
            reps: arg_count("--reps")?,
            presets,
            steps: arg_count("--steps")?,
            stream_steps: arg_count("--stream-steps")?,
        })
    }

    fn runs(&self, section: &str) -> bool {
        self.sections.contains(&section)
    }
}

/// One row of the table.
#[derive(Debug)]
struct Row {
    measure: &'static str,
    setting: String,
    value: String,
    unit: &'static str,
}

#[derive(Debug, Default)]
struct Table(Vec<Row>);

impl Table {
    fn push(&mut self, measure: &'static str, setting: String, value: String, unit: &'static str) {
        eprintln!("  {measure} | {setting} | {value} {unit}");
        self.0.push(Row {
            measure,
            setting,
            value,
            unit,
        });
    }
}

fn pipeline(args: &Args, cores: usize, table: &mut Table) -> anyhow::Result<()> {
    for name in DRIVES {
        eprintln!("pipeline: {name}, {} samples per run ...", args.samples);
        let dataset = Dataset::open(&[drive_path(name)], &Default::default())
            .with_context(|| format!("opening {name}"))?;
        let builder = SampleBuilder::new(&dataset, SampleConfig::default())?;
        let run = superflow_tests::bench::sample::one_and_all(&builder, args.samples, cores)?;
        let (one, all) = (run.one, run.all);
        let s = if cores == 1 { "" } else { "s" };
        table.push(
            "pipeline samples/s",
            format!("{name}, 1 core"),
            format!("{one:.1}"),
            "samples/s",
        );
        table.push(
            "pipeline samples/s",
            format!("{name}, {cores} core{s}"),
            format!("{all:.1}"),
            "samples/s",
        );
        table.push(
            "pipeline samples/s per core",
            format!("{name}, {cores} core{s}"),
            format!("{:.1}", all / cores as f64),
            "samples/s/core",
        );
    }
    Ok(())
}

fn latency(args: &Args, table: &mut Table) -> anyhow::Result<()> {
    for (k, &size) in LATENCY_SIZES.iter().enumerate() {
        let reps = args
            .reps
            .unwrap_or(transport::latency_reps(size, args.quick));
        let label = transport::size_label(size);
        eprintln!("latency: {label}, {reps} messages ...");
        let (mut lat, _) = transport::iceoryx2_run(size, reps, 1, &format!("l{k}"))?;
        lat.sort_by(f64::total_cmp);
        for (p, q) in [("median", 0.5), ("p99", 0.99)] {
            table.push(
                "delivery latency, iceoryx2",
                format!("{label}, {p}"),
                format!("{:.0}", percentile(&lat, q)),
                "µs",
            );
        }
    }
    Ok(())
}

fn fanout(args: &Args, size: usize, table: &mut Table) -> anyhow::Result<()> {
    let label = transport::size_label(size);
    for subscribers in FANOUT {
        let reps = args.reps.unwrap_or(transport::fanout_reps(args.quick));
        let s = if subscribers == 1 { "" } else { "s" };
        eprintln!("fan-out: {label} to {subscribers} subscriber{s}, {reps} messages ...");
        let (_, ms) = transport::iceoryx2_run(size, reps, subscribers, &format!("f{subscribers}"))?;
        table.push(
            "fan-out: producer time per batch",
            format!("{label} batch, {subscribers} subscriber{s}"),
            format!("{ms:.2}"),
            "ms",
        );
    }
    Ok(())
}

fn trainer(
    args: &Args,
    dataset: &Dataset,
    config: &PipelineConfig,
    batch: &BatchFile,
    table: &mut Table,
) -> anyhow::Result<()> {
    let builder = SampleBuilder::new(dataset, config.sample.clone())?;
    for preset in &args.presets {
        let quick = |n: usize| if args.quick { n.div_ceil(2).max(1) } else { n };
        let steps = args.steps.unwrap_or(quick(preset.steps));
        let stream_steps = args
            .stream_steps
            .unwrap_or(quick(preset.stream_steps).max(2));
        eprintln!(
            "trainer: {}, {steps} timed + {stream_steps} streamed steps ...",
            preset.name
        );
        let (mut trainer, init_s) = train::new_trainer(preset)?;
        let c = train::compute(&mut trainer, batch, preset, steps, init_s)?;
        let s = train::stream(&mut trainer, &builder, preset, stream_steps)?;
        table.push(
            "trainer steps/s",
            format!("{}, compute only (1 batch, {steps} steps)", preset.name),
            format!("{:.3}", 1e3 / c.ms),
            "steps/s",
        );
        table.push(
            "trainer steps/s",
            format!(
                "{}, streamed from the service ({stream_steps} steps)",
                preset.name
            ),
            format!("{:.3}", s.steps_per_second()),
            "steps/s",
        );
        table.push(
            "trainer data-stall fraction",
            format!("{}, streamed", preset.name),
            format!("{:.3}", s.stall_fraction()),
            "of wall time",
        );
    }
    Ok(())
}

/// The pipeline binary's allocator (see `superflow_pipeline::memory`).
#[global_allocator]
static ALLOCATOR: superflow_common::memory::Allocator = superflow_common::memory::Allocator;

fn main() -> anyhow::Result<()> {
    superflow_common::memory::keep_freed_pages();
    let args = Args::parse()?;
    let cores = cores();
    let started = Instant::now();
    let load_start = load_average(1);
    let date = now_utc();
    eprintln!(
        "superflow bench summary: {} on {cores} cores",
        args.sections.join(", ")
    );
    let mut table = Table::default();

    if args.runs("pipeline") {
        pipeline(&args, cores, &mut table)?;
    }
    if args.runs("latency") {
        latency(&args, &mut table)?;
    }
    // The fan-out message and the trainer's input: one real batch.
    let mut batch_note = String::new();
    if args.runs("fanout") || args.runs("trainer") {
        let config = PipelineConfig::default();
        let drive = common::root().join(DRIVE);
        let dataset = Dataset::open(std::slice::from_ref(&drive), &config.ingest)
            .with_context(|| format!("opening {}", drive.display()))?;
        let path = common::root().join("target/superflow-bench-batch.bin");
        train::build_batch(&dataset, &config, &path)?;
        let batch = BatchFile::read(&path)?;
        let bytes = batch.bytes();
        batch_note = format!(
            "batch: {BATCH_SIZE} samples of {DRIVE} (keyframes 0..{BATCH_SIZE}, default recipe), {bytes} bytes. "
        );
        if args.runs("fanout") {
            fanout(&args, bytes, &mut table)?;
        }
        if args.runs("trainer") {
            trainer(&args, &dataset, &config, &batch, &mut table)?;
        }
    }

    let left = transport::release_shared_memory();
    let mut out = String::new();
    writeln!(
        out,
        "Machine: {} ({cores} cores), {date}; load average {load_start} at start, {} at end (1 min); {} build, {:.0} s.",
        cpu_model(),
        load_average(1),
        if cfg!(debug_assertions) {
            "debug"
        } else {
            "release"
        },
        started.elapsed().as_secs_f64(),
    )?;
    writeln!(out)?;
    writeln!(out, "| measure | setting | value | unit |")?;
    writeln!(out, "|---|---|---:|---|")?;
    for r in &table.0 {
        writeln!(
            out,
            "| {} | {} | {} | {} |",
            r.measure, r.setting, r.value, r.unit
        )?;
    }
    writeln!(out)?;
    writeln!(
        out,
        "Pipeline: default recipe, {} samples per run after a warm-up epoch. Latency: `send` to `receive` returning, one message in flight, the subscriber woken by the ready event. Fan-out: loan + write every byte + send + notify. Trainer: burn `flex` on the CPU; streamed = the pipeline service in the same process, sharing the cores; stall = time blocked in `receive` / wall time. {batch_note}Shared memory left in /dev/shm: {}.",
        args.samples,
        transport::left_in_shm(&left),
    )?;
    transport::publish_report("bench-summary.md", &out, &left)
}
