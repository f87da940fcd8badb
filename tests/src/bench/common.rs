//! What every benchmark needs: where the drives are, command-line values, medians and
//! percentiles, the machine (CPU model, load average) and the date.
//!
//! Compiled into `superflow_tests::bench` and, through `#[path]`, into the benches of
//! `superflow-pipeline` and `superflow-trainer` (which cannot depend on this crate
//! without building each other), so it uses only `std` and `anyhow`.

use std::path::PathBuf;

/// The sample drives, by name (`recordings/drives/<name>.mcap`).
pub const DRIVES: [&str; 2] = ["street_foxglove", "street_ros2"];

/// The repository root (benches run with their package as working directory).
pub fn root() -> PathBuf {
    PathBuf::from(env!("CARGO_MANIFEST_DIR")).join("..")
}

/// `recordings/drives/<name>.mcap`.
pub fn drive_path(name: &str) -> PathBuf {
    root().join(format!("recordings/drives/{name}.mcap"))
}

/// The value of `--name VALUE` or `--name=VALUE` on the command line.
pub fn arg_value(name: &str) -> Option<String> {
    let argv: Vec<String> = std::env::args().skip(1).collect();
    let prefix = format!("{name}=");
    argv.iter()
        .position(|a| a == name)
        .and_then(|i| argv.get(i + 1))
        .cloned()
        .or_else(|| {
            argv.iter()
                .find_map(|a| a.strip_prefix(&prefix).map(str::to_owned))
        })
}

/// `--name N` as a positive count; an error if it is there but not one.
pub fn arg_count(name: &str) -> anyhow::Result<Option<usize>> {
    arg_value(name)
        .map(|v| {
            v.parse::<usize>()
                .ok()
                .filter(|n| *n > 0)
                .ok_or_else(|| anyhow::anyhow!("{name} {v}: expected a positive integer"))
        })
        .transpose()
}

/// Whether `--name` is on the command line.
pub fn flag(name: &str) -> bool {
    std::env::args().skip(1).any(|a| a == name)
}

/// The median (mean of the two middle values for an even count; NaN when empty).
pub fn median(values: &[f64]) -> f64 {
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

/// The `p` quantile (0..=1) of sorted values, nearest rank.
pub fn percentile(sorted: &[f64], p: f64) -> f64 {
    if sorted.is_empty() {
        return f64::NAN;
    }
    sorted[((sorted.len() - 1) as f64 * p).round() as usize]
}

/// The first `n` load averages of `/proc/loadavg`, comma-separated.
pub fn load_average(n: usize) -> String {
    std::fs::read_to_string("/proc/loadavg")
        .map(|s| s.split_whitespace().take(n).collect::<Vec<_>>().join(", "))
        .unwrap_or_else(|_| "?".into())
}

/// The cores this process may use.
pub fn cores() -> usize {
    std::thread::available_parallelism().map_or(1, |c| c.get())
}

/// Writes a bench's report to `target/<file>` (or under `CARGO_TARGET_DIR`) and says
/// where on stderr.
pub fn write_report(file: &str, text: &str) -> std::io::Result<PathBuf> {
    let target = std::env::var_os("CARGO_TARGET_DIR")
        .map(PathBuf::from)
        .unwrap_or_else(|| root().join("target"));
    let path = target.join(file);
    std::fs::write(&path, text)
        .map_err(|e| std::io::Error::new(e.kind(), format!("writing {}: {e}", path.display())))?;
    eprintln!(
        "written to {}",
        path.canonicalize()
            .unwrap_or_else(|_| path.clone())
            .display()
    );
    Ok(path)
}

/// The CPU model (first `model name` of /proc/cpuinfo).
pub fn cpu_model() -> String {
    std::fs::read_to_string("/proc/cpuinfo")
        .ok()
        .and_then(|s| {
            s.lines()
                .find_map(|l| l.strip_prefix("model name"))
                .map(|v| v.trim_start_matches([' ', '\t', ':']).trim().to_owned())
        })
        .unwrap_or_else(|| "unknown CPU".into())
}

/// `date -u`, to the minute.
pub fn now_utc() -> String {
    std::process::Command::new("date")
        .args(["-u", "+%Y-%m-%d %H:%M UTC"])
        .output()
        .ok()
        .filter(|o| o.status.success())
        .map(|o| String::from_utf8_lossy(&o.stdout).trim().to_owned())
        .unwrap_or_else(|| "unknown date".into())
}
