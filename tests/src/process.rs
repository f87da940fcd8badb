//! Child processes for the end-to-end tests: killed when dropped (a failing test leaves
//! nothing running), waited for with a watchdog, their output read line by line, and
//! the check that they left nothing in /dev/shm; and the commands that start the
//! project's binaries as the tests run them (a serving pipeline, a one-shot pipeline
//! command, a subscriber, a trainer), each a [`Command`] the caller adds to.

#![allow(clippy::unwrap_used, clippy::expect_used)] // test support fails loudly

use std::path::Path;
use std::process::{Child, Command, Stdio};
use std::sync::mpsc::Receiver;
use std::time::{Duration, Instant};

/// A unique iceoryx2 prefix for one test of this test process.
pub fn prefix(test: &str) -> String {
    format!("sft{}{test}", std::process::id())
}

/// A child process killed (and reaped) when dropped, so a failing test leaves no
/// pipeline or subscriber running.
#[derive(Debug)]
pub struct Proc(pub Option<Child>);

impl std::ops::Deref for Proc {
    type Target = Child;
    fn deref(&self) -> &Child {
        self.0.as_ref().expect("process taken")
    }
}

impl std::ops::DerefMut for Proc {
    fn deref_mut(&mut self) -> &mut Child {
        self.0.as_mut().expect("process taken")
    }
}

impl Drop for Proc {
    fn drop(&mut self) {
        if let Some(mut child) = self.0.take() {
            let _ = child.kill();
            let _ = child.wait();
        }
    }
}

/// Waits for `child` with a watchdog; returns (success, stdout, stderr).
pub fn finish(mut proc: Proc, limit: Duration) -> (bool, String, String) {
    let mut child = proc.0.take().expect("process taken");
    let started = Instant::now();
    loop {
        if let Some(status) = child.try_wait().unwrap() {
            let out = child.wait_with_output().unwrap();
            return (
                status.success(),
                String::from_utf8_lossy(&out.stdout).into_owned(),
                String::from_utf8_lossy(&out.stderr).into_owned(),
            );
        }
        if started.elapsed() > limit {
            child.kill().unwrap();
            let out = child.wait_with_output().unwrap();
            panic!(
                "watchdog: process ran past {limit:?}\nstdout:\n{}\nstderr:\n{}",
                String::from_utf8_lossy(&out.stdout),
                String::from_utf8_lossy(&out.stderr)
            );
        }
        std::thread::sleep(Duration::from_millis(20));
    }
}

/// The lines `stream` produces, as they come (read on a thread).
pub fn lines_of(stream: impl std::io::Read + Send + 'static) -> std::sync::mpsc::Receiver<String> {
    let (tx, rx) = std::sync::mpsc::channel();
    std::thread::spawn(move || {
        for line in std::io::BufRead::lines(std::io::BufReader::new(stream)).map_while(Result::ok) {
            if tx.send(line).is_err() {
                break;
            }
        }
    });
    rx
}

/// The lines `rx` ([`lines_of`]) gives until none comes for `quiet` (its process ended
/// or fell silent), each ending in a newline.
pub fn drain(rx: &Receiver<String>, quiet: Duration) -> String {
    let mut text = String::new();
    while let Ok(line) = rx.recv_timeout(quiet) {
        text.push_str(&line);
        text.push('\n');
    }
    text
}

/// Sends `signal` (`-INT`, `-TERM`) to a running process.
pub fn send_signal(proc: &Proc, signal: &str) {
    let status = Command::new("kill")
        .args([signal, &proc.id().to_string()])
        .status()
        .unwrap();
    assert!(status.success());
}

/// Stops `proc` as an operator does, with SIGTERM (a pipeline then removes its shared
/// memory), and waits for it under the watchdog `limit` ([`finish`]): (success, stdout,
/// stderr).
pub fn stop(proc: Proc, limit: Duration) -> (bool, String, String) {
    send_signal(&proc, "-TERM");
    finish(proc, limit)
}

/// [`stop`], failing unless `proc` exits successfully; its stderr.
pub fn stop_cleanly(proc: Proc, limit: Duration) -> String {
    let (ok, _, err) = stop(proc, limit);
    assert!(ok, "{err}");
    err
}

/// Fails if a file of `prefix` (other than iceoryx2's per-prefix `.global_mgmt`) is left
/// in /dev/shm.
pub fn no_shared_memory_left(prefix: &str) {
    let left: Vec<String> = std::fs::read_dir("/dev/shm")
        .unwrap()
        .filter_map(|e| e.ok())
        .map(|e| e.file_name().to_string_lossy().into_owned())
        .filter(|n| n.starts_with(prefix) && !n.ends_with(".global_mgmt"))
        .collect();
    assert!(left.is_empty(), "left in /dev/shm: {left:?}");
}

/// Spawns `command` as a [`Proc`].
pub fn spawn(command: &mut Command) -> Proc {
    Proc(Some(command.spawn().unwrap()))
}

/// What a serving pipeline and a trainer start with: the iceoryx2 prefix `prefix`, logging
/// at `info`, the workspace root, stdout dropped and stderr piped.
fn in_run<'a>(command: &'a mut Command, prefix: &str) -> &'a mut Command {
    command
        .env("SUPERFLOW_IOX_PREFIX", prefix)
        .env("RUST_LOG", "info")
        .current_dir(crate::workspace_root())
        .stdout(Stdio::null())
        .stderr(Stdio::piped())
}

/// `superflow-pipeline` serving under the iceoryx2 prefix `prefix`, no argument yet:
/// from the workspace root, logging at `info`, its stdout dropped and its stderr piped
/// (for [`wait_until_ready`]). `subscriber` is the test's
/// `env!("CARGO_BIN_EXE_superflow-subscriber")` (the pipeline binary lies beside it).
/// Every serving pipeline of the tests starts here: the caller adds its arguments
/// (`--run`, its inputs, `--index-cache off`, …) and sets over these what it runs
/// otherwise (`RUST_LOG`, `NO_COLOR`, where stderr goes).
pub fn pipeline_server(subscriber: &str, prefix: &str) -> Command {
    let mut command = Command::new(crate::pipeline_binary(subscriber));
    in_run(&mut command, prefix);
    command
}

/// `superflow-pipeline --mcap drive --run run args…` ([`pipeline_server`]), started.
pub fn pipeline(subscriber: &str, drive: &str, prefix: &str, run: &str, args: &[&str]) -> Proc {
    spawn(&mut pipeline_command(subscriber, drive, prefix, run, args))
}

/// [`pipeline`] of the ROS 2 sample drive ([`crate::SAMPLE_DRIVE`]).
pub fn serve(subscriber: &str, prefix: &str, run: &str, args: &[&str]) -> Proc {
    pipeline(subscriber, crate::SAMPLE_DRIVE, prefix, run, args)
}

/// The command [`pipeline`] spawns, for a caller that adds to it (an environment, a log
/// level) before spawning it.
pub fn pipeline_command(
    subscriber: &str,
    drive: &str,
    prefix: &str,
    run: &str,
    args: &[&str],
) -> Command {
    let mut command = pipeline_server(subscriber, prefix);
    command.args(["--mcap", drive, "--run", run]).args(args);
    command
}

/// Reads the stderr of `pipe` (a [`pipeline_server`], its stderr piped) until the
/// pipeline logs `waiting for subscribers`: it is up and holds its first batch for them.
/// Its further stderr lines ([`lines_of`]) and the log read so far; fails, with that
/// log, when no line comes for `limit`.
pub fn wait_until_ready(pipe: &mut Proc, limit: Duration) -> (Receiver<String>, String) {
    let rx = lines_of(pipe.stderr.take().expect("the pipeline's stderr is piped"));
    let mut log = String::new();
    while !log.contains("waiting for subscribers") {
        let line = rx
            .recv_timeout(limit)
            .unwrap_or_else(|_| panic!("the pipeline starts:\n{log}"));
        log.push_str(&line);
        log.push('\n');
    }
    (rx, log)
}

/// `superflow-pipeline args…` as a one-shot command (`inspect`, `sample`, `batch`,
/// `index`, …), run to its end under the watchdog `limit`: from the workspace root with
/// `env` added to its environment (an object store's endpoint and credentials), logging
/// warnings only, without colours. (success, stdout, stderr); fails on a panic (the word
/// `panicked` in either output).
pub fn run_pipeline(
    subscriber: &str,
    args: &[&str],
    env: &[(String, String)],
    limit: Duration,
) -> (bool, String, String) {
    let (ok, stdout, stderr) = finish(
        spawn(
            Command::new(crate::pipeline_binary(subscriber))
                .args(args)
                .envs(env.iter().map(|(k, v)| (k, v)))
                .env("RUST_LOG", "warn")
                .env("NO_COLOR", "1")
                .current_dir(crate::workspace_root())
                .stdout(Stdio::piped())
                .stderr(Stdio::piped()),
        ),
        limit,
    );
    assert!(
        !stderr.contains("panicked") && !stdout.contains("panicked"),
        "superflow-pipeline {args:?} panicked:\n{stderr}"
    );
    (ok, stdout, stderr)
}

/// `superflow-subscriber --run run args…` under the iceoryx2 prefix `prefix`, its output
/// piped.
pub fn subscriber(subscriber: &str, prefix: &str, run: &str, args: &[&str]) -> Proc {
    spawn(
        Command::new(subscriber)
            .args(["--run", run])
            .args(args)
            .env("SUPERFLOW_IOX_PREFIX", prefix)
            .current_dir(crate::workspace_root())
            .stdout(Stdio::piped())
            .stderr(Stdio::piped()),
    )
}

/// `superflow-trainer` (the binary beside `subscriber`), under `launcher` when given
/// ([`mpirun`]), training run `run` for `steps` steps with the tiny presets under the
/// iceoryx2 prefix `prefix`, waiting at most 120 s for a batch: `--run run --steps steps
/// --unet tiny --vit tiny --pixel-stride 4 --timeout-secs 120`, from the workspace root,
/// logging at `info`, its stdout dropped and its stderr piped. The caller adds the rest
/// (`--out`) and sets over these what it runs otherwise.
pub fn trainer_command(
    subscriber: &str,
    launcher: Option<Command>,
    prefix: &str,
    run: &str,
    steps: u64,
) -> Command {
    let binary = crate::trainer_binary(subscriber);
    let mut command = match launcher {
        Some(mut launcher) => {
            launcher.arg(binary);
            launcher
        }
        None => Command::new(binary),
    };
    in_run(&mut command, prefix)
        .args(["--run", run, "--steps", &steps.to_string()])
        .args(["--unet", "tiny", "--vit", "tiny", "--pixel-stride", "4"])
        .args(["--timeout-secs", "120"]);
    command
}

/// [`trainer_command`] writing into `out` (`--out out extra…`), started.
pub fn trainer(
    subscriber: &str,
    prefix: &str,
    run: &str,
    steps: u64,
    out: &Path,
    extra: &[&str],
) -> Proc {
    spawn(
        trainer_command(subscriber, None, prefix, run, steps)
            .arg("--out")
            .arg(out)
            .args(extra),
    )
}

/// The batches a `superflow-subscriber` printed (its JSON lines with a `sequence`; a lost
/// batch has `"lost":true` and no sample).
pub fn batches(stdout: &str) -> Vec<serde_json::Value> {
    stdout
        .lines()
        .map(|l| serde_json::from_str::<serde_json::Value>(l).unwrap())
        .filter(|v| v.get("sequence").is_some())
        .collect()
}

/// `(epoch, keyframe)` of every sample of `batches` (as [`batches`] returns them).
pub fn sample_keys(batches: &[serde_json::Value]) -> Vec<(u64, u64)> {
    batches
        .iter()
        .flat_map(|b| b["samples"].as_array().unwrap().clone())
        .map(|s| (s[0].as_u64().unwrap(), s[2].as_u64().unwrap()))
        .collect()
}

/// A free TCP port of 127.0.0.1 (for a server a child process starts: a metrics
/// endpoint, a rendezvous).
pub fn free_port() -> String {
    let listener = std::net::TcpListener::bind("127.0.0.1:0").unwrap();
    listener.local_addr().unwrap().port().to_string()
}

/// One `GET /metrics` of the Prometheus endpoint at `addr`: the whole response, status
/// line and headers included.
pub fn scrape(addr: &str) -> std::io::Result<String> {
    use std::io::{Read as _, Write as _};
    let mut stream = std::net::TcpStream::connect(addr)?;
    stream.set_read_timeout(Some(Duration::from_secs(30)))?;
    stream.write_all(b"GET /metrics HTTP/1.1\r\nHost: x\r\n\r\n")?;
    let mut text = String::new();
    stream.read_to_string(&mut text)?;
    Ok(text)
}

/// The value of the Prometheus counter `name` in `text`, summed over its labelled series
/// (`name{cause="…"} n`); 0 when absent.
pub fn counter(text: &str, name: &str) -> u64 {
    text.lines()
        .filter_map(|l| {
            let rest = l.strip_prefix(name)?;
            let value = match rest.strip_prefix('{') {
                Some(labelled) => labelled.split_once('}')?.1,
                None => rest.strip_prefix(' ')?,
            };
            value.trim().parse::<u64>().ok()
        })
        .sum()
}

/// Fails unless, in each of `epochs`, the ranks' `(epoch, keyframe)` samples cover every
/// one of `keyframes` exactly once, each rank taking an equal share.
pub fn assert_shards_cover(per_rank: &[Vec<(u64, u64)>], epochs: u64, keyframes: u64) {
    let share = keyframes as usize / per_rank.len();
    for epoch in 0..epochs {
        let mut seen = std::collections::BTreeMap::<u64, usize>::new();
        for (rank, keys) in per_rank.iter().enumerate() {
            let mine: Vec<u64> = keys.iter().filter(|k| k.0 == epoch).map(|k| k.1).collect();
            assert_eq!(mine.len(), share, "rank {rank} epoch {epoch}: {mine:?}");
            for k in mine {
                *seen.entry(k).or_default() += 1;
            }
        }
        assert_eq!(seen.len() as u64, keyframes, "epoch {epoch}: {seen:?}");
        assert!(seen.values().all(|n| *n == 1), "epoch {epoch}: {seen:?}");
    }
}

/// SIGKILLs `first` (a pipeline) once `reader` printed `lines` lines, starts `restart()`
/// in its place, then waits for the reader (which must succeed) and the restarted
/// pipeline; every line the reader printed.
pub fn kill_and_restart(
    mut reader: Proc,
    mut first: Proc,
    lines: usize,
    restart: impl FnOnce() -> Proc,
    limit: Duration,
) -> String {
    let rx = lines_of(reader.stdout.take().expect("the reader's stdout is piped"));
    let mut out = String::new();
    for _ in 0..lines {
        out.push_str(&rx.recv_timeout(limit).expect("lines before the kill"));
        out.push('\n');
    }
    first.kill().unwrap(); // SIGKILL
    let _ = first.wait();
    let second = restart();
    let (ok, _, err) = finish(reader, limit);
    assert!(ok, "{err}\n{out}");
    out.push_str(&drain(&rx, Duration::from_secs(5)));
    let (ok, _, err) = finish(second, limit);
    assert!(ok, "{err}");
    out
}

/// `mpirun -np ranks` as the data-parallel tests run it: on this host, oversubscribed
/// (CI has 2 cores), allowed as root (CI runs as root), waiting ranks yielding the CPU
/// instead of busy-polling, and the shared-memory transport without CMA (ptrace is
/// off in containers). Open MPI's `mpirun` must be installed (`openmpi-bin`).
///
/// Each job gets its own session directory (`TMPDIR`, which Open MPI puts its
/// `ompi.<host>.<uid>` tree under). Jobs started together by parallel tests otherwise
/// race to create and remove the one shared `/tmp/ompi.<host>.<uid>`: Open MPI 4.1
/// fails `orte_init` with "mkdir ... File exists" when one job creates it between
/// another's check and its `mkdir` (seen once in CI). `mpirun` removes its tree when it
/// ends; the empty directory stays in the system's temporary directory.
pub fn mpirun(ranks: usize) -> Command {
    static JOBS: std::sync::atomic::AtomicUsize = std::sync::atomic::AtomicUsize::new(0);
    let job = JOBS.fetch_add(1, std::sync::atomic::Ordering::Relaxed);
    let session = std::env::temp_dir().join(format!("sfmpi-{}-{job}", std::process::id()));
    std::fs::create_dir_all(&session).expect("a session directory for mpirun");
    let mut command = Command::new("mpirun");
    command
        .args([
            "-np",
            &ranks.to_string(),
            "--oversubscribe",
            "--bind-to",
            "none",
        ])
        .env("OMPI_ALLOW_RUN_AS_ROOT", "1")
        .env("OMPI_ALLOW_RUN_AS_ROOT_CONFIRM", "1")
        .env("OMPI_MCA_mpi_yield_when_idle", "1")
        .env("OMPI_MCA_btl_vader_single_copy_mechanism", "none")
        .env("TMPDIR", &session);
    command
}
