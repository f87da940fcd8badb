//! Opening a whole dataset: N = 1, 10, 100 and 1 000 nuScenes-layout drives (hard links
//! of two generated drives, Foxglove and ROS 2, each with its class-map sidecar, made at
//! bench time), every process under `ulimit -n 256`. For each N, one table row: cold
//! (index cache off) on one core and on all, warm (every file's index and every drive's
//! camera scan in the cache), the warm process's peak RSS and most open files; the wall
//! time of the whole warm `superflow-pipeline index` process (open, plan, summary, exit;
//! the median of three runs, unwatched); the time from starting `superflow-pipeline
//! batch` with a warm cache to its first batch written (open, plan, one batch built
//! exactly as the service publishes it); and the time from starting the service with a
//! warm cache to its first batch received by a subscriber this bench holds (iceoryx2).
//!
//! `cargo bench -p superflow-pipeline --bench scale` (`-- --size 800x450` for the
//! cameras, `--max N` to stop at N drives, `--keep DIR` to work in DIR and leave the drives
//! and caches there for profiling, `--warm-only` for the warm columns alone;
//! `SUPERFLOW_PIPELINE_BIN=PATH` times another build of the binary, e.g. an earlier one). Hard links share every byte a fingerprint reads, so
//! "cold" is the cache turned off, never a second file.

#[allow(dead_code)]
#[path = "../../tests/src/bench/common.rs"]
mod common;

#[allow(dead_code)]
#[path = "../../tests/src/bench/transport.rs"]
mod transport;

use anyhow::{Context, anyhow, bail};
use common::{arg_count, arg_value, load_average};
use std::path::{Path, PathBuf};
use std::process::{Command, Stdio};
use std::time::{Duration, Instant};
use superflow_recordings::{Dialect, generate_with, options::DriveOptions};

const BIN: &str = env!("CARGO_BIN_EXE_superflow-pipeline");
const OPEN_FILES: u32 = 256;

fn main() -> anyhow::Result<()> {
    let (width, height) = match arg_value("--size") {
        Some(size) => {
            let (w, h) = size.split_once('x').context("--size WxH")?;
            (w.parse()?, h.parse()?)
        }
        None => (800, 450),
    };
    let max = arg_count("--max")?.unwrap_or(1000);
    let keep = arg_value("--keep").map(PathBuf::from);
    let warm_only = common::flag("--warm-only");
    let dir = keep.clone().unwrap_or_else(|| {
        std::env::temp_dir().join(format!("superflow-scale-bench-{}", std::process::id()))
    });
    std::fs::create_dir_all(&dir)?;
    let started = Instant::now();
    let sources = generate(&dir, width, height)?;
    println!(
        "scale: nuScenes-layout drives {width}x{height} (2 generated in {:.0} s, {:.1} MB with sidecars), \
         hard-linked; every process under ulimit -n {OPEN_FILES}; load {}",
        started.elapsed().as_secs_f64(),
        sources
            .iter()
            .flat_map(|(d, s)| [d, s])
            .map(|p| std::fs::metadata(p).map_or(0, |m| m.len()))
            .sum::<u64>() as f64
            / 1e6,
        load_average(3),
    );
    println!(
        "| drives | files | GB | cold 1 core s | cold all cores s | speed-up | warm open s | cold / warm | warm peak RSS MB | warm most open files | warm plan s | warm `index` wall s | first batch written (`batch`) s | service start → first batch at a subscriber s |"
    );
    println!("|---:|---:|---:|---:|---:|---:|---:|---:|---:|---:|---:|---:|---:|---:|");
    for count in [1usize, 10, 100, 1000].into_iter().filter(|&n| n <= max) {
        let inputs = linked(&dir, &sources, count)?;
        let cache = dir.join(format!("cache-{count}"));
        let _ = std::fs::remove_dir_all(&cache); // a kept one of an earlier run
        let cold = if warm_only {
            None
        } else {
            let one = run_index(&inputs, None, true)?.seconds;
            let all = run_index(&inputs, None, false)?.seconds;
            Some((one, all))
        };
        run_index(&inputs, Some(&cache), false)?; // fills the cache
        let warm = run_index(&inputs, Some(&cache), false)?;
        anyhow::ensure!(
            warm.hits == 2 * count && warm.scans_cached.is_none_or(|n| n == count),
            "{count} drives: {} cache hits of {} files, {:?} camera scans from the cache",
            warm.hits,
            2 * count,
            warm.scans_cached
        );
        let mut walls = Vec::new();
        let mut plans = Vec::new();
        for _ in 0..3 {
            let started = Instant::now();
            let run = run_index_unwatched(&inputs, &cache)?;
            walls.push(started.elapsed().as_secs_f64());
            plans.extend(run.plan_seconds);
        }
        let first = first_batch(&inputs, &cache, &dir)?;
        let published = first_published(&inputs, &cache, &dir)?;
        let cold = match cold {
            Some((one, all)) => format!(
                "{one:.2} | {all:.2} | {:.2} | {:.3} | {:.0}",
                one / all,
                warm.seconds,
                all / warm.seconds
            ),
            None => format!("- | - | - | {:.3} | -", warm.seconds),
        };
        println!(
            "| {count} | {} | {:.2} | {cold} | {:.0} | {} | {} | {:.2} | {:.2} | {:.2} |",
            2 * count,
            warm.gb,
            warm.peak_rss_mb,
            warm.most_open,
            if plans.is_empty() {
                "-".to_string()
            } else {
                format!("{:.3}", common::median(&plans))
            },
            common::median(&walls),
            first,
            published,
        );
        if keep.is_none() {
            std::fs::remove_dir_all(&inputs)?;
        }
    }
    if keep.is_none() {
        std::fs::remove_dir_all(&dir)?;
    }
    Ok(())
}

/// The two generated drives and their class-map sidecars.
fn generate(dir: &Path, width: u32, height: u32) -> anyhow::Result<Vec<(PathBuf, PathBuf)>> {
    let options = DriveOptions::nuscenes(width, height);
    [Dialect::Foxglove, Dialect::Ros2]
        .into_iter()
        .map(|dialect| {
            let drive = generate_with(dialect, &options)?;
            let sidecar = drive
                .sidecar
                .context("nuScenes drives keep class maps in a sidecar")?;
            let name = options.drive_name(dialect);
            let path = dir.join(format!("{name}.mcap"));
            let side = dir.join(
                options
                    .sidecar_name(dialect)
                    .context("nuScenes drives keep class maps in a sidecar")?,
            );
            std::fs::write(&path, &drive.mcap)?;
            std::fs::write(&side, &sidecar)?;
            Ok((path, side))
        })
        .collect()
}

/// A fresh directory of `count` drives, hard links taking the sources in turn.
fn linked(dir: &Path, sources: &[(PathBuf, PathBuf)], count: usize) -> anyhow::Result<PathBuf> {
    let sub = dir.join(format!("drives-{count}"));
    let _ = std::fs::remove_dir_all(&sub);
    std::fs::create_dir_all(&sub)?;
    for i in 0..count {
        let (drive, sidecar) = &sources[i % sources.len()];
        // `<drive>.<tag>.mcap`: the link keeps the tag.
        let tag = sidecar
            .file_name()
            .and_then(|n| n.to_str())
            .and_then(|n| n.rsplit('.').nth(1))
            .context("a sidecar is named <drive>.<tag>.mcap")?;
        std::fs::hard_link(drive, sub.join(format!("scene-{i:04}.mcap")))?;
        std::fs::hard_link(sidecar, sub.join(format!("scene-{i:04}.{tag}.mcap")))?;
    }
    Ok(sub)
}

/// What one `superflow-pipeline index` run printed and used.
struct IndexRun {
    seconds: f64,
    /// `None` from a build that did not print it.
    plan_seconds: Option<f64>,
    gb: f64,
    hits: usize,
    scans_cached: Option<usize>,
    peak_rss_mb: f64,
    most_open: usize,
}

/// `command` under the open-file limit, optionally on core 0 only.
fn limited(one_core: bool) -> Command {
    let mut command = Command::new("sh");
    command.arg("-c").arg(format!(
        "ulimit -n {OPEN_FILES} && exec {} \"$0\" \"$@\"",
        if one_core { "taskset -c 0" } else { "" }
    ));
    command.arg(std::env::var("SUPERFLOW_PIPELINE_BIN").unwrap_or_else(|_| BIN.to_string()));
    command
}

/// `superflow-pipeline index` of `inputs` (cache `off` without `cache`).
fn index_command(inputs: &Path, cache: Option<&Path>, one_core: bool) -> Command {
    let mut command = limited(one_core);
    command
        .args(["index", "--mcap"])
        .arg(inputs)
        .arg("--index-cache")
        .arg(cache.unwrap_or(Path::new("off")))
        .env("RUST_LOG", "warn")
        .stdout(Stdio::piped())
        .stderr(Stdio::piped());
    command
}

/// A warm `superflow-pipeline index` run on all cores, not watched (the watcher's reads
/// of `/proc` would take a share of the cores the run is timed on).
fn run_index_unwatched(inputs: &Path, cache: &Path) -> anyhow::Result<IndexRun> {
    let output = index_command(inputs, Some(cache), false).output()?;
    summary(&output, 0.0, 0)
}

fn run_index(inputs: &Path, cache: Option<&Path>, one_core: bool) -> anyhow::Result<IndexRun> {
    let child = index_command(inputs, cache, one_core)
        .spawn()
        .context("starting superflow-pipeline index")?;
    let (peak_rss_mb, most_open) = watch(child.id());
    let output = child.wait_with_output()?;
    summary(&output, peak_rss_mb, most_open)
}

/// The summary an `index` run printed.
fn summary(
    output: &std::process::Output,
    peak_rss_mb: f64,
    most_open: usize,
) -> anyhow::Result<IndexRun> {
    let stdout = String::from_utf8_lossy(&output.stdout);
    if !output.status.success() {
        bail!(
            "superflow-pipeline index failed:\n{stdout}\n{}",
            String::from_utf8_lossy(&output.stderr)
        );
    }
    let field = |name: &str| -> anyhow::Result<String> {
        stdout
            .lines()
            .find_map(|l| l.strip_prefix(name))
            .and_then(|rest| rest.split_whitespace().next())
            .map(str::to_owned)
            .with_context(|| format!("no `{name}` in the summary:\n{stdout}"))
    };
    let gb = stdout
        .lines()
        .find_map(|l| l.strip_prefix("files"))
        .and_then(|rest| rest.split('(').nth(1))
        .and_then(|rest| rest.split_whitespace().next())
        .and_then(|gb| gb.parse().ok())
        .unwrap_or(0.0);
    let plan = stdout.lines().find_map(|l| l.strip_prefix("plan seconds"));
    let plan_seconds = plan
        .and_then(|rest| rest.split_whitespace().next())
        .and_then(|s| s.parse().ok());
    let scans_cached = plan
        .and_then(|rest| rest.split("camera scans:").nth(1))
        .and_then(|rest| rest.split_whitespace().next())
        .and_then(|n| n.parse().ok());
    Ok(IndexRun {
        seconds: field("seconds")?.parse()?,
        plan_seconds,
        gb,
        hits: field("cache hits")?.parse()?,
        scans_cached,
        peak_rss_mb,
        most_open,
    })
}

/// Seconds from starting `superflow-pipeline batch` (warm cache) to its batch written.
fn first_batch(inputs: &Path, cache: &Path, dir: &Path) -> anyhow::Result<f64> {
    let out = dir.join("first.batch");
    let started = Instant::now();
    let output = limited(false)
        .args(["batch", "--mcap"])
        .arg(inputs)
        .arg("--index-cache")
        .arg(cache)
        .arg("--out")
        .arg(&out)
        .env("RUST_LOG", "warn")
        .output()?;
    let seconds = started.elapsed().as_secs_f64();
    if !output.status.success() {
        bail!(
            "superflow-pipeline batch failed: {}",
            String::from_utf8_lossy(&output.stderr)
        );
    }
    std::fs::remove_file(out)?;
    Ok(seconds)
}

/// Seconds from starting the service (`superflow-pipeline --mcap … --epochs 1`, warm
/// cache, its own iceoryx2 prefix) to its first batch received by a subscriber of this
/// process, attached before the service starts (the service publishes once a subscriber
/// is there). The service is then stopped with SIGTERM, which releases its shared memory.
fn first_published(inputs: &Path, cache: &Path, dir: &Path) -> anyhow::Result<f64> {
    let prefix = format!("sfscale{}", std::process::id());
    let run = "scale";
    let receiver = transport::BatchReceiver::open(&prefix, run, 1)?;
    let (subscriber, listener) = (&receiver.subscriber, &receiver.listener);
    let log = dir.join("service.log");
    let started = Instant::now();
    let mut child = limited(false)
        .arg("--mcap")
        .arg(inputs)
        .arg("--index-cache")
        .arg(cache)
        .args(["--run", run, "--epochs", "1"])
        .env("SUPERFLOW_IOX_PREFIX", &prefix)
        .env("RUST_LOG", "warn")
        .stdout(Stdio::null())
        .stderr(std::fs::File::create(&log)?)
        .spawn()
        .context("starting the service")?;
    let received = loop {
        match subscriber.receive() {
            Ok(Some(sample)) => {
                let seconds = started.elapsed().as_secs_f64();
                superflow_schemas::batch::BatchView::new(sample.user_header(), sample.payload())
                    .map_err(|e| anyhow!("the first batch does not validate: {e}"))?;
                break Ok(seconds);
            }
            Ok(None) => {}
            Err(e) => break Err(anyhow!("receiving: {e:?}")),
        }
        if let Some(status) = child.try_wait()? {
            break Err(anyhow!(
                "the service ended ({status}) before a batch:\n{}",
                std::fs::read_to_string(&log).unwrap_or_default()
            ));
        }
        if started.elapsed() > Duration::from_secs(600) {
            break Err(anyhow!("no batch from the service in 10 minutes"));
        }
        listener
            .timed_wait(|_| {}, Duration::from_millis(10))
            .map_err(|e| anyhow!("waiting for the ready event: {e:?}"))?;
    };
    let _ = Command::new("kill")
        .args(["-TERM", &child.id().to_string()])
        .status();
    let stopped = Instant::now();
    while child.try_wait()?.is_none() {
        if stopped.elapsed() > Duration::from_secs(30) {
            child.kill()?;
            child.wait()?;
            break;
        }
        std::thread::sleep(Duration::from_millis(10));
    }
    drop(receiver);
    // iceoryx2 leaves one management file per prefix; nothing else runs under this one.
    for entry in std::fs::read_dir("/dev/shm")?.flatten() {
        if entry.file_name().to_string_lossy().starts_with(&prefix) {
            let _ = std::fs::remove_file(entry.path());
        }
    }
    std::fs::remove_file(&log)?;
    received
}

/// The peak RSS (MB) and the most open files of process `pid` until it exits, sampled
/// every few milliseconds.
fn watch(pid: u32) -> (f64, usize) {
    let (mut peak_kb, mut most_open) = (0u64, 0usize);
    let status = PathBuf::from(format!("/proc/{pid}/status"));
    let fds = PathBuf::from(format!("/proc/{pid}/fd"));
    while let Ok(text) = std::fs::read_to_string(&status) {
        if text.contains("State:\tZ") {
            break;
        }
        if let Some(kb) = text
            .lines()
            .find_map(|l| l.strip_prefix("VmHWM:"))
            .and_then(|v| v.split_whitespace().next())
            .and_then(|v| v.parse::<u64>().ok())
        {
            peak_kb = peak_kb.max(kb);
        }
        if let Ok(entries) = std::fs::read_dir(&fds) {
            most_open = most_open.max(entries.count());
        }
        std::thread::sleep(Duration::from_millis(3));
    }
    (peak_kb as f64 / 1024.0, most_open)
}
