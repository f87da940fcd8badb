//! Opening a whole dataset: N = 1, 10, 100 and 1 000 nuScenes-layout drives (hard links
//! of two generated drives, Foxglove and ROS 2, each with its class-map sidecar, made at
//! bench time), every process under `ulimit -n 256`. For each N, one table row: cold
//! (index cache off) on one core and on all, warm (every file's index in the cache),
//! the warm process's peak RSS and most open files, and the time from starting
//! `superflow-pipeline batch` with a warm cache to its first batch written (opening the
//! dataset, the plan, one batch built exactly as the service publishes it).
//!
//! `cargo bench -p superflow-pipeline --bench scale` (`-- --size 800x450` for the
//! cameras, `--max N` to stop at N drives). Hard links share every byte a fingerprint
//! reads, so "cold" is the cache turned off, never a second file.

#[allow(dead_code)]
#[path = "../../tests/src/bench/common.rs"]
mod common;

use anyhow::{Context, bail};
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
    let dir = std::env::temp_dir().join(format!("superflow-scale-bench-{}", std::process::id()));
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
        "| drives | files | GB | cold 1 core s | cold all cores s | speed-up | warm s | cold / warm | warm peak RSS MB | warm most open files | first batch (warm) s |"
    );
    println!("|---:|---:|---:|---:|---:|---:|---:|---:|---:|---:|---:|");
    for count in [1usize, 10, 100, 1000].into_iter().filter(|&n| n <= max) {
        let inputs = linked(&dir, &sources, count)?;
        let cache = dir.join(format!("cache-{count}"));
        let cold_one = run_index(&inputs, None, true)?;
        let cold_all = run_index(&inputs, None, false)?;
        run_index(&inputs, Some(&cache), false)?; // fills the cache
        let warm = run_index(&inputs, Some(&cache), false)?;
        anyhow::ensure!(
            warm.hits == 2 * count,
            "{count} drives: {} cache hits of {} files",
            warm.hits,
            2 * count
        );
        let first = first_batch(&inputs, &cache, &dir)?;
        println!(
            "| {count} | {} | {:.2} | {:.2} | {:.2} | {:.2} | {:.3} | {:.0} | {:.0} | {} | {:.2} |",
            2 * count,
            warm.gb,
            cold_one.seconds,
            cold_all.seconds,
            cold_one.seconds / cold_all.seconds,
            warm.seconds,
            cold_all.seconds / warm.seconds,
            warm.peak_rss_mb,
            warm.most_open,
            first,
        );
        std::fs::remove_dir_all(&inputs)?;
    }
    std::fs::remove_dir_all(&dir)?;
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
    gb: f64,
    hits: usize,
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
    command.arg(BIN);
    command
}

fn run_index(inputs: &Path, cache: Option<&Path>, one_core: bool) -> anyhow::Result<IndexRun> {
    let mut command = limited(one_core);
    command
        .args(["index", "--mcap"])
        .arg(inputs)
        .arg("--index-cache")
        .arg(cache.unwrap_or(Path::new("off")))
        .env("RUST_LOG", "warn")
        .stdout(Stdio::piped())
        .stderr(Stdio::piped());
    let child = command
        .spawn()
        .context("starting superflow-pipeline index")?;
    let (peak_rss_mb, most_open) = watch(child.id());
    let output = child.wait_with_output()?;
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
    Ok(IndexRun {
        seconds: field("seconds")?.parse()?,
        gb,
        hits: field("cache hits")?.parse()?,
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
