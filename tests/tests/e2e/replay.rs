//! Replay: the real `superflow-pipeline` and two real `superflow-trainer` processes
//! (tiny presets) on the sample drives of both dialects, each test with its own run and
//! iceoryx2 prefix (so they run in parallel), and the faults a long run meets: a
//! trainer SIGKILLed mid-epoch and resumed, the pipeline SIGKILLed and restarted, a
//! stalled (SIGSTOPped) trainer, and two simulated hosts sharing each epoch. Every test
//! accounts for every sample by its id (epoch, index in the epoch) in the trainers'
//! `metrics.jsonl` — one record per trained step, each sample exactly once per epoch —
//! and checks that nothing is left in /dev/shm.

#![allow(clippy::unwrap_used, clippy::expect_used)] // tests fail loudly on purpose

use std::collections::BTreeMap;
use std::path::PathBuf;
use std::process::{Command, Stdio};
use std::time::{Duration, Instant};
use superflow_tests::process::{Proc, finish, no_shared_memory_left, prefix, send_signal, spawn};
use superflow_tests::{pipeline_binary, workspace_binary, workspace_root};
use superflow_trainer::metrics::{self, StepRecord};

const ROS2: &str = "recordings/drives/street_ros2.mcap";
const FOXGLOVE: &str = "recordings/drives/street_foxglove.mcap";
/// Keyframes of one sample drive (0.5 s apart over 3 s).
const KEYFRAMES: u64 = 6;
const LIMIT: Duration = Duration::from_secs(600);
/// The pipeline's flags for 2 ranks, batches of 1, 3 epochs.
const SHARDS_OF_1_FOR_3_EPOCHS: [&str; 8] = [
    "--world-size",
    "2",
    "--batch-size",
    "1",
    "--epochs",
    "3",
    "--subscribers",
    "1",
];

/// One test's run: its name, iceoryx2 prefix and scratch directory (logs, outputs).
struct Run {
    name: String,
    prefix: String,
    dir: PathBuf,
}

impl Run {
    fn new(name: &str) -> Self {
        let dir =
            std::env::temp_dir().join(format!("superflow-replay-{name}-{}", std::process::id()));
        let _ = std::fs::remove_dir_all(&dir);
        std::fs::create_dir_all(&dir).unwrap();
        Self {
            name: name.to_string(),
            prefix: prefix(name),
            dir,
        }
    }

    fn log(&self, name: &str) -> std::fs::File {
        std::fs::File::create(self.dir.join(format!("{name}.log"))).unwrap()
    }

    fn read_log(&self, name: &str) -> String {
        std::fs::read_to_string(self.dir.join(format!("{name}.log"))).unwrap_or_default()
    }

    /// `superflow-pipeline --run <name>` on `drives` with `args`; its log goes to
    /// `<dir>/<log>.log`.
    fn pipeline(&self, log: &str, drives: &[&str], args: &[&str]) -> Proc {
        spawn(
            Command::new(pipeline_binary(env!("CARGO_BIN_EXE_superflow-subscriber")))
                .arg("--mcap")
                .args(drives)
                .args(["--run", &self.name])
                .args(args)
                .env("SUPERFLOW_IOX_PREFIX", &self.prefix)
                .env("RUST_LOG", "info")
                .current_dir(workspace_root())
                .stdout(Stdio::null())
                .stderr(self.log(log)),
        )
    }

    /// `superflow-trainer` (tiny presets) for `steps` steps into `<dir>/<name>/`.
    fn trainer(&self, name: &str, steps: u64, args: &[&str]) -> Proc {
        spawn(
            Command::new(workspace_binary(
                env!("CARGO_BIN_EXE_superflow-subscriber"),
                "superflow-trainer",
            ))
            .args(["--run", &self.name, "--steps", &steps.to_string()])
            .args(["--unet", "tiny", "--vit", "tiny", "--pixel-stride", "4"])
            .args(["--timeout-secs", "300", "--out"])
            .arg(self.dir.join(name))
            .args(args)
            .env("SUPERFLOW_IOX_PREFIX", &self.prefix)
            .env("RUST_LOG", "info")
            .current_dir(workspace_root())
            .stdout(Stdio::null())
            .stderr(self.log(name)),
        )
    }

    fn metrics_path(&self, trainer: &str) -> PathBuf {
        self.dir.join(trainer).join("metrics.jsonl")
    }

    /// Steps recorded so far by `trainer` (0 before its first).
    fn steps_done(&self, trainer: &str) -> u64 {
        std::fs::read_to_string(self.metrics_path(trainer))
            .map(|t| t.lines().filter(|l| l.ends_with('}')).count() as u64)
            .unwrap_or(0)
    }

    /// Waits until `trainer` has recorded `step` steps.
    fn wait_for_step(&self, trainer: &str, step: u64) {
        let started = Instant::now();
        while self.steps_done(trainer) < step {
            assert!(
                started.elapsed() < LIMIT,
                "{trainer} never reached step {step}:\n{}",
                self.read_log(trainer)
            );
            std::thread::sleep(Duration::from_millis(50));
        }
    }

    /// Waits until `<name>.log` contains `needle`.
    fn wait_for_log(&self, name: &str, needle: &str) {
        let started = Instant::now();
        while !self.read_log(name).contains(needle) {
            assert!(
                started.elapsed() < LIMIT,
                "{name} never logged `{needle}`:\n{}",
                self.read_log(name)
            );
            std::thread::sleep(Duration::from_millis(50));
        }
    }

    /// Waits for a process to exit successfully; its log is in the failure message.
    fn succeeds(&self, proc: Proc, log: &str) {
        let (ok, _, _) = finish(proc, LIMIT);
        assert!(ok, "{log} failed:\n{}", self.read_log(log));
    }

    /// The records of `trainer`: exactly one per step 1..=`steps`, in order.
    fn lineage(&self, trainer: &str, steps: u64) -> Vec<StepRecord> {
        let records = metrics::read(&self.metrics_path(trainer)).unwrap();
        let numbers: Vec<u64> = records.iter().map(|r| r.step).collect();
        assert_eq!(
            numbers,
            (1..=steps).collect::<Vec<_>>(),
            "{trainer}: one record per step"
        );
        for r in &records {
            assert!(
                [r.loss, r.l_sc, r.l_tc, r.l_d2s]
                    .iter()
                    .all(|v| v.is_finite() && *v > 0.0),
                "{trainer}: {r:?}"
            );
        }
        records
    }

    fn cleanup(self) {
        no_shared_memory_left(&self.prefix);
        let _ = std::fs::remove_dir_all(&self.dir);
    }
}

/// Sample ids of all `records` by epoch, sorted.
fn ids_by_epoch<'a>(records: impl IntoIterator<Item = &'a StepRecord>) -> BTreeMap<u64, Vec<u64>> {
    let mut seen: BTreeMap<u64, Vec<u64>> = BTreeMap::new();
    for r in records {
        for &[epoch, index] in &r.sample_ids {
            seen.entry(epoch).or_default().push(index);
        }
    }
    seen.values_mut().for_each(|ids| ids.sort_unstable());
    seen
}

/// Every one of `epochs` epochs saw each of its `keyframes` samples exactly once.
fn each_sample_once<'a>(
    records: impl IntoIterator<Item = &'a StepRecord>,
    epochs: u64,
    keyframes: u64,
) {
    let seen = ids_by_epoch(records);
    assert_eq!(
        seen.keys().copied().collect::<Vec<_>>(),
        (0..epochs).collect::<Vec<_>>()
    );
    for (epoch, ids) in seen {
        assert_eq!(
            ids,
            (0..keyframes).collect::<Vec<_>>(),
            "epoch {epoch}: each sample once"
        );
    }
}

#[test]
fn sharded_trainers_on_ros2_survive_a_sigkill_and_a_sigterm_mid_epoch() {
    const STEPS: u64 = 9; // 3 epochs of 3 batches of 1 per rank
    let run = Run::new("killtrainer");
    let pipe = run.pipeline("pipeline", &[ROS2], &SHARDS_OF_1_FOR_3_EPOCHS);
    let rank0 = run.trainer("rank0", STEPS, &["--rank", "0", "--world-size", "2"]);
    let rank1_args = [
        "--rank",
        "1",
        "--world-size",
        "2",
        "--checkpoint-every",
        "4",
    ];
    let rank1 = run.trainer("rank1", STEPS, &rank1_args);
    // Step 5 is batch 1 of epoch 1; the last checkpoint is step 4's.
    run.wait_for_step("rank1", 5);
    send_signal(&rank1, "-KILL");
    drop(rank1);
    let killed_log = run.read_log("rank1");
    assert!(killed_log.contains("checkpoint saved"), "{killed_log}");
    let rank1 = run.trainer("rank1", STEPS, &[&rank1_args[..], &["--resume"]].concat());
    // Rank 0 is stopped with SIGTERM (a preemption, a Slurm time limit): it finishes
    // the step in progress, checkpoints it, exits 143 and resumes where it stopped.
    run.wait_for_step("rank0", 2);
    send_signal(&rank0, "-TERM");
    let (ok, _, _) = finish(rank0, LIMIT);
    let stopped_log = run.read_log("rank0");
    assert!(
        !ok && stopped_log.contains("stopped by a signal; checkpoint saved"),
        "{stopped_log}"
    );
    let stopped_at = run.steps_done("rank0");
    assert!(stopped_at < STEPS, "{stopped_log}");
    let rank0 = run.trainer(
        "rank0",
        STEPS,
        &["--rank", "0", "--world-size", "2", "--resume"],
    );
    run.succeeds(rank1, "rank1");
    run.succeeds(rank0, "rank0");
    let resumed0 = run.read_log("rank0");
    assert!(
        resumed0.contains("resuming") && !resumed0.contains("will be redone"),
        "{resumed0}"
    );
    // With --epochs 3 the pipeline ends once both trainers have left.
    run.succeeds(pipe, "pipeline");
    let resumed_log = run.read_log("rank1");
    assert!(resumed_log.contains("resuming"), "{resumed_log}");

    let r0 = run.lineage("rank0", STEPS);
    let r1 = run.lineage("rank1", STEPS);
    // Each rank's batches come in order: epochs 0, 1, 2, batches 0..3.
    for records in [&r0, &r1] {
        let positions: Vec<(u64, u64)> = records.iter().map(|r| (r.epoch, r.batch)).collect();
        let expected: Vec<(u64, u64)> = (0..3).flat_map(|e| (0..3).map(move |b| (e, b))).collect();
        assert_eq!(positions, expected);
    }
    // Together the ranks saw every keyframe exactly once per epoch, the killed one's
    // redone steps included once.
    each_sample_once(r0.iter().chain(&r1), 3, KEYFRAMES);
    let pipeline_log = run.read_log("pipeline");
    assert!(pipeline_log.contains("resume"), "{pipeline_log}");
    run.cleanup();
}

#[test]
fn sharded_trainers_on_foxglove_wait_for_a_restarted_pipeline() {
    const STEPS: u64 = 9;
    let run = Run::new("killpipeline");
    let args = SHARDS_OF_1_FOR_3_EPOCHS;
    let pipe = run.pipeline("pipeline", &[FOXGLOVE], &args);
    let rank0 = run.trainer("rank0", STEPS, &["--rank", "0", "--world-size", "2"]);
    let rank1 = run.trainer("rank1", STEPS, &["--rank", "1", "--world-size", "2"]);
    run.wait_for_step("rank0", 4);
    send_signal(&pipe, "-KILL");
    drop(pipe);
    // The trainers use up the batches they hold, notice that no pipeline publishes,
    // and wait: no step is taken until a pipeline publishes again.
    for name in ["rank0", "rank1"] {
        run.wait_for_log(name, "no pipeline is publishing");
    }
    let stalled = (run.steps_done("rank0"), run.steps_done("rank1"));
    std::thread::sleep(Duration::from_secs(4));
    assert_eq!(
        stalled,
        (run.steps_done("rank0"), run.steps_done("rank1")),
        "steps taken without a pipeline"
    );
    assert!(stalled.0 < STEPS && stalled.1 < STEPS);
    let pipe = run.pipeline("pipeline2", &[FOXGLOVE], &args);
    run.succeeds(rank0, "rank0");
    run.succeeds(rank1, "rank1");
    run.succeeds(pipe, "pipeline2");
    for name in ["rank0", "rank1"] {
        let log = run.read_log(name);
        assert!(log.contains("restarted=true"), "{name}:\n{log}");
    }
    let r0 = run.lineage("rank0", STEPS);
    let r1 = run.lineage("rank1", STEPS);
    each_sample_once(r0.iter().chain(&r1), 3, KEYFRAMES);
    run.cleanup();
}

#[test]
fn a_stalled_trainer_slows_the_other_only_by_its_buffer() {
    const STEPS: u64 = 12; // broadcast: 2 epochs of 6 batches of 1, for each trainer
    let run = Run::new("stall");
    let pipe = run.pipeline(
        "pipeline",
        &[ROS2],
        &["--batch-size", "1", "--epochs", "2", "--subscribers", "2"],
    );
    let fast = run.trainer("fast", STEPS, &[]);
    let slow = run.trainer("slow", STEPS, &[]);
    run.wait_for_step("slow", 2);
    send_signal(&slow, "-STOP");
    let stopped_at = run.steps_done("slow");
    // The other trainer goes on until the stalled one's queue is full, then waits.
    let mut last = (run.steps_done("fast"), Instant::now());
    while last.1.elapsed() < Duration::from_secs(8) {
        std::thread::sleep(Duration::from_millis(200));
        let now = run.steps_done("fast");
        if now != last.0 {
            last = (now, Instant::now());
        }
        assert!(
            now < STEPS,
            "the fast trainer finished while the other was stopped"
        );
    }
    let lead = last.0 - stopped_at;
    // Its lead is at most what the stalled trainer holds: its queue (2), the batch in its
    // hands, and the one the publisher is retrying.
    eprintln!("stalled at step {stopped_at}: the other trainer led by {lead} batches and waited");
    assert!(lead <= 4, "lead {lead}");
    send_signal(&slow, "-CONT");
    run.succeeds(slow, "slow");
    run.succeeds(fast, "fast");
    run.succeeds(pipe, "pipeline");
    // Nothing was dropped: both trained on every batch of both epochs, in order.
    for name in ["fast", "slow"] {
        let records = run.lineage(name, STEPS);
        let positions: Vec<(u64, u64)> = records.iter().map(|r| (r.epoch, r.batch)).collect();
        let expected: Vec<(u64, u64)> = (0..2).flat_map(|e| (0..6).map(move |b| (e, b))).collect();
        assert_eq!(positions, expected, "{name}");
        each_sample_once(&records, 2, KEYFRAMES);
    }
    run.cleanup();
}

#[test]
fn two_hosts_share_each_epoch_of_both_dialects_exactly_once() {
    const STEPS: u64 = 6; // 12 keyframes / 2 hosts = 6 per epoch, batches of 2, 2 epochs
    let hosts: Vec<Run> = (0..2).map(|h| Run::new(&format!("host{h}"))).collect();
    let mut procs = Vec::new();
    for (h, run) in hosts.iter().enumerate() {
        let rank = h.to_string();
        let pipe = run.pipeline(
            "pipeline",
            &["recordings/drives"],
            &[
                "--host-rank",
                &rank,
                "--host-count",
                "2",
                "--batch-size",
                "2",
                "--epochs",
                "2",
            ],
        );
        let trainer = run.trainer("trainer", STEPS, &[]);
        procs.push((pipe, trainer));
    }
    for (run, (pipe, trainer)) in hosts.iter().zip(procs) {
        run.succeeds(trainer, "trainer");
        run.succeeds(pipe, "pipeline");
        assert!(
            run.read_log("pipeline").contains("hosts=2"),
            "{}",
            run.read_log("pipeline")
        );
    }
    let shares: Vec<Vec<StepRecord>> = hosts
        .iter()
        .map(|run| run.lineage("trainer", STEPS))
        .collect();
    for share in &shares {
        // Each host gets half of each epoch.
        for (epoch, ids) in ids_by_epoch(share) {
            assert_eq!(ids.len(), 6, "epoch {epoch}: {ids:?}");
        }
    }
    each_sample_once(shares.iter().flatten(), 2, 2 * KEYFRAMES);
    hosts.into_iter().for_each(Run::cleanup);
}
