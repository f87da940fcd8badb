//! `--orders`: the epoch's order side by side. The bench drive is copied into a dataset
//! of `copies` drives (3 copies of the 8 s drive: 36 keyframes), and whole epochs are
//! built the way the service builds them — batches of [`BATCH`] in order, a batch's
//! samples in parallel — under `global` and under `blocks` (the service's defaults:
//! blocks of 8 keyframes, 16 open). One core, then every core; ms a sample amortised
//! over the epochs, the stages, how often a shared frame was found built, and the most
//! the shared frames held.
//!
//! Then the service itself: `superflow-pipeline` over the same dataset for `epochs`
//! epochs, batch 2, received by a subscriber of this process: the process's CPU time
//! (user + system, read from /proc before it is stopped: start-up, indexing, building,
//! writing and publishing) per sample.

use super::sample::stage_cells;
use super::transport;
use rayon::prelude::*;
use std::path::{Path, PathBuf};
use std::process::{Command, Stdio};
use std::time::{Duration, Instant};
use superflow_pipeline::drive::{Dataset, IngestConfig};
use superflow_pipeline::sample::recipe::KernelMaps;
use superflow_pipeline::sample::{EpochOrder, SampleBuilder, SampleConfig, StageTimes};

/// Samples a batch in the builder runs (the service's default batch).
const BATCH: usize = 4;

/// The orders compared: the service's `global`, and `blocks` with its defaults.
pub const ORDERS: [(&str, EpochOrder); 2] = [
    ("global", EpochOrder::Global),
    (
        "blocks",
        EpochOrder::Blocks {
            length: 8,
            open: 16,
        },
    ),
];

/// `copies` copies of the drive at `path` (and its class-map sidecar) in a directory
/// beside it, written once; their paths.
pub fn copies(path: &Path, copies: usize) -> anyhow::Result<Vec<PathBuf>> {
    let dir = path.with_file_name(format!("copies{copies}"));
    std::fs::create_dir_all(&dir)?;
    let stem = path
        .file_stem()
        .and_then(|s| s.to_str())
        .unwrap_or("drive")
        .to_owned();
    let sidecar = path.with_file_name(format!("{stem}.superpixels.mcap"));
    let mut out = Vec::new();
    for k in 0..copies {
        let copy = dir.join(format!("{stem}_{k}.mcap"));
        if !copy.exists() {
            std::fs::copy(path, &copy)?;
            if sidecar.exists() {
                std::fs::copy(&sidecar, dir.join(format!("{stem}_{k}.superpixels.mcap")))?;
            }
        }
        out.push(copy);
    }
    Ok(out)
}

/// One order's run of the builder.
pub struct Run {
    /// ms a sample on one core, amortised over the epochs.
    pub ms_one: f64,
    /// samples/s on every core.
    pub per_s_all: f64,
    /// Stage times of the one-core run.
    pub times: StageTimes,
    /// Samples of the one-core run.
    pub samples: usize,
    /// Shared frames found built / looked up (one-core run).
    pub hit_rate: Option<f64>,
    /// The most bytes the shared frames held (one-core run).
    pub peak_mb: Option<f64>,
}

/// What [`epochs_on`] measured.
struct Measured {
    /// Wall seconds of the measured epochs.
    secs: f64,
    /// Samples built in them.
    samples: usize,
    /// Their stage times.
    times: StageTimes,
    /// Shared frames found built / looked up, and the most MB they held.
    cache: Option<(f64, f64)>,
}

/// Epochs `epochs` (after a warm-up epoch) of `dataset` under `order`, on `threads`
/// threads, batch by batch.
fn epochs_on(
    dataset: &Dataset,
    config: &SampleConfig,
    order: EpochOrder,
    epochs: std::ops::Range<u64>,
    threads: usize,
) -> anyhow::Result<Measured> {
    let builder = SampleBuilder::new(dataset, config.clone())?
        .with_order(order)
        .keep_frames_for(2 * BATCH as u64);
    let pool = rayon::ThreadPoolBuilder::new()
        .num_threads(threads)
        .build()?;
    let run_epoch = |epoch: u64| -> anyhow::Result<StageTimes> {
        let mut total = StageTimes::default();
        let len = builder.epoch_len() as u64;
        let positions: Vec<u64> = (0..len).collect();
        for batch in positions.chunks(BATCH) {
            let times = pool.install(|| {
                batch
                    .par_iter()
                    .map(|&i| builder.build(epoch, i).map(|s| s.times))
                    .collect::<Result<Vec<_>, _>>()
            })?;
            times.iter().for_each(|t| total.add(t));
        }
        Ok(total)
    };
    run_epoch(epochs.start.saturating_sub(1))?;
    let before = builder.frame_cache().map(|c| {
        let s = c.stats();
        (
            s.hits.load(std::sync::atomic::Ordering::Relaxed),
            s.misses.load(std::sync::atomic::Ordering::Relaxed),
        )
    });
    let started = Instant::now();
    let mut times = StageTimes::default();
    let mut samples = 0;
    for epoch in epochs {
        times.add(&run_epoch(epoch)?);
        samples += builder.epoch_len();
    }
    let secs = started.elapsed().as_secs_f64();
    let cache = builder.frame_cache().zip(before).map(|(c, (h0, m0))| {
        let s = c.stats();
        let hits = s.hits.load(std::sync::atomic::Ordering::Relaxed) - h0;
        let misses = s.misses.load(std::sync::atomic::Ordering::Relaxed) - m0;
        let peak = s.peak_bytes.load(std::sync::atomic::Ordering::Relaxed) as f64 / 1e6;
        (hits as f64 / (hits + misses).max(1) as f64, peak)
    });
    Ok(Measured {
        secs,
        samples,
        times,
        cache,
    })
}

/// Each order's run over `paths`: `epochs` epochs on one core, then on `cores`.
pub fn runs(
    paths: &[PathBuf],
    maps: KernelMaps,
    epochs: u64,
    cores: usize,
) -> anyhow::Result<Vec<(&'static str, Run)>> {
    let dataset = Dataset::open(paths, &IngestConfig::default())?;
    let config = SampleConfig {
        kernel_maps: maps,
        ..SampleConfig::default()
    };
    let mut out = Vec::new();
    for (name, order) in ORDERS {
        let one = epochs_on(&dataset, &config, order, 1..1 + epochs, 1)?;
        let all = epochs_on(&dataset, &config, order, 1..1 + epochs, cores)?;
        out.push((
            name,
            Run {
                ms_one: one.secs * 1e3 / one.samples as f64,
                per_s_all: all.samples as f64 / all.secs,
                times: one.times,
                samples: one.samples,
                hit_rate: one.cache.map(|c| c.0),
                peak_mb: one.cache.map(|c| c.1),
            },
        ));
    }
    Ok(out)
}

/// A table row of [`runs`].
pub fn row(size: &str, name: &str, run: &Run) -> String {
    let cell =
        |v: Option<f64>, digits: usize| v.map_or("–".to_owned(), |v| format!("{v:.digits$}"));
    format!(
        "| {size} | {name} | {:.1} | {:.1} | {} | {} | {} |",
        run.ms_one,
        run.per_s_all,
        stage_cells(&run.times, run.samples),
        cell(run.hit_rate.map(|h| h * 100.0), 0),
        cell(run.peak_mb, 0),
    )
}

/// CPU seconds (user + system) of process `pid` so far, from /proc (100 ticks a second,
/// Linux's `USER_HZ`).
fn cpu_secs(pid: u32) -> anyhow::Result<f64> {
    let stat = std::fs::read_to_string(format!("/proc/{pid}/stat"))?;
    // Fields after the command name (which may hold spaces), from the 3rd: utime is the
    // 14th field, stime the 15th.
    let rest = stat
        .rsplit_once(')')
        .map(|(_, r)| r)
        .ok_or_else(|| anyhow::anyhow!("/proc/{pid}/stat: {stat}"))?;
    let fields: Vec<&str> = rest.split_whitespace().collect();
    let ticks = |i: usize| -> anyhow::Result<f64> { Ok(fields[i - 3].parse::<f64>()?) };
    Ok((ticks(14)? + ticks(15)?) / 100.0)
}

/// The service over `paths` for `epochs` epochs in `order` (`global`, `blocks`), batch
/// 2, from a warm index cache: its CPU ms a sample (start-up included), samples
/// received, wall seconds.
pub fn service(
    binary: &Path,
    paths: &[PathBuf],
    order: &str,
    epochs: u64,
) -> anyhow::Result<(f64, u64, f64)> {
    let prefix = transport::prefix();
    let run = format!("speed{order}");
    let cache = index_cache(binary, paths)?;
    let dataset = Dataset::open(paths, &IngestConfig::default())?;
    let expected =
        epochs * SampleBuilder::new(&dataset, SampleConfig::default())?.epoch_len() as u64;
    let receiver = transport::BatchReceiver::open(&prefix, &run, 4)?;
    let started = Instant::now();
    let mut child = Command::new(binary)
        .arg("--mcap")
        .args(paths)
        .arg("--index-cache")
        .arg(&cache)
        .args([
            "--run",
            &run,
            "--epochs",
            &epochs.to_string(),
            "--batch-size",
            "2",
        ])
        .args(["--order", order])
        .env("SUPERFLOW_IOX_PREFIX", &prefix)
        .env("RUST_LOG", "warn")
        .stdin(Stdio::null())
        .stdout(Stdio::null())
        .stderr(Stdio::null())
        .spawn()?;
    let mut samples = 0u64;
    let mut last = Instant::now();
    let outcome = loop {
        while let Some(batch) = receiver
            .subscriber
            .receive()
            .map_err(|e| anyhow::anyhow!("receiving: {e:?}"))?
        {
            samples += u64::from(batch.user_header().sample_count);
            last = Instant::now();
        }
        if let Some(status) = child.try_wait()? {
            break Err(anyhow::anyhow!(
                "the service ended ({status}) after {samples} samples"
            ));
        }
        if samples >= expected {
            // Every batch is in (the service lingers for its subscribers).
            break Ok(());
        }
        if last.elapsed() > Duration::from_secs(120) {
            break Err(anyhow::anyhow!(
                "no batch for 120 s after {samples} samples"
            ));
        }
        receiver
            .listener
            .timed_wait(|_| {}, Duration::from_millis(10))
            .map_err(|e| anyhow::anyhow!("waiting: {e:?}"))?;
    };
    let wall = last.duration_since(started).as_secs_f64();
    let cpu = cpu_secs(child.id());
    let _ = child.kill();
    let _ = child.wait();
    drop(receiver);
    outcome?;
    let cpu = cpu?;
    Ok((cpu * 1e3 / samples.max(1) as f64, samples, wall))
}

/// The index cache of the dataset at `paths` (beside the drives), made warm by
/// `superflow-pipeline index`: the runs compared start alike.
fn index_cache(binary: &Path, paths: &[PathBuf]) -> anyhow::Result<PathBuf> {
    let base = paths
        .first()
        .and_then(|p| p.parent())
        .unwrap_or(Path::new("."));
    let dir = base.join("index-cache");
    let status = Command::new(binary)
        .arg("--mcap")
        .args(paths)
        .arg("--index-cache")
        .arg(&dir)
        .arg("index")
        .stdout(Stdio::null())
        .stderr(Stdio::null())
        .status()?;
    anyhow::ensure!(status.success(), "superflow-pipeline index: {status}");
    Ok(dir)
}

/// One layout of a job for [`statistics`]: ranks, batch per rank, open blocks.
pub const LAYOUTS: [(usize, usize, u32); 3] = [(1, 4, 16), (8, 4, 32), (64, 4, 256)];

/// How local and how mixed each order's batches are on a nuScenes-sized dataset (850
/// drives of 40 keyframes; no decoding: the orders alone), for each of [`LAYOUTS`],
/// averaged over 3 seeds: table rows of the share of distinct drives in a global batch,
/// the share of rank batches drawn from distinct blocks, and how many steps a block stays
/// open on its rank.
pub fn statistics() -> Vec<String> {
    use superflow_pipeline::sample::{EpochMix, KeyframeRef, Plan};
    let (drives, per_drive) = (850u32, 40u32);
    let mut plan = Plan::default();
    for drive in 0..drives {
        for sweep in 0..per_drive {
            plan.keyframes.push(KeyframeRef {
                drive,
                sweep: sweep * 10,
                frame_sweeps: vec![sweep * 10],
                reused: 0,
                worst_camera_offset_nanos: 0,
            });
        }
    }
    let mut rows = Vec::new();
    for (ranks, batch, open) in LAYOUTS {
        let orders = [
            ("global", EpochOrder::Global),
            ("blocks", EpochOrder::Blocks { length: 8, open }),
        ];
        for (name, order) in orders {
            let mix = EpochMix::whole(&plan).ordered(order);
            let (mut drives_share, mut distinct_blocks, mut open_steps) = (0.0, 0.0, 0.0);
            let seeds = 3;
            for seed in 0..seeds {
                let a = mix.arrange(seed, 0);
                let global = ranks * batch;
                let steps = a.keyframes.len() / global;
                let drive_of = |p: usize| plan.keyframes[a.keyframes[p] as usize].drive;
                let mut shares = 0.0;
                let mut distinct = 0usize;
                // (rank, block) → (first step, last step)
                let mut spans: std::collections::HashMap<(usize, u32), (usize, usize)> =
                    std::collections::HashMap::new();
                for step in 0..steps {
                    let positions = step * global..(step + 1) * global;
                    let mut seen: Vec<u32> = positions.clone().map(drive_of).collect();
                    seen.sort_unstable();
                    seen.dedup();
                    shares += seen.len() as f64 / global as f64;
                    for rank in 0..ranks {
                        let mine: Vec<usize> = (0..batch)
                            .map(|j| step * global + j * ranks + rank)
                            .collect();
                        let mut blocks: Vec<u32> = mine.iter().map(|&p| a.blocks[p]).collect();
                        for &b in &blocks {
                            let span = spans.entry((rank, b)).or_insert((step, step));
                            span.1 = step;
                        }
                        blocks.sort_unstable();
                        blocks.dedup();
                        distinct += usize::from(blocks.len() == batch);
                    }
                }
                drives_share += shares / steps as f64;
                distinct_blocks += distinct as f64 / (steps * ranks) as f64;
                open_steps += spans.values().map(|(f, l)| (l - f + 1) as f64).sum::<f64>()
                    / spans.len().max(1) as f64;
            }
            let n = seeds as f64;
            let layout = format!("{ranks} × {batch}");
            let open_cell = match order {
                EpochOrder::Global => "–".to_owned(),
                EpochOrder::Blocks { open, .. } => open.to_string(),
            };
            rows.push(format!(
                "| {layout} | {name} | {open_cell} | {:.1} | {:.1} | {:.1} |",
                drives_share / n * 100.0,
                distinct_blocks / n * 100.0,
                open_steps / n,
            ));
        }
    }
    rows
}
