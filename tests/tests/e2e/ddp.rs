//! Synchronous data parallelism over MPI (`superflow-trainer --ddp`), under Open MPI's
//! `mpirun` on this host:
//!
//! * the gradient exchange itself: a toy model (a small MLP, mean-squared error, no batch
//!   statistics) trained on 2 ranks equals one process trained on the union of their
//!   batches — short and empty per-rank batches included;
//! * a hung rank: the collective watchdog aborts the job within its timeout;
//! * the real pipeline in shard mode feeding 2 trainer ranks: equal `params_hash` on both
//!   ranks at every step, different from a run without `--ddp`, both ranks ending
//!   together at the end of the stream (asked for more steps than it holds); a rank SIGKILLed
//!   mid-epoch ends the job, and the job restarted with `--resume` continues both ranks
//!   from the checkpoint with every keyframe trained exactly once per epoch; the finished
//!   job requeued with `--resume` is told the run is complete and succeeds on every rank;
//!   batches lost in the pipeline keep the ranks in step (a rank with a lost batch adds
//!   no gradient, a position lost on every rank is no step).
//!
//! The toy and hang tests run this test binary itself under `mpirun` (an ignored worker
//! test, selected by `SUPERFLOW_DDP_WORKER`).

#![allow(clippy::unwrap_used, clippy::expect_used)] // tests fail loudly on purpose

use crate::SUBSCRIBER;
use burn::module::{Module, ModuleVisitor, Param};
use burn::nn::loss::{MseLoss, Reduction};
use burn::nn::{Linear, LinearConfig};
use burn::optim::{AdamWConfig, GradientsParams};
use burn::tensor::{Device, Tensor, TensorData};
use std::collections::BTreeMap;
use std::path::{Path, PathBuf};
use std::process::{Command, Stdio};
use std::time::{Duration, Instant};
use superflow_tests::process::{
    Proc, drain, finish, lines_of, mpirun, no_shared_memory_left, pipeline, prefix, serve, spawn,
    stop, trainer_command, wait_until_ready,
};
use superflow_tests::scratch;
use superflow_trainer::ddp::Ddp;
use superflow_trainer::metrics::{self, StepRecord};
use superflow_trainer::sync::{GradientBuffer, params_hash};

const LIMIT: Duration = Duration::from_secs(600);
const WORKER: &str = "SUPERFLOW_DDP_WORKER";
const OUT: &str = "SUPERFLOW_DDP_OUT";

/// This test binary under `mpirun -np 2`, running the ignored test `worker` in mode `mode`.
fn run_workers(mode: &str, out: &Path, limit: Duration) -> (bool, String, String, Duration) {
    let exe = std::env::current_exe().unwrap();
    let started = Instant::now();
    let proc = spawn(
        mpirun(2)
            .arg(exe)
            .args([
                "--exact",
                "ddp::worker",
                "--ignored",
                "--nocapture",
                "--test-threads",
                "1",
            ])
            .env(WORKER, mode)
            .env(OUT, out)
            .stdout(Stdio::piped())
            .stderr(Stdio::piped()),
    );
    let (ok, stdout, stderr) = finish(proc, limit);
    (ok, stdout, stderr, started.elapsed())
}

/// The toy model: 4 → 8 → 1 with tanh, no batch statistics.
#[derive(Module, Debug)]
struct Toy {
    a: Linear,
    b: Linear,
}

impl Toy {
    fn forward(&self, x: Tensor<2>) -> Tensor<2> {
        self.b.forward(self.a.forward(x).tanh())
    }
}

/// Sample `i` of the toy data set: 4 inputs and a target.
fn sample(i: usize) -> ([f32; 4], f32) {
    let t = i as f32;
    let x = [
        (0.7 * t).sin(),
        (1.3 * t).cos(),
        (0.11 * t) - 1.0,
        ((t * 0.37).sin() * 2.0),
    ];
    (x, x[0] * 0.5 - x[1] * x[2] + 0.25 * x[3])
}

/// Global batches of the toy run, and how many of each go to rank 0 (the rest to rank
/// 1): equal halves, uneven splits, and rank 1 without a sample.
const GLOBAL: [(usize, usize); 6] = [(4, 2), (4, 2), (3, 2), (4, 3), (1, 1), (4, 2)];

/// The samples of `indices` as tensors.
fn batch(indices: &[usize], device: &Device) -> (Tensor<2>, Tensor<2>) {
    let (xs, ys): (Vec<[f32; 4]>, Vec<f32>) = indices.iter().map(|&i| sample(i)).unzip();
    let n = indices.len();
    let x = Tensor::from_data(TensorData::new(xs.concat(), [n, 4]), device);
    let y = Tensor::from_data(TensorData::new(ys, [n, 1]), device);
    (x, y)
}

/// The gradients of the mean-squared error of `model` on `indices` (none when empty).
fn gradients(model: &Toy, indices: &[usize], device: &Device) -> GradientsParams {
    if indices.is_empty() {
        return GradientsParams::new();
    }
    let (x, y) = batch(indices, device);
    let loss = MseLoss::new().forward(model.forward(x), y, Reduction::Mean);
    GradientsParams::from_grads(loss.backward(), model)
}

/// Every float parameter's values, in visitor order.
fn parameters(model: &Toy) -> Vec<f32> {
    struct Collect(Vec<f32>);
    impl ModuleVisitor for Collect {
        fn visit_float<const D: usize>(&mut self, param: &Param<Tensor<D>>) {
            self.0
                .extend(param.val().into_data().try_to_vec::<f32>().unwrap());
        }
    }
    let mut c = Collect(Vec::new());
    model.visit(&mut c);
    c.0
}

/// One rank of the toy job: starts from rank 0's parameters (broadcast as the trainer
/// does), trains GLOBAL's batches split between the ranks with the gradient all-reduce,
/// records its parameter hash per step; rank 0 then trains a copy of the initial model
/// on the union of each step's batches in this process and writes the largest parameter
/// difference.
fn toy_worker(out: &Path) {
    let ddp = Ddp::init(Duration::from_secs(60)).unwrap();
    assert_eq!(ddp.size(), 2);
    let rank = ddp.rank();
    let device = Device::flex().autodiff();
    let grads_device = device.clone().inner();
    let fresh = Toy {
        a: LinearConfig::new(4, 8).init(&device),
        b: LinearConfig::new(8, 1).init(&device),
    };
    let bytes = fresh.clone().into_record().into_bytes().unwrap().to_vec();
    let bytes = ddp.broadcast_bytes(bytes, "toy parameters");
    let record =
        burn::store::ModuleRecord::from_bytes(burn::tensor::Bytes::from_bytes_vec(bytes)).unwrap();
    let initial = fresh.load_record(record);
    let optimizer = || AdamWConfig::new().with_weight_decay(1e-2).init();
    let lr = 2e-2;

    let mut model = initial.clone();
    let mut optim = optimizer();
    let mut hashes = Vec::new();
    let mut next = 0;
    let mut steps = Vec::new();
    for (size, first) in GLOBAL {
        let all: Vec<usize> = (next..next + size).collect();
        next += size;
        let mine = if rank == 0 {
            &all[..first]
        } else {
            &all[first..]
        };
        let mut grads = gradients(&model, mine, &device);
        let mut buffer = GradientBuffer::from_gradients(&model, &mut grads, mine.len(), &[]);
        ddp.all_reduce_sum(&mut buffer.values, "toy gradients");
        assert_eq!(buffer.samples() as usize, size, "samples of all ranks");
        let grads = buffer.into_gradients(&model, &grads_device);
        model = optim.step(lr, model, grads);
        hashes.push(params_hash(&model));
        steps.push(all);
    }
    let text: Vec<String> = hashes.iter().map(u64::to_string).collect();
    std::fs::write(out.join(format!("hashes-{rank}")), text.join("\n")).unwrap();
    if rank == 0 {
        let initial_copy = initial.clone();
        let mut reference = initial;
        let mut optim = optimizer();
        for all in &steps {
            let grads = gradients(&reference, all, &device);
            reference = optim.step(lr, reference, grads);
        }
        let (a, b) = (parameters(&model), parameters(&reference));
        assert_eq!(a.len(), b.len());
        let worst = a
            .iter()
            .zip(&b)
            .map(|(x, y)| (x - y).abs())
            .fold(0.0f32, f32::max);
        // Training moved the parameters: the comparison is not of two untouched models.
        let moved = parameters(&initial_copy)
            .iter()
            .zip(&b)
            .map(|(x, y)| (x - y).abs())
            .fold(0.0f32, f32::max);
        assert!(moved > 1e-2, "the parameters barely moved: {moved}");
        std::fs::write(out.join("worst"), worst.to_string()).unwrap();
    }
    ddp.barrier("end of the toy run");
}

/// One rank of the hang job: rank 1 never joins the all-reduce.
fn hang_worker() {
    let ddp = Ddp::init(Duration::from_secs(3)).unwrap();
    if ddp.rank() == 1 {
        std::thread::sleep(Duration::from_secs(120));
    }
    let mut values = vec![1.0f32; 16];
    ddp.all_reduce_sum(&mut values, "gradient all-reduce of step 1");
}

/// The worker side of the tests above (ignored: run only under `mpirun` by them).
#[test]
#[ignore = "run by the other tests under mpirun"]
fn worker() {
    let Ok(mode) = std::env::var(WORKER) else {
        return;
    };
    let out = PathBuf::from(std::env::var(OUT).unwrap());
    match mode.as_str() {
        "toy" => toy_worker(&out),
        "hang" => hang_worker(),
        other => panic!("unknown worker mode {other}"),
    }
}

#[test]
fn two_ranks_train_the_toy_model_as_one_process_on_the_union_of_their_batches() {
    let out = scratch::dir("ddp", "toy");
    let (ok, stdout, stderr, _) = run_workers("toy", &out, Duration::from_secs(120));
    assert!(ok, "mpirun failed:\n{stdout}\n{stderr}");
    let hashes: Vec<String> = (0..2)
        .map(|r| std::fs::read_to_string(out.join(format!("hashes-{r}"))).unwrap())
        .collect();
    assert_eq!(hashes[0], hashes[1], "the ranks hold different models");
    assert_eq!(
        hashes[0]
            .lines()
            .collect::<std::collections::BTreeSet<_>>()
            .len(),
        GLOBAL.len()
    );
    let worst: f32 = std::fs::read_to_string(out.join("worst"))
        .unwrap()
        .parse()
        .unwrap();
    eprintln!("2 ranks vs one process on the union: largest parameter difference {worst:.2e}");
    assert!(
        worst <= 1e-6,
        "2 ranks differ from one process by {worst:e}"
    );
    let _ = std::fs::remove_dir_all(&out);
}

#[test]
fn a_hung_rank_aborts_the_job_within_the_collective_timeout() {
    let out = scratch::dir("ddp", "hang");
    let (ok, stdout, stderr, took) = run_workers("hang", &out, Duration::from_secs(90));
    assert!(
        !ok,
        "the job succeeded with a hung rank:\n{stdout}\n{stderr}"
    );
    assert!(
        took < Duration::from_secs(60),
        "the job took {took:?} to end (timeout 3 s)"
    );
    assert!(
        stderr.contains("gradient all-reduce of step 1: no answer from the other ranks"),
        "{stderr}"
    );
    let _ = std::fs::remove_dir_all(&out);
}

/// The drive's keyframes: 3 per rank and epoch in batches of 1.
const KEYFRAMES: u64 = 6;

/// The pipeline in shard mode for 2 ranks, batches of 1, `epochs` epochs.
fn shard_pipeline(prefix: &str, run: &str, epochs: u64) -> Proc {
    let epochs = epochs.to_string();
    let args = [
        "--mode",
        "shard",
        "--world-size",
        "2",
        "--batch-size",
        "1",
        "--epochs",
        &epochs,
    ];
    serve(SUBSCRIBER, prefix, run, &args)
}

/// The trainer as the data-parallel tests start it ([`trainer_command`]: the tiny presets
/// for `steps` steps), under `launcher` (`mpirun -np 2` for `--ddp`, or none), with the
/// collective watchdog at 300 s, writing into `out`, its stdout piped too.
fn ddp_trainer(
    launcher: Option<Command>,
    prefix: &str,
    run: &str,
    steps: u64,
    out: &Path,
    extra: &[&str],
) -> Proc {
    spawn(
        trainer_command(SUBSCRIBER, launcher, prefix, run, steps)
            .args(["--collective-timeout-secs", "300", "--out"])
            .arg(out)
            .args(extra)
            .stdout(Stdio::piped()),
    )
}

/// Rank `rank`'s metrics of a `--ddp` run in `out`, the last record of every step.
fn rank_records(out: &Path, rank: usize) -> BTreeMap<u64, StepRecord> {
    let path = out.join(format!("rank-{rank}/metrics.jsonl"));
    metrics::read(&path)
        .unwrap_or_else(|e| panic!("{e}"))
        .into_iter()
        .map(|r| (r.step, r))
        .collect()
}

/// Both ranks recorded steps 1..=steps with the same parameter hash at every step, and
/// their samples cover every keyframe once per epoch.
fn assert_replicas_agree(out: &Path, steps: u64) -> [BTreeMap<u64, StepRecord>; 2] {
    let ranks = [rank_records(out, 0), rank_records(out, 1)];
    for (rank, records) in ranks.iter().enumerate() {
        assert_eq!(
            records.keys().copied().collect::<Vec<_>>(),
            (1..=steps).collect::<Vec<_>>(),
            "rank {rank}'s steps"
        );
    }
    for step in 1..=steps {
        let (a, b) = (&ranks[0][&step], &ranks[1][&step]);
        assert_ne!(a.params_hash, 0, "step {step}: no hash recorded");
        assert_eq!(
            a.params_hash, b.params_hash,
            "step {step}: the ranks' models differ"
        );
        assert_eq!(
            (a.epoch, a.batch),
            (b.epoch, b.batch),
            "step {step}: stream positions"
        );
        let (da, db) = (a.ddp.as_ref().unwrap(), b.ddp.as_ref().unwrap());
        assert_eq!((da.rank, db.rank, da.world_size), (0, 1, 2));
        assert_eq!(da.samples, 2, "step {step}: samples of both ranks");
        assert!(
            (da.loss - db.loss).abs() <= 1e-12 * da.loss.abs(),
            "step {step}: global loss"
        );
        assert!(da.reduce_bytes > 0);
    }
    let keys: Vec<Vec<(u64, u64)>> = ranks
        .iter()
        .map(|records| {
            records
                .values()
                .flat_map(|r| r.sample_ids.iter().map(|&[e, k]| (e, k)))
                .collect()
        })
        .collect();
    superflow_tests::process::assert_shards_cover(&keys, steps / 3, KEYFRAMES);
    ranks
}

#[test]
fn two_ranks_hold_the_same_model_at_every_step_and_differ_from_one_rank_alone() {
    // Asked for more steps than the 2 epochs hold: every trainer ends with the stream.
    const ASKED: u64 = 20;
    const STEPS: u64 = 6;
    let p = prefix("tworanks");
    let out = scratch::dir("ddp", "two-ranks");
    let pipe = shard_pipeline(&p, "ddp", 2);
    let (ok, stdout, stderr) = finish(
        ddp_trainer(
            Some(mpirun(2)),
            &p,
            "ddp",
            ASKED,
            &out,
            &["--ddp", "--plot"],
        ),
        LIMIT,
    );
    assert!(ok, "{stdout}\n{stderr}");
    let _ = stop(pipe, LIMIT);
    no_shared_memory_left(&p);
    let [ddp, _] = assert_replicas_agree(&out, STEPS);
    assert!(
        out.join("checkpoints/latest").exists(),
        "rank 0 writes the checkpoints"
    );
    assert!(out.join("rank-0/losses.svg").exists() && out.join("rank-1/losses.svg").exists());
    assert!(
        stderr.contains("every rank starts from rank 0's parameters"),
        "{stderr}"
    );
    assert_eq!(
        stderr.matches("trained 6 of the 20 steps asked").count(),
        2,
        "both ranks end with the stream, together: {stderr}"
    );

    // The finished job requeued: every rank is told the run is complete, and the job
    // succeeds without a step.
    let p = prefix("tworanks-done");
    let pipe = shard_pipeline(&p, "ddp", 2);
    let (ok, stdout, stderr) = finish(
        ddp_trainer(
            Some(mpirun(2)),
            &p,
            "ddp",
            ASKED,
            &out,
            &["--ddp", "--resume"],
        ),
        LIMIT,
    );
    assert!(ok, "{stdout}\n{stderr}");
    assert_eq!(
        stderr
            .matches("the run is complete (2 epochs): nothing left to train")
            .count(),
        2,
        "{stderr}"
    );
    let _ = stop(pipe, LIMIT);
    no_shared_memory_left(&p);

    // The same 2 shards trained by 2 independent trainers (no --ddp): what a skipped
    // all-reduce would give.
    let p = prefix("onerank");
    let alone_dir = scratch::dir("ddp", "one-rank");
    let pipe = shard_pipeline(&p, "alone", 2);
    let independent: Vec<Proc> = (0..2)
        .map(|rank| {
            let out = alone_dir.join(format!("rank{rank}"));
            let rank = rank.to_string();
            ddp_trainer(
                None,
                &p,
                "alone",
                ASKED,
                &out,
                &["--rank", &rank, "--world-size", "2"],
            )
        })
        .collect();
    for proc in independent {
        let (ok, stdout, stderr) = finish(proc, LIMIT);
        assert!(ok, "{stdout}\n{stderr}");
        assert!(
            stderr.contains("trained 6 of the 20 steps asked"),
            "{stderr}"
        );
    }
    let _ = stop(pipe, LIMIT);
    no_shared_memory_left(&p);
    let alone: BTreeMap<u64, StepRecord> = metrics::read(&alone_dir.join("rank0/metrics.jsonl"))
        .unwrap()
        .into_iter()
        .map(|r| (r.step, r))
        .collect();
    for step in 1..=STEPS {
        assert_eq!(
            alone[&step].sample_ids, ddp[&step].sample_ids,
            "step {step}: same shard"
        );
        assert_ne!(
            alone[&step].params_hash, ddp[&step].params_hash,
            "step {step}: rank 0 of the job equals rank 0 alone (no all-reduce?)"
        );
        assert!(alone[&step].ddp.is_none());
    }
    let _ = std::fs::remove_dir_all(&out);
    let _ = std::fs::remove_dir_all(&alone_dir);
}

/// The pid of rank `rank` among `mpirun`'s children.
fn rank_pid(mpirun: &Proc, rank: usize) -> Option<u32> {
    let children = std::fs::read_to_string(format!(
        "/proc/{}/task/{}/children",
        mpirun.id(),
        mpirun.id()
    ))
    .ok()?;
    children.split_whitespace().find_map(|pid| {
        let environ = std::fs::read(format!("/proc/{pid}/environ")).ok()?;
        let wanted = format!("OMPI_COMM_WORLD_RANK={rank}");
        environ
            .split(|b| *b == 0)
            .any(|v| v == wanted.as_bytes())
            .then(|| pid.parse().ok())
            .flatten()
    })
}

#[test]
fn a_killed_rank_ends_the_job_and_the_restarted_job_resumes_every_rank() {
    const STEPS: u64 = 9; // 3 epochs
    let p = prefix("killrank");
    let out = scratch::dir("ddp", "kill");
    let pipe = shard_pipeline(&p, "kill", 3);
    let extra = ["--ddp", "--checkpoint-every", "2"];
    let mut job = ddp_trainer(Some(mpirun(2)), &p, "kill", STEPS, &out, &extra);
    let rx = lines_of(job.stderr.take().unwrap());
    // Kill rank 1 in the middle of epoch 1: after step 5, checkpoint at step 4.
    let started = Instant::now();
    let rank1 = out.join("rank-1/metrics.jsonl");
    while std::fs::read_to_string(&rank1).map_or(0, |t| t.lines().count()) < 5 {
        assert!(started.elapsed() < LIMIT, "the job did not reach step 5");
        assert!(job.try_wait().unwrap().is_none(), "the job ended early");
        std::thread::sleep(Duration::from_millis(50));
    }
    let pid = rank_pid(&job, 1).expect("rank 1 among mpirun's children");
    assert!(
        Command::new("kill")
            .args(["-KILL", &pid.to_string()])
            .status()
            .unwrap()
            .success()
    );
    let killed = Instant::now();
    let (ok, _, _) = finish(job, Duration::from_secs(120));
    let mut log = String::new();
    log.push_str(&drain(&rx, Duration::from_secs(1)));
    assert!(!ok, "the job succeeded with a killed rank:\n{log}");
    eprintln!(
        "the job ended {:.1} s after rank 1 was killed",
        killed.elapsed().as_secs_f64()
    );

    let (ok, stdout, stderr) = finish(
        ddp_trainer(
            Some(mpirun(2)),
            &p,
            "kill",
            STEPS,
            &out,
            &[&extra[..], &["--resume"]].concat(),
        ),
        LIMIT,
    );
    assert!(ok, "{stdout}\n{stderr}");
    assert!(
        stderr.contains("the job continues from this checkpoint"),
        "{stderr}"
    );
    let _ = stop(pipe, LIMIT);
    no_shared_memory_left(&p);
    // The lineage: steps 1..=4 of the first job, 5..=9 of the resumed one; every
    // keyframe once per epoch, the ranks equal at every step.
    let ranks = assert_replicas_agree(&out, STEPS);
    assert_eq!(ranks[0][&5].epoch, 1, "step 5 is mid-epoch 1");
    let _ = std::fs::remove_dir_all(&out);
}

/// A preempted job back on another number of GPUs: 2 `--ddp` ranks stopped by SIGTERM
/// mid-epoch (their checkpoint counts the samples the job consumed), then the pipeline
/// restarted with 3 shards and the job resumed with `mpirun -np 3 --resume`: each rank
/// asks to continue after those samples, the pipeline deals the rest of the epoch to the
/// 3 ranks, and over both jobs every keyframe is trained on exactly once per epoch.
#[test]
fn a_job_of_two_ranks_resumed_on_three_trains_every_keyframe_once() {
    const STEPS: u64 = 20; // more than the stream holds: both jobs end with it
    let p = prefix("elastic");
    let out = scratch::dir("ddp", "elastic");
    let extra = ["--ddp", "--checkpoint-every", "1"];
    let pipe = shard_pipeline(&p, "elastic", 2);
    let mut job = ddp_trainer(Some(mpirun(2)), &p, "elastic", STEPS, &out, &extra);
    let rank0 = out.join("rank-0/metrics.jsonl");
    let started = Instant::now();
    while std::fs::read_to_string(&rank0).map_or(0, |t| t.lines().count()) < 2 {
        assert!(started.elapsed() < LIMIT, "the job did not reach step 2");
        assert!(job.try_wait().unwrap().is_none(), "the job ended early");
        std::thread::sleep(Duration::from_millis(50));
    }
    let (ok, _, stderr) = stop(job, LIMIT);
    assert!(!ok, "a stopped job exits with 128 + SIGTERM:\n{stderr}");
    let _ = stop(pipe, LIMIT);
    let first = [rank_records(&out, 0), rank_records(&out, 1)];
    let stopped_at = first[0].keys().max().copied().unwrap_or(0);
    assert!(stopped_at >= 2, "{first:?}");

    let args = [
        "--mode",
        "shard",
        "--world-size",
        "3",
        "--batch-size",
        "1",
        "--epochs",
        "2",
    ];
    let pipe = serve(SUBSCRIBER, &p, "elastic", &args);
    let resumed = [&extra[..], &["--resume"]].concat();
    let (ok, stdout, stderr) = finish(
        ddp_trainer(Some(mpirun(3)), &p, "elastic", STEPS, &out, &resumed),
        LIMIT,
    );
    assert!(ok, "{stdout}\n{stderr}");
    assert!(stderr.contains("ranks_before=2"), "{stderr}");
    let (ok, _, err) = finish(pipe, LIMIT);
    assert!(ok, "{err}");
    no_shared_memory_left(&p);
    // Both jobs' steps: ranks 0 and 1 kept the first job's records up to its checkpoint
    // (a resumed run drops the metrics of the steps it redoes); rank 2 is the second's.
    let mut seen = BTreeMap::<(u64, u64), usize>::new();
    for rank in 0..3 {
        for record in rank_records(&out, rank).values() {
            for &[epoch, position] in &record.sample_ids {
                *seen.entry((epoch, position)).or_default() += 1;
            }
        }
    }
    let expected: Vec<(u64, u64)> = (0..2)
        .flat_map(|e| (0..KEYFRAMES).map(move |k| (e, k)))
        .collect();
    assert_eq!(
        seen.keys().copied().collect::<Vec<_>>(),
        expected,
        "{seen:?}"
    );
    assert!(
        seen.values().all(|n| *n == 1),
        "a sample trained twice: {seen:?}"
    );
    let _ = std::fs::remove_dir_all(&out);
}

/// 2 `--ddp` ranks on a pipeline whose drives are replaced by truncated copies after its
/// first batch was built (it reopens its files for every read): most batches built from
/// then on are lost, on both shards. At a position where one rank's batch is lost it
/// takes part in the all-reduce with no gradient; where every rank's is, no rank steps.
/// The replicas stay equal, the samples trained are exactly those of the batches not
/// lost, and both ranks end with the stream, together.
#[test]
fn lost_batches_keep_the_ranks_in_step_and_the_stream_ends() {
    const ASKED: u64 = 20;
    // 12 keyframes of both sample drives, 6 per rank, one epoch.
    const POSITIONS: usize = 6;
    let p = prefix("ddplost");
    let out = scratch::dir("ddp", "lost");
    let dir = scratch::dir("ddp", "lost-drives");
    let (drives, config) = superflow_tests::replaceable_drives(&dir).unwrap();
    let (first, second, config) = (
        drives[0].to_str().unwrap(),
        drives[1].to_str().unwrap(),
        config.to_str().unwrap(),
    );
    let args = [
        "--mcap",
        second,
        "--config",
        config,
        "--mode",
        "shard",
        "--world-size",
        "2",
        "--batch-size",
        "1",
        "--epochs",
        "1",
    ];
    let mut pipe = pipeline(SUBSCRIBER, first, &p, "ddplost", &args);
    let (rx, mut pipe_log) = wait_until_ready(&mut pipe, LIMIT);
    superflow_tests::truncate_drives(&drives).unwrap();
    let (ok, stdout, stderr) = finish(
        ddp_trainer(Some(mpirun(2)), &p, "ddplost", ASKED, &out, &["--ddp"]),
        LIMIT,
    );
    assert!(ok, "{stdout}\n{stderr}");
    let (ok, _, _) = finish(pipe, LIMIT);
    pipe_log.push_str(&drain(&rx, Duration::from_secs(2)));
    assert!(ok, "the pipeline ends once the job left: {pipe_log}");
    no_shared_memory_left(&p);

    let lost = stderr
        .matches("batch lost: every sample failed in the pipeline")
        .count();
    assert_eq!(
        pipe_log.matches("batch lost: all").count(),
        lost,
        "every lost batch reached its rank:\n{pipe_log}\n{stderr}"
    );
    assert!(lost > 0, "{stderr}");
    let ranks = [rank_records(&out, 0), rank_records(&out, 1)];
    let steps = ranks[0].len();
    assert_eq!(ranks[1].len(), steps, "both ranks took every step");
    assert!((1..=POSITIONS).contains(&steps), "{steps} steps: {stderr}");
    let mut samples = 0;
    for (step, a) in &ranks[0] {
        let b = &ranks[1][step];
        assert_eq!(
            a.params_hash, b.params_hash,
            "step {step}: the replicas differ"
        );
        assert_eq!((a.epoch, a.batch), (b.epoch, b.batch), "step {step}");
        let global = a.ddp.as_ref().unwrap().samples;
        assert!(global >= 1, "step {step}: a step without a sample");
        assert_eq!(global, a.samples + b.samples, "step {step}");
        assert!(a.loss.is_finite() && b.loss.is_finite());
        samples += global;
    }
    // Each of the 12 batches is either trained (1 sample) or lost.
    assert_eq!(samples + lost, 2 * POSITIONS, "{stderr}");
    // Which samples still build depends on what the pipeline's chunk caches hold: say
    // which paths this run took (in practice both: positions with one rank's batch lost,
    // and positions lost on both ranks, which are no step).
    let alone = ranks[0]
        .values()
        .filter(|r| r.ddp.as_ref().unwrap().samples == 1);
    eprintln!(
        "{steps} steps ({} with one rank's batch lost), {lost} batches lost",
        alone.count()
    );
    let asked = format!("trained {steps} of the {ASKED} steps asked");
    assert_eq!(stderr.matches(&asked).count(), 2, "{stderr}");
    let _ = std::fs::remove_dir_all(&out);
    let _ = std::fs::remove_dir_all(&dir);
}
