//! Drives in object storage against local files: the service's throughput when it reads
//! its drives from `s3://` through a proxy that adds latency and caps the bandwidth, the
//! requests and bytes that costs per sample, and the opening of a thousand small remote
//! drives, cold and warm.
//!
//! `cargo bench -p superflow-tests --bench object_store [-- OPTIONS]`; the tables go to
//! stdout and to `target/bench-object-store.md`, progress to stderr. Options:
//!
//! * `--quick`: 2 drives, one run per row, 0 and 20 ms only, no small-budget row, 100
//!   small drives (a smoke run: ~20 s once the drives are generated);
//! * `--only throughput,open`: one of the two tables;
//! * `--drives N`: nuScenes-like drives served (copies of two generated ones; default 8);
//! * `--reps N`: service runs per row of the first table, interleaved (default 3); the
//!   table shows their medians;
//! * `--latencies 20,50`: the added latencies of the first table, ms (0 always runs);
//! * `--bandwidth MB`: the proxy's bandwidth cap in the first table, MB/s (default 200);
//! * `--prefetch-mb N`: `remote_prefetch_mb` of the prefetching rows (default: the
//!   pipeline's, 256);
//! * `--tight-mb N`: the prefetch budget of a row where it is smaller than the batches in
//!   flight need (default 32; 0 leaves the row out);
//! * `--open-bandwidth MB`: a bandwidth cap in the second table (default none: latency
//!   only);
//! * `--small N`: drives of the second table (default 1 000);
//! * `--keep DIR`: work in DIR and leave the drives, caches and logs there;
//! * `--no-pin`: let every process share every core (see below).
//!
//! By default the pipeline runs on all cores but the last (`taskset`), and this process
//! — the subscriber, the proxy and moto, its child — on the last one: on a small machine
//! the store's CPU (moto is Python, a few ms a request) would otherwise come out of the
//! sample builders' and be read as the cost of object storage. Local and remote rows are
//! pinned alike. `--no-pin` measures the shared case.
//!
//! Everything goes through the test harness of `tests/src/s3/`: moto on 127.0.0.1 as the
//! store, and [`FaultProxy`] in front of it for the latency, the bandwidth cap and the
//! request and byte counts. The pipeline is the real `superflow-pipeline` binary (built
//! with `cargo build --release` at the start; `SUPERFLOW_PIPELINE_BIN=PATH` runs
//! another), given the store's endpoint and credentials in the environment.
//!
//! The first table runs the service (`--epochs 1`) with a warm index cache, filled by an
//! `index` run beforehand, so that what is timed is serving samples; a subscriber of this
//! process takes the batches over iceoryx2 as they come. Samples/s are counted from the
//! first batch received to the last, with the service's CPU time, page faults and peak
//! memory over the same span (/proc); requests and bytes are the proxy's counts over the
//! whole service run (its start, a LIST, included), and the distinct bytes those GETs
//! covered (each byte of an object once, however often it was read). "Chunks needed" is
//! the distinct bytes of a run with `remote_prefetch_mb = 0` at no added latency: demand
//! reads only, each exactly a chunk record some sample read, so their union is the chunk
//! records the epoch's samples need.

use anyhow::{Context as _, anyhow, bail};
use std::collections::HashMap;
use std::fmt::Write as _;
use std::io::{Read as _, Write as _};
use std::path::{Path, PathBuf};
use std::process::{Command, Stdio};
use std::time::{Duration, Instant};
use superflow_recordings::{Dialect, DriveOptions, GENERATOR_VERSION, generate_with};
use superflow_tests::bench::common::{
    self, arg_count, arg_value, cores, cpu_model, flag, load_average, median, now_utc,
};
use superflow_tests::bench::transport;
use superflow_tests::s3::{Counters, FaultPlan, FaultProxy, S3Server};

/// The bucket every drive is uploaded to.
const BUCKET: &str = "superflow-bench";
/// Camera size of the nuScenes-like drives (the common 800×450 conversion).
const SIZE: (u32, u32) = (800, 450);
/// Samples per batch (the service's default).
const BATCH: u64 = 4;
/// The added latency of the second table.
const OPEN_LATENCY_MS: u64 = 20;
/// How long a service run may go without a batch before it is given up.
const IDLE: Duration = Duration::from_secs(60);

#[derive(Debug)]
struct Args {
    quick: bool,
    throughput: bool,
    open: bool,
    drives: usize,
    reps: usize,
    latencies: Vec<u64>,
    bandwidth: u64,
    open_bandwidth: Option<u64>,
    prefetch_mb: Option<u64>,
    tight_mb: Option<u64>,
    small: usize,
    keep: Option<PathBuf>,
    pin: bool,
}

impl Args {
    fn parse() -> anyhow::Result<Self> {
        let quick = flag("--quick");
        let (mut throughput, mut open) = (true, true);
        if let Some(only) = arg_value("--only") {
            throughput = false;
            open = false;
            for name in only.split(',').filter(|s| !s.is_empty()) {
                match name {
                    "throughput" => throughput = true,
                    "open" => open = true,
                    other => bail!("--only {other}: throughput or open"),
                }
            }
        }
        let latencies = match arg_value("--latencies") {
            Some(list) => list
                .split(',')
                .filter(|s| !s.is_empty())
                .map(|s| {
                    s.parse::<u64>()
                        .with_context(|| format!("--latencies {s}: milliseconds"))
                })
                .collect::<anyhow::Result<Vec<_>>>()?,
            None if quick => vec![20],
            None => vec![20, 50],
        };
        Ok(Self {
            quick,
            throughput,
            open,
            drives: arg_count("--drives")?.unwrap_or(if quick { 2 } else { 8 }),
            reps: arg_count("--reps")?.unwrap_or(if quick { 1 } else { 3 }),
            latencies: latencies.into_iter().filter(|&l| l > 0).collect(),
            bandwidth: arg_count("--bandwidth")?.unwrap_or(200) as u64,
            open_bandwidth: arg_count("--open-bandwidth")?.map(|mb| mb as u64),
            prefetch_mb: arg_count("--prefetch-mb")?.map(|mb| mb as u64),
            tight_mb: match arg_value("--tight-mb") {
                Some(v) => Some(v.parse::<u64>().context("--tight-mb: MiB")?).filter(|&mb| mb > 0),
                None if quick => None,
                None => Some(32),
            },
            small: arg_count("--small")?.unwrap_or(if quick { 100 } else { 1000 }),
            keep: arg_value("--keep").map(PathBuf::from),
            pin: !flag("--no-pin") && cores() >= 2,
        })
    }

    /// The proxy's cap, bytes per second.
    fn cap(&self) -> u64 {
        self.bandwidth * 1_000_000
    }
}

/// The pipeline binary beside this package's binaries, brought up to date with `cargo
/// build --release` (the bench profile's directory); `SUPERFLOW_PIPELINE_BIN` overrides it.
fn pipeline_binary() -> anyhow::Result<PathBuf> {
    if let Some(bin) = std::env::var_os("SUPERFLOW_PIPELINE_BIN") {
        return Ok(PathBuf::from(bin));
    }
    let sibling = PathBuf::from(env!("CARGO_BIN_EXE_superflow-subscriber"));
    let path = sibling.with_file_name("superflow-pipeline");
    let cargo = std::env::var("CARGO").unwrap_or_else(|_| "cargo".into());
    let mut build = Command::new(cargo);
    build
        .args([
            "build",
            "-p",
            "superflow-pipeline",
            "--bin",
            "superflow-pipeline",
        ])
        .current_dir(common::root());
    if !cfg!(debug_assertions) {
        build.arg("--release");
    }
    let status = build.status().context("running cargo build")?;
    anyhow::ensure!(status.success(), "building superflow-pipeline failed");
    anyhow::ensure!(path.is_file(), "{} was not built", path.display());
    Ok(path)
}

/// One generated drive: the MCAP file and its class-map sidecar.
#[derive(Debug, Clone)]
struct Source {
    drive: PathBuf,
    sidecar: Option<PathBuf>,
}

/// Writes (or finds) the drive of `options` in `dialect` under
/// `target/bench-drives/object-store-v<generator version>/`.
fn generated(dialect: Dialect, options: &DriveOptions) -> anyhow::Result<Source> {
    let dir = common::root()
        .join("target/bench-drives")
        .join(format!("object-store-v{GENERATOR_VERSION}"));
    std::fs::create_dir_all(&dir)?;
    let name = options.drive_name(dialect);
    let drive = dir.join(format!("{name}.mcap"));
    let sidecar = options.sidecar_name(dialect).map(|n| dir.join(n));
    let complete = drive.is_file() && sidecar.as_ref().is_none_or(|s| s.is_file());
    if !complete {
        let started = Instant::now();
        let generated = generate_with(dialect, options)?;
        if let (Some(path), Some(bytes)) = (&sidecar, &generated.sidecar) {
            std::fs::write(path, bytes)?;
        }
        std::fs::write(&drive, &generated.mcap)?;
        eprintln!(
            "generated {} ({:.1} MB) in {:.1} s",
            drive.display(),
            generated.mcap.len() as f64 / 1e6,
            started.elapsed().as_secs_f64()
        );
    }
    Ok(Source { drive, sidecar })
}

/// `scene-<i>.mcap` and its sidecar (`scene-<i>.<tag>.mcap`), the names a copy of
/// `source` takes.
fn copy_names(source: &Source, i: usize) -> Vec<(String, &Path)> {
    let mut names = vec![(format!("scene-{i:04}.mcap"), source.drive.as_path())];
    if let Some(sidecar) = &source.sidecar {
        // `<drive>.<tag>.mcap`: the copy keeps the tag.
        let tag = sidecar
            .file_name()
            .and_then(|n| n.to_str())
            .and_then(|n| n.rsplit('.').nth(1))
            .unwrap_or("superpixels");
        names.push((format!("scene-{i:04}.{tag}.mcap"), sidecar.as_path()));
    }
    names
}

/// `count` drives taking `sources` in turn, hard-linked into `dir` (a fresh directory)
/// and uploaded under `prefix/`; returns their bytes.
fn place(
    server: &S3Server,
    sources: &[Source],
    count: usize,
    dir: &Path,
    prefix: &str,
) -> anyhow::Result<u64> {
    let _ = std::fs::remove_dir_all(dir);
    std::fs::create_dir_all(dir)?;
    let mut uploads = Vec::new();
    let mut bytes = 0;
    for i in 0..count {
        for (name, from) in copy_names(&sources[i % sources.len()], i) {
            std::fs::hard_link(from, dir.join(&name))?;
            bytes += std::fs::metadata(from)?.len();
            uploads.push((format!("{prefix}/{name}"), from.to_path_buf()));
        }
    }
    let read = |(key, from): (String, PathBuf)| {
        let bytes = std::fs::read(&from).unwrap_or_else(|e| panic!("{}: {e}", from.display()));
        (key, bytes)
    };
    server.put_many(BUCKET, uploads.into_iter().map(read));
    Ok(bytes)
}

/// Runs the pipeline binary with the store's environment.
#[derive(Debug)]
struct Runner {
    bin: PathBuf,
    dir: PathBuf,
    /// The cores the pipeline runs on (`taskset -c`), when pinned.
    cores: Option<String>,
    /// Runs started, for unique run names and log files.
    runs: usize,
}

/// What an `index` run printed, and how long the process took.
#[derive(Debug, Clone, Copy)]
struct Indexed {
    wall: f64,
    /// The summary's `seconds`: opening the dataset.
    open: f64,
    /// The summary's `plan seconds`.
    plan: f64,
    samples_per_epoch: u64,
    files: usize,
    hits: usize,
}

impl Runner {
    fn command(&self, env: &[(String, String)]) -> Command {
        let mut command = match &self.cores {
            Some(cores) => {
                let mut taskset = Command::new("taskset");
                taskset.args(["-c", cores]).arg(&self.bin);
                taskset
            }
            None => Command::new(&self.bin),
        };
        command
            .envs(env.iter().map(|(k, v)| (k, v)))
            .env("RUST_LOG", "warn")
            .current_dir(&self.dir);
        command
    }

    /// `superflow-pipeline --mcap input index --index-cache cache`, timed from its start to
    /// its exit.
    fn index(
        &mut self,
        input: &str,
        env: &[(String, String)],
        cache: &Path,
    ) -> anyhow::Result<Indexed> {
        let started = Instant::now();
        let output = self
            .command(env)
            .args(["--mcap", input, "--index-cache"])
            .arg(cache)
            .arg("index")
            .stdin(Stdio::null())
            .output()
            .context("starting superflow-pipeline index")?;
        let wall = started.elapsed().as_secs_f64();
        let stdout = String::from_utf8_lossy(&output.stdout);
        if !output.status.success() {
            bail!(
                "superflow-pipeline --mcap {input} index failed:\n{stdout}\n{}",
                String::from_utf8_lossy(&output.stderr)
            );
        }
        let field = |name: &str| -> anyhow::Result<&str> {
            stdout
                .lines()
                .find_map(|l| l.strip_prefix(name))
                .and_then(|rest| rest.split_whitespace().next())
                .with_context(|| format!("no `{name}` in the summary:\n{stdout}"))
        };
        Ok(Indexed {
            wall,
            open: field("seconds")?.parse()?,
            plan: field("plan seconds")?.parse()?,
            samples_per_epoch: field("samples/epoch")?.parse()?,
            files: field("files")?.parse()?,
            hits: field("cache hits")?.parse()?,
        })
    }

    /// The service over `input` for one epoch of `expected` samples, its batches taken by
    /// a subscriber of this process; the proxy's counts over the run when there is one.
    fn serve(
        &mut self,
        input: &str,
        env: &[(String, String)],
        config: &Path,
        cache: &Path,
        expected: u64,
        proxy: Option<&FaultProxy>,
    ) -> anyhow::Result<Served> {
        self.runs += 1;
        let prefix = transport::prefix();
        let run = format!("os{}", self.runs);
        let receiver = transport::BatchReceiver::open(&prefix, &run, 4)?;
        let (subscriber, listener) = (&receiver.subscriber, &receiver.listener);
        let metrics_port = free_port()?;
        let log = self.dir.join(format!("{run}.log"));
        if let Some(proxy) = proxy {
            proxy.reset_counters();
        }
        let started = Instant::now();
        let mut child = self
            .command(env)
            .args(["--mcap", input, "--index-cache"])
            .arg(cache)
            .arg("--config")
            .arg(config)
            .args(["--run", &run, "--epochs", "1"])
            .args(["--metrics-addr", &format!("127.0.0.1:{metrics_port}")])
            .env("SUPERFLOW_IOX_PREFIX", &prefix)
            .stdin(Stdio::null())
            .stdout(Stdio::null())
            .stderr(std::fs::File::create(&log)?)
            .spawn()
            .context("starting the service")?;
        // (seconds since the start, samples) of each batch received.
        let mut received: Vec<(f64, u64)> = Vec::new();
        let mut lost = 0u64;
        let mut last = Instant::now();
        // The service's CPU at its first batch, then at its last.
        let mut cpu_at_first = None;
        let outcome = loop {
            let mut got = false;
            loop {
                match subscriber.receive() {
                    Ok(Some(sample)) => {
                        let at = started.elapsed().as_secs_f64();
                        let header = sample.user_header();
                        if header.flags & superflow_schemas::batch::BATCH_LOST != 0 {
                            lost += 1;
                        }
                        received.push((at, u64::from(header.sample_count)));
                        if cpu_at_first.is_none() {
                            cpu_at_first = Some(Cpu::of(child.id()));
                        }
                        got = true;
                    }
                    Ok(None) => break,
                    Err(e) => bail!("receiving: {e:?}"),
                }
            }
            let samples: u64 = received.iter().map(|r| r.1).sum();
            if samples >= expected {
                break Ok(());
            }
            if got {
                last = Instant::now();
            } else if last.elapsed() > IDLE {
                break Err(anyhow!(
                    "no batch for {IDLE:?} after {samples} of {expected} samples"
                ));
            }
            if let Some(status) = child.try_wait()? {
                break Err(anyhow!(
                    "the service ended ({status}) after {samples} samples"
                ));
            }
            listener
                .timed_wait(|_| {}, Duration::from_millis(10))
                .map_err(|e| anyhow!("waiting for the ready event: {e:?}"))?;
        };
        // The service lingers while this subscriber is attached: its counters are there.
        let cpu = Cpu::of(child.id()).since(&cpu_at_first.unwrap_or_default());
        let metrics = scrape(metrics_port).unwrap_or_default();
        let counters = proxy.map(FaultProxy::counters);
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
        if let Err(e) = outcome {
            bail!(
                "{e}; the service's log:\n{}",
                std::fs::read_to_string(&log).unwrap_or_default()
            );
        }
        let samples: u64 = received.iter().map(|r| r.1).sum();
        let (first_at, first_samples) = received[0];
        let last_at = received.last().map_or(first_at, |r| r.0);
        Ok(Served {
            samples,
            lost,
            first_batch: first_at,
            rate: (samples - first_samples) as f64 / (last_at - first_at).max(1e-9),
            measured: samples - first_samples,
            counters,
            metrics,
            cpu,
        })
    }
}

/// The CPU seconds of process `pid` so far: all its threads (live or ended) together,
/// and its live threads by name (digits taken out: `object-store-3` counts as
/// `object-store-`). Read from /proc at 100 ticks a second (Linux's `USER_HZ`).
#[derive(Debug, Clone, Default)]
struct Cpu {
    total: f64,
    threads: HashMap<String, f64>,
    /// Minor page faults (each a fresh page the kernel zeroed or mapped).
    faults: f64,
    /// Peak resident memory, MB (`VmHWM`).
    peak_mb: f64,
    /// Transparent huge pages faulted in, machine-wide (`thp_fault_alloc` of
    /// /proc/vmstat): each one 2 MiB the kernel zeroed.
    thp_faults: f64,
}

impl Cpu {
    fn of(pid: u32) -> Cpu {
        // (name, CPU seconds, minor faults) of a `stat` line.
        let parse = |stat: &str| -> Option<(String, f64, f64)> {
            let (head, rest) = stat.rsplit_once(") ")?;
            let name = head.split_once(" (")?.1;
            let fields: Vec<&str> = rest.split_whitespace().collect();
            let field = |i: usize| fields.get(i)?.parse::<u64>().ok();
            let ticks = field(11)? + field(12)?;
            let name: String = name.chars().filter(|c| !c.is_ascii_digit()).collect();
            Some((name, ticks as f64 / 100.0, field(7)? as f64))
        };
        let mut cpu = Cpu::default();
        if let Some((_, total, faults)) = std::fs::read_to_string(format!("/proc/{pid}/stat"))
            .ok()
            .as_deref()
            .and_then(parse)
        {
            cpu.total = total;
            cpu.faults = faults;
        }
        cpu.peak_mb = std::fs::read_to_string(format!("/proc/{pid}/status"))
            .ok()
            .and_then(|s| {
                let kb = s.lines().find_map(|l| l.strip_prefix("VmHWM:"))?;
                kb.split_whitespace().next()?.parse::<f64>().ok()
            })
            .map_or(f64::NAN, |kb| kb / 1024.0);
        cpu.thp_faults = std::fs::read_to_string("/proc/vmstat")
            .ok()
            .and_then(|s| {
                let n = s.lines().find_map(|l| l.strip_prefix("thp_fault_alloc "))?;
                n.trim().parse::<f64>().ok()
            })
            .unwrap_or(f64::NAN);
        for task in std::fs::read_dir(format!("/proc/{pid}/task"))
            .into_iter()
            .flatten()
            .flatten()
        {
            if let Some((name, secs, _)) = std::fs::read_to_string(task.path().join("stat"))
                .ok()
                .as_deref()
                .and_then(parse)
            {
                *cpu.threads.entry(name).or_default() += secs;
            }
        }
        cpu
    }

    /// What was spent from `earlier` to this snapshot.
    fn since(&self, earlier: &Cpu) -> Cpu {
        Cpu {
            total: self.total - earlier.total,
            faults: self.faults - earlier.faults,
            thp_faults: self.thp_faults - earlier.thp_faults,
            peak_mb: self.peak_mb,
            threads: self
                .threads
                .iter()
                .map(|(name, secs)| {
                    (
                        name.clone(),
                        secs - earlier.threads.get(name).copied().unwrap_or(0.0),
                    )
                })
                .collect(),
        }
    }

    /// The threads' seconds, largest first, as `name 1.23 s` items.
    fn breakdown(&self) -> String {
        let mut threads: Vec<_> = self.threads.iter().filter(|(_, s)| **s >= 0.01).collect();
        threads.sort_by(|a, b| b.1.total_cmp(a.1));
        threads
            .iter()
            .map(|(name, secs)| format!("{name} {secs:.2} s"))
            .collect::<Vec<_>>()
            .join(", ")
    }
}

/// A free port of 127.0.0.1 (bound, then let go).
fn free_port() -> anyhow::Result<u16> {
    Ok(std::net::TcpListener::bind("127.0.0.1:0")?
        .local_addr()?
        .port())
}

/// The service's Prometheus counters (`name value` lines; labelled ones keep their labels
/// in the name).
fn scrape(port: u16) -> anyhow::Result<HashMap<String, f64>> {
    let mut stream = std::net::TcpStream::connect(("127.0.0.1", port))?;
    stream.set_read_timeout(Some(Duration::from_secs(5)))?;
    write!(
        stream,
        "GET /metrics HTTP/1.1\r\nHost: 127.0.0.1\r\nConnection: close\r\n\r\n"
    )?;
    let mut text = String::new();
    stream.read_to_string(&mut text)?;
    Ok(text
        .lines()
        .filter(|l| !l.starts_with('#'))
        .filter_map(|l| {
            let (name, value) = l.rsplit_once(' ')?;
            Some((name.to_owned(), value.parse().ok()?))
        })
        .collect())
}

/// One service run.
#[derive(Debug, Clone)]
struct Served {
    samples: u64,
    lost: u64,
    /// Seconds from the start to the first batch received.
    first_batch: f64,
    /// Samples/s from the first batch to the last (the first batch's samples not counted).
    rate: f64,
    /// The samples that rate counts.
    measured: u64,
    counters: Option<Counters>,
    metrics: HashMap<String, f64>,
    /// The service's CPU from its first batch to its last.
    cpu: Cpu,
}

impl Served {
    /// The service's CPU ms per sample from its first batch to its last (the first
    /// batch's samples not counted), all threads or those named `prefix…`.
    fn cpu_ms(&self, prefix: Option<&str>) -> f64 {
        let secs = match prefix {
            None => self.cpu.total,
            Some(p) => self
                .cpu
                .threads
                .iter()
                .filter(|(n, _)| n.starts_with(p))
                .map(|(_, s)| s)
                .sum(),
        };
        1e3 * secs / self.measured as f64
    }

    fn metric(&self, name: &str) -> f64 {
        self.metrics.get(name).copied().unwrap_or(f64::NAN)
    }
}

/// A row of the first table: how the drives are reached.
#[derive(Debug, Clone, Copy, PartialEq)]
struct Setting {
    remote: bool,
    latency_ms: u64,
    /// `remote_prefetch_mb` (0: off); `None`: the bench's default budget.
    prefetch_mb: Option<u64>,
}

impl Setting {
    fn label(&self) -> String {
        if !self.remote {
            return "local files".into();
        }
        let mut label = match self.latency_ms {
            0 => "s3://, no added latency".to_string(),
            ms => format!("s3:// + {ms} ms per request"),
        };
        match self.prefetch_mb {
            None => {}
            Some(0) => label.push_str(", prefetch off"),
            Some(mb) => label.push_str(&format!(", prefetch budget {mb} MiB")),
        }
        label
    }

    /// The configuration file of this row (written once per budget).
    fn config(&self, dir: &Path, default_mb: Option<u64>) -> anyhow::Result<PathBuf> {
        let budget = self.prefetch_mb.or(default_mb);
        let path = dir.join(match budget {
            Some(mb) => format!("prefetch-{mb}.toml"),
            None => "prefetch-default.toml".to_string(),
        });
        std::fs::write(
            &path,
            match budget {
                Some(mb) => format!("[ingest]\nremote_prefetch_mb = {mb}\n"),
                None => "[ingest]\n".to_string(),
            },
        )?;
        Ok(path)
    }
}

fn throughput(
    args: &Args,
    runner: &mut Runner,
    server: &S3Server,
    proxy: &FaultProxy,
    out: &mut String,
) -> anyhow::Result<()> {
    let options = DriveOptions::nuscenes(SIZE.0, SIZE.1);
    let sources = [Dialect::Foxglove, Dialect::Ros2]
        .into_iter()
        .map(|d| generated(d, &options))
        .collect::<anyhow::Result<Vec<_>>>()?;
    let local = runner.dir.join("nuscenes");
    eprintln!("uploading {} drives with their sidecars ...", args.drives);
    let started = Instant::now();
    let bytes = place(server, &sources, args.drives, &local, "nuscenes")?;
    eprintln!(
        "uploaded {:.0} MB in {:.1} s",
        bytes as f64 / 1e6,
        started.elapsed().as_secs_f64()
    );
    let url = format!("s3://{BUCKET}/nuscenes/");
    let local_input = local.display().to_string();
    let env = server.env(&proxy.endpoint());

    // Warm index caches (filled here, then only read).
    let (local_cache, remote_cache) = (runner.dir.join("cache-local"), runner.dir.join("cache-s3"));
    proxy.set_plan(FaultPlan::default());
    let indexed = runner.index(&local_input, &[], &local_cache)?;
    let remote_indexed = runner.index(&url, &env, &remote_cache)?;
    anyhow::ensure!(
        indexed.samples_per_epoch == remote_indexed.samples_per_epoch,
        "local {indexed:?} and remote {remote_indexed:?} plans differ"
    );
    let expected = indexed.samples_per_epoch;
    let warm = runner.index(&url, &env, &remote_cache)?;
    anyhow::ensure!(
        warm.hits == warm.files,
        "the remote index cache is not warm: {warm:?}"
    );

    let row = |remote, latency_ms, prefetch_mb| Setting {
        remote,
        latency_ms,
        prefetch_mb,
    };
    let mut settings = vec![row(false, 0, None), row(true, 0, None)];
    for &latency_ms in &args.latencies {
        settings.push(row(true, latency_ms, None));
    }
    if let Some(mb) = args.tight_mb {
        settings.push(row(true, OPEN_LATENCY_MS, Some(mb)));
    }
    for latency_ms in [0, OPEN_LATENCY_MS] {
        settings.push(row(true, latency_ms, Some(0)));
    }
    let mut runs: Vec<Vec<Served>> = vec![Vec::new(); settings.len()];
    for rep in 0..args.reps {
        for (setting, runs) in settings.iter().zip(&mut runs) {
            eprintln!(
                "throughput: {} (run {} of {}), {expected} samples ...",
                setting.label(),
                rep + 1,
                args.reps
            );
            let config = &setting.config(&runner.dir, args.prefetch_mb)?;
            let served = if setting.remote {
                proxy.set_plan(FaultPlan {
                    latency: Duration::from_millis(setting.latency_ms),
                    bandwidth_bytes_per_sec: Some(args.cap()),
                    ..FaultPlan::default()
                });
                runner.serve(&url, &env, config, &remote_cache, expected, Some(proxy))?
            } else {
                runner.serve(&local_input, &[], config, &local_cache, expected, None)?
            };
            eprintln!(
                "  {:.1} samples/s, first batch at {:.2} s, {:.1} CPU ms a sample ({}), {:.0} page faults a sample ({:.1} huge pages machine-wide), peak RSS {:.0} MB{}",
                served.rate,
                served.first_batch,
                served.cpu_ms(None),
                served.cpu.breakdown(),
                served.cpu.faults / served.measured as f64,
                served.cpu.thp_faults / served.measured as f64,
                served.cpu.peak_mb,
                served.counters.map_or(String::new(), |c| format!(
                    ", {} GETs, {:.1} MB ({:.1} MB distinct), prefetched {:.1} MB of which \
                     {:.1} MB dropped unread",
                    c.gets(),
                    c.body_bytes as f64 / 1e6,
                    c.distinct_get_bytes as f64 / 1e6,
                    served.metric("superflow_remote_prefetch_bytes_total") / 1e6,
                    served.metric("superflow_remote_prefetch_unused_bytes_total") / 1e6,
                ))
            );
            runs.push(served);
        }
    }

    // Chunks needed: the demand reads of the prefetch-off run at no added latency.
    let needed_index = settings
        .iter()
        .position(|s| s.remote && s.prefetch_mb == Some(0) && s.latency_ms == 0)
        .context("the prefetch-off row")?;
    let per_sample = |s: &Served, v: u64| v as f64 / s.samples as f64;
    let needed = median(
        &runs[needed_index]
            .iter()
            .filter_map(|s| Some(per_sample(s, s.counters?.distinct_get_bytes)))
            .collect::<Vec<_>>(),
    );
    let local_rate = median(&runs[0].iter().map(|s| s.rate).collect::<Vec<_>>());

    writeln!(
        out,
        "### Throughput: local files against s3:// on loopback\n\n\
         {} drives of nuScenes shape ({}×{} cameras, 8 s, 16 keyframes, zstd chunks of 1 MiB, \
         class maps in a sidecar; copies of one Foxglove and one ROS 2 drive), {bytes_mb:.0} MB \
         with their sidecars, {expected} samples an epoch, default recipe, batches of {BATCH}; \
         the service (`--epochs 1`, warm index cache) with a subscriber of this process. \
         s3:// rows: moto on 127.0.0.1 behind the harness's proxy with the latency shown \
         before each response and a bandwidth cap of {} MB/s shared by all connections; \
         prefetch budget {} (the whole epoch's chunks fit in it){}. Medians of {} run{} \
         per row, the rows interleaved.\n",
        args.drives,
        SIZE.0,
        SIZE.1,
        args.bandwidth,
        match args.prefetch_mb {
            Some(mb) => format!("`remote_prefetch_mb = {mb}`"),
            None => "the default (`remote_prefetch_mb = 256`)".to_string(),
        },
        match args.tight_mb {
            Some(mb) => format!(
                "; the \"prefetch budget {mb} MiB\" row's budget is below what the batch \
                 being built and the two read ahead hold (12 samples of ~1.5 MB of chunks, and \
                 the chunks read before that are kept until evicted)"
            ),
            None => String::new(),
        },
        args.reps,
        if args.reps == 1 { "" } else { "s" },
        bytes_mb = bytes as f64 / 1e6,
    )?;
    writeln!(
        out,
        "| drives | samples/s | vs local | first batch s | service CPU ms / sample | of it object-store threads | page faults / sample | peak RSS MB | GETs / sample | MB read / sample | of them distinct | MB of chunks needed / sample | read / needed | prefetch hits / misses |"
    )?;
    writeln!(
        out,
        "|---|---:|---:|---:|---:|---:|---:|---:|---:|---:|---:|---:|---:|---:|"
    )?;
    for (setting, runs) in settings.iter().zip(&runs) {
        let m = |f: &dyn Fn(&Served) -> f64| median(&runs.iter().map(f).collect::<Vec<_>>());
        let rate = m(&|s| s.rate);
        let first = m(&|s| s.first_batch);
        let cpu = m(&|s| s.cpu_ms(None));
        let store_cpu = if setting.remote {
            format!("{:.1}", m(&|s| s.cpu_ms(Some("object-store"))))
        } else {
            "–".into()
        };
        let faults = m(&|s| s.cpu.faults / s.measured as f64);
        let peak = m(&|s| s.cpu.peak_mb);
        let (gets, read, distinct, ratio, prefetch) = if setting.remote {
            let gets = m(&|s| per_sample(s, s.counters.map_or(0, |c| c.gets())));
            let read = m(&|s| per_sample(s, s.counters.map_or(0, |c| c.body_bytes)));
            let distinct = m(&|s| per_sample(s, s.counters.map_or(0, |c| c.distinct_get_bytes)));
            let hits = m(&|s| s.metric("superflow_remote_prefetch_hits_total"));
            let misses = m(&|s| s.metric("superflow_remote_prefetch_misses_total"));
            (
                format!("{gets:.2}"),
                format!("{:.2}", read / 1e6),
                format!("{:.2}", distinct / 1e6),
                format!("{:.2}×", read / needed),
                format!("{hits:.0} / {misses:.0}"),
            )
        } else {
            let dash = || "–".to_string();
            (dash(), dash(), dash(), dash(), dash())
        };
        writeln!(
            out,
            "| {} | {rate:.1} | {:.1} % | {first:.2} | {cpu:.1} | {store_cpu} | {faults:.0} | {peak:.0} | {gets} | {read} | {distinct} | {} | {ratio} | {prefetch} |",
            setting.label(),
            100.0 * rate / local_rate,
            if setting.remote {
                format!("{:.2}", needed / 1e6)
            } else {
                "–".into()
            },
        )?;
    }
    let failed: f64 = runs
        .iter()
        .flatten()
        .map(|s| s.metric("superflow_failed_samples_total"))
        .filter(|v| v.is_finite())
        .sum();
    let lost: u64 = runs.iter().flatten().map(|s| s.lost).sum();
    writeln!(
        out,
        "\nsamples/s: from the first batch received to the last (the first batch's samples \
         not counted); first batch: seconds from the service's start. Service CPU: the \
         service process's CPU time (/proc) over the same span, per sample; of it, its \
         `object-store` threads (the runtime the HTTP requests run on); page faults: its \
         minor faults over the span, per sample; peak RSS: its `VmHWM` at the end. GETs and MB read: the \
         proxy's counts (response bodies, the LIST page included) over the whole run, per \
         sample served; distinct: the bytes of the objects those GETs covered, each byte \
         once however often it was read (the union of the responses' `Content-Range`s). \
         Chunks needed: the distinct bytes of the prefetch-off run at no added latency \
         (demand reads only: each GET is one chunk record a sample read), per sample. \
         Prefetch hits and misses: the service's own counters \
         (`superflow_remote_prefetch_*`). Failed samples over all runs: {failed}; lost \
         batches: {lost}.\n"
    )?;
    Ok(())
}

fn open(
    args: &Args,
    runner: &mut Runner,
    server: &S3Server,
    proxy: &FaultProxy,
    out: &mut String,
) -> anyhow::Result<()> {
    let source = generated(Dialect::Foxglove, &DriveOptions::short())?;
    let drive_bytes = std::fs::metadata(&source.drive)?.len();
    let count = args.small;
    eprintln!(
        "open: uploading {count} small drives ({:.2} MB each) ...",
        drive_bytes as f64 / 1e6
    );
    let started = Instant::now();
    // Local copies, not links: a local file's fingerprint is its inode's.
    let local = runner.dir.join("small");
    let _ = std::fs::remove_dir_all(&local);
    std::fs::create_dir_all(&local)?;
    let bytes = std::fs::read(&source.drive)?;
    for i in 0..count {
        std::fs::write(local.join(format!("drive-{i:04}.mcap")), &bytes)?;
    }
    server.put_many(
        BUCKET,
        (0..count).map(|i| (format!("small/drive-{i:04}.mcap"), bytes.clone())),
    );
    eprintln!("uploaded in {:.1} s", started.elapsed().as_secs_f64());
    let url = format!("s3://{BUCKET}/small/");
    let env = server.env(&proxy.endpoint());
    proxy.set_plan(FaultPlan {
        latency: Duration::from_millis(OPEN_LATENCY_MS),
        bandwidth_bytes_per_sec: args.open_bandwidth.map(|mb| mb * 1_000_000),
        ..FaultPlan::default()
    });
    let warm_reps = if args.quick { 1 } else { 3 };
    let mut rows = Vec::new();
    for remote in [true, false] {
        let cache = runner.dir.join(if remote {
            "small-cache-s3"
        } else {
            "small-cache-local"
        });
        let _ = std::fs::remove_dir_all(&cache);
        std::fs::create_dir_all(&cache)?;
        let (input, env): (String, &[(String, String)]) = if remote {
            (url.clone(), &env)
        } else {
            (local.display().to_string(), &[])
        };
        let name = if remote {
            format!("s3:// + {OPEN_LATENCY_MS} ms per request")
        } else {
            "local files".to_string()
        };
        for warm in [false, true] {
            let reps = if warm { warm_reps } else { 1 };
            let mut walls = Vec::new();
            let mut last = None;
            for _ in 0..reps {
                eprintln!("open: {name}, {} ...", if warm { "warm" } else { "cold" });
                proxy.reset_counters();
                let indexed = runner.index(&input, env, &cache)?;
                anyhow::ensure!(
                    indexed.files == count,
                    "{count} drives, {} files indexed",
                    indexed.files
                );
                if warm {
                    anyhow::ensure!(indexed.hits == count, "warm but {indexed:?}");
                }
                eprintln!("  {:.2} s", indexed.wall);
                walls.push(indexed.wall);
                last = Some((indexed, proxy.counters()));
            }
            let (indexed, counters) = last.context("no run")?;
            rows.push((
                name.clone(),
                warm,
                median(&walls),
                indexed,
                counters,
                remote,
            ));
        }
    }
    writeln!(
        out,
        "### Opening {count} remote drives\n\n\
         {count} copies of one small drive (`DriveOptions::short()`: 1.5 s, 3 keyframes, 2 \
         cameras at 240×136, {:.2} MB, Foxglove), uploaded under one prefix; \
         `superflow-pipeline --mcap s3://{BUCKET}/small/ index --index-cache DIR` through the \
         proxy with {OPEN_LATENCY_MS} ms before each response ({}), and the same drives as \
         local files for reference. Cold: an empty cache directory; warm: the same command \
         again (median of {warm_reps}).\n",
        drive_bytes as f64 / 1e6,
        match args.open_bandwidth {
            Some(mb) => format!("a bandwidth cap of {mb} MB/s"),
            None => "no bandwidth cap".to_string(),
        },
    )?;
    writeln!(
        out,
        "| drives | cache | wall s | open s | plan s | LISTs | GETs | HEADs | MB read | goal |"
    )?;
    writeln!(out, "|---|---|---:|---:|---:|---:|---:|---:|---:|---|")?;
    for (name, warm, wall, indexed, counters, remote) in rows {
        let (lists, gets, heads, mb, goal) = if remote {
            let goal = if warm { 1.0 } else { 5.0 };
            (
                counters.list.to_string(),
                counters.gets().to_string(),
                counters.head.to_string(),
                format!("{:.1}", counters.body_bytes as f64 / 1e6),
                format!(
                    "≤ {goal:.0} s: {}",
                    if wall <= goal { "met" } else { "missed" }
                ),
            )
        } else {
            let dash = || "–".to_string();
            (dash(), dash(), dash(), dash(), dash())
        };
        writeln!(
            out,
            "| {name} | {} | {wall:.2} | {:.2} | {:.2} | {lists} | {gets} | {heads} | {mb} | {goal} |",
            if warm { "warm" } else { "cold" },
            indexed.open,
            indexed.plan,
        )?;
    }
    writeln!(
        out,
        "\nwall: the `index` process from its start to its exit (open, plan, summary); open \
         and plan: its summary's `seconds` (opening the dataset: listing, reading and \
         indexing the files, or their cache entries) and `plan seconds` (the plan, with \
         each drive's camera timing measured from its sweeps, or read from the cache). \
         Requests and MB: the proxy's counts over the process.\n"
    )?;
    Ok(())
}

fn main() -> anyhow::Result<()> {
    let args = Args::parse()?;
    let started = Instant::now();
    let load_start = load_average(3);
    let date = now_utc();
    let bin = pipeline_binary()?;
    let cores = cores();
    // This process (and the children it starts from now on: moto) on the last core, the
    // pipeline on the others.
    let pipeline_cores = if args.pin {
        let last = cores - 1;
        let status = Command::new("taskset")
            .args([
                "-a",
                "-cp",
                &last.to_string(),
                &std::process::id().to_string(),
            ])
            .stdout(Stdio::null())
            .status()
            .context("running taskset")?;
        anyhow::ensure!(status.success(), "taskset -a -cp {last} failed");
        Some(if last == 1 {
            "0".to_string()
        } else {
            format!("0-{}", last - 1)
        })
    } else {
        None
    };
    let dir = args.keep.clone().unwrap_or_else(|| {
        std::env::temp_dir().join(format!(
            "superflow-object-store-bench-{}",
            std::process::id()
        ))
    });
    std::fs::create_dir_all(&dir)?;
    eprintln!("object_store bench in {} ...", dir.display());
    let server = S3Server::start();
    server.create_bucket(BUCKET);
    let proxy = FaultProxy::start(&server.endpoint(), FaultPlan::default());
    let mut runner = Runner {
        bin,
        dir: dir.clone(),
        cores: pipeline_cores.clone(),
        runs: 0,
    };
    let mut tables = String::new();
    if args.throughput {
        throughput(&args, &mut runner, &server, &proxy, &mut tables)?;
    }
    if args.open {
        open(&args, &mut runner, &server, &proxy, &mut tables)?;
    }
    drop(proxy);
    drop(server);
    let left = transport::release_shared_memory();
    if args.keep.is_none() {
        std::fs::remove_dir_all(&dir)?;
    }
    let mut out = String::new();
    writeln!(
        out,
        "Machine: {} ({cores} cores), {date}; load average {load_start} at start, {} at end; \
         {} build, {:.0} s. {}\n",
        cpu_model(),
        load_average(3),
        if cfg!(debug_assertions) {
            "debug"
        } else {
            "release"
        },
        started.elapsed().as_secs_f64(),
        match &pipeline_cores {
            Some(on) => format!(
                "The pipeline ran on core(s) {on} (`taskset`); moto, the proxy and the \
                 subscriber on core {}.",
                cores - 1
            ),
            None => "Every process shared every core (`--no-pin`).".to_string(),
        },
    )?;
    out.push_str(&tables);
    writeln!(
        out,
        "The latency and bandwidth cap come from the test harness's proxy \
         (tests/src/s3/proxy.rs), not object_store's throttle wrapper. Shared memory left in \
         /dev/shm: {}.",
        transport::left_in_shm(&left),
    )?;
    transport::publish_report("bench-object-store.md", &out, &left)
}
