//! The real `superflow-pipeline` feeding the real `superflow-trainer` (tiny presets) on
//! the sample drive: the loss goes down, checkpoints are written, and a trainer killed
//! after a checkpoint and restarted with `--resume` continues with the same batches and
//! the same losses as an uninterrupted run; a trainer asked for more steps than the
//! stream has ends at the end of the stream, and `--resume` of that finished run ends at
//! once, successfully; batches lost in the pipeline (every sample failed) are counted
//! without a step and the stream still ends; `superflow-trainer probe` of the trained
//! checkpoint and of an untrained network on the drives' labels (linear and fine-tuned)
//! prints its JSON report. `superflow-trainer check` (the backend
//! comparison `deploy/gpu/check.sh` runs on a GPU) on a batch file from
//! `superflow-pipeline batch`, and the same on burn's `wgpu` backend against the CPU on a
//! Vulkan device (Mesa's software llvmpipe in CI).

#![allow(clippy::unwrap_used, clippy::expect_used)] // tests fail loudly on purpose

use crate::SUBSCRIBER;
use std::collections::BTreeMap;
use std::ffi::OsStr;
use std::path::{Path, PathBuf};
use std::process::{Command, Stdio};
use std::time::{Duration, Instant};
use superflow_tests::process::{
    Proc, drain, finish, lines_of, no_shared_memory_left, pipeline_command, pipeline_server,
    prefix, send_signal, spawn, stop, stop_cleanly, trainer, wait_until_ready,
};
use superflow_tests::{SAMPLE_DRIVE, pipeline_binary, scratch, trainer_binary, workspace_root};
use superflow_trainer::metrics::{self, StepRecord};

const LIMIT: Duration = Duration::from_secs(600);
/// Steps of each run: 4 epochs of the drive's 6 keyframes in batches of 1.
const STEPS: u64 = 24;
const EPOCHS: &str = "4";

/// The sample drive served in batches of 1 for `epochs` epochs as run `run`
/// ([`pipeline_command`]), logging warnings only.
fn quiet_pipeline(prefix: &str, run: &str, epochs: &str) -> Command {
    let mut command = pipeline_command(
        SUBSCRIBER,
        SAMPLE_DRIVE,
        prefix,
        run,
        &["--batch-size", "1", "--epochs", epochs],
    );
    command.env("RUST_LOG", "warn");
    command
}

/// The last record of every step (a resumed run repeats the steps after its checkpoint).
fn by_step(records: Vec<StepRecord>) -> BTreeMap<u64, StepRecord> {
    records.into_iter().map(|r| (r.step, r)).collect()
}

/// `superflow-trainer probe --json` of `backbone` on the sample drives (tiny presets).
fn probe(backbone: &str, extra: &[&str]) -> serde_json::Value {
    let (ok, out, err) = finish(
        spawn(
            Command::new(trainer_binary(SUBSCRIBER))
                .args([
                    "probe",
                    "--mcap",
                    "recordings/drives",
                    "--checkpoint",
                    backbone,
                ])
                .args([
                    "--unet",
                    "tiny",
                    "--json",
                    "--val-fraction",
                    "0.3",
                    "--gap-secs",
                    "0.5",
                ])
                .args(extra)
                .current_dir(workspace_root())
                .stdout(Stdio::piped())
                .stderr(Stdio::piped()),
        ),
        LIMIT,
    );
    assert!(ok, "probe {backbone} {extra:?}:\n{err}");
    serde_json::from_str(out.lines().last().unwrap_or_default())
        .unwrap_or_else(|e| panic!("probe output {out:?}: {e}"))
}

fn mean(values: impl Iterator<Item = f64>) -> f64 {
    let v: Vec<f64> = values.collect();
    v.iter().sum::<f64>() / v.len() as f64
}

#[test]
fn training_lowers_the_loss_and_a_resumed_run_matches_an_uninterrupted_one() {
    // The uninterrupted run.
    let p = prefix("train");
    let full = scratch::vacant("trainer", "full");
    let pipe = spawn(quiet_pipeline(&p, "full", EPOCHS).stderr(Stdio::null()));
    let (ok, _, err) = finish(
        trainer(
            SUBSCRIBER,
            &p,
            "full",
            STEPS,
            &full,
            &["--checkpoint-every", "10", "--plot"],
        ),
        LIMIT,
    );
    assert!(ok, "{err}");
    let _ = stop(pipe, LIMIT);
    no_shared_memory_left(&p);
    let uninterrupted = by_step(metrics::read(&full.join("metrics.jsonl")).unwrap());
    assert_eq!(uninterrupted.len() as u64, STEPS);
    let first = mean(uninterrupted.values().take(6).map(|r| r.loss));
    let last = mean(
        uninterrupted
            .values()
            .skip(STEPS as usize - 6)
            .map(|r| r.loss),
    );
    eprintln!("loss: first 6 steps {first:.4}, last 6 steps {last:.4}");
    assert!(
        last < first * 0.95,
        "the loss did not decrease: {first} → {last}"
    );
    for r in uninterrupted.values() {
        assert!(
            r.l_sc > 0.0 && r.l_tc > 0.0 && r.l_d2s > 0.0,
            "a term is empty: {r:?}"
        );
    }
    // Every epoch saw every keyframe once (by sample id).
    let mut seen: BTreeMap<u64, Vec<u64>> = BTreeMap::new();
    for r in uninterrupted.values() {
        for &[epoch, index] in &r.sample_ids {
            seen.entry(epoch).or_default().push(index);
        }
    }
    for (epoch, mut ids) in seen {
        ids.sort_unstable();
        assert_eq!(ids, (0..6).collect::<Vec<_>>(), "epoch {epoch}");
    }
    assert!(full.join("checkpoints/latest").exists());
    assert!(full.join("checkpoints/step-00000020/model.bpk").exists());
    assert!(full.join("losses.svg").exists());

    // The trained backbone and an untrained one, probed on the sample drives' labels.
    let checkpoint = full.join("checkpoints");
    for (backbone, extra) in [
        (checkpoint.to_str().unwrap(), &["--epochs", "5"][..]),
        ("random", &["--epochs", "5"][..]),
        (
            checkpoint.to_str().unwrap(),
            &["--finetune", "--epochs", "1"][..],
        ),
    ] {
        let report = probe(backbone, extra);
        let miou = report["miou"].as_f64().unwrap();
        assert!((0.0..=1.0).contains(&miou), "{report}");
        let per_class = report["per_class"].as_object().unwrap();
        assert!(
            per_class.len() >= 3,
            "the drives' classes are scored: {report}"
        );
        let mean =
            per_class.values().map(|v| v.as_f64().unwrap()).sum::<f64>() / per_class.len() as f64;
        assert!(
            (mean - miou).abs() < 1e-9,
            "mIoU is the mean of the classes' IoU: {report}"
        );
        assert!(report["points"]["val"].as_u64().unwrap() > 1000, "{report}");
        assert!(report["split"]["train"].as_u64().unwrap() >= 1, "{report}");
        assert!(report["split"]["val"].as_u64().unwrap() >= 1, "{report}");
        if backbone != "random" {
            assert!(
                report["backbone"].as_str().unwrap().contains("step 24"),
                "{report}"
            );
        }
        eprintln!("probe {backbone} {extra:?}: mIoU {miou:.3}");
    }

    // The same run, killed after its checkpoint at step 10, then resumed.
    let p = prefix("resume");
    let cut = scratch::vacant("trainer", "cut");
    let pipe = spawn(quiet_pipeline(&p, "cut", EPOCHS).stderr(Stdio::null()));
    let mut first_half = trainer(
        SUBSCRIBER,
        &p,
        "cut",
        STEPS,
        &cut,
        &["--checkpoint-every", "10"],
    );
    let rx = lines_of(first_half.stderr.take().unwrap());
    let started = Instant::now();
    let mut log = String::new();
    while !log.contains("checkpoint saved") {
        let line = rx
            .recv_timeout(LIMIT)
            .unwrap_or_else(|_| panic!("no checkpoint:\n{log}"));
        log.push_str(&line);
        log.push('\n');
        assert!(started.elapsed() < LIMIT, "{log}");
    }
    send_signal(&first_half, "-KILL");
    let _ = first_half.wait();
    drop(first_half);
    let (ok, _, err) = finish(
        trainer(
            SUBSCRIBER,
            &p,
            "cut",
            STEPS,
            &cut,
            &["--checkpoint-every", "10", "--resume"],
        ),
        LIMIT,
    );
    assert!(ok, "{err}");
    assert!(err.contains("resuming"), "{err}");
    let _ = stop(pipe, LIMIT);
    no_shared_memory_left(&p);

    let resumed = by_step(metrics::read(&cut.join("metrics.jsonl")).unwrap());
    assert_eq!(
        resumed.len() as u64,
        STEPS,
        "steps 1..{STEPS} all recorded; the resumed trainer said:\n{err}"
    );
    let mut worst = 0.0_f64;
    for (step, r) in &resumed {
        let u = &uninterrupted[step];
        assert_eq!(
            (r.epoch, r.batch),
            (u.epoch, u.batch),
            "step {step}: stream position"
        );
        assert_eq!(r.sample_ids, u.sample_ids, "step {step}: samples");
        for (a, b) in [
            (r.loss, u.loss),
            (r.l_sc, u.l_sc),
            (r.l_tc, u.l_tc),
            (r.l_d2s, u.l_d2s),
        ] {
            worst = worst.max((a - b).abs() / b.abs().max(1e-12));
        }
        assert!((r.lr - u.lr).abs() <= 1e-12 * u.lr, "step {step}: lr");
    }
    eprintln!("resumed vs uninterrupted: worst relative loss difference {worst:.2e}");
    assert!(
        worst <= 1e-5,
        "resumed losses differ from the uninterrupted run by {worst:.2e}"
    );
    let _ = std::fs::remove_dir_all(&full);
    let _ = std::fs::remove_dir_all(&cut);
}

/// A pipeline serving 1 epoch (6 batches of 1) to a trainer asked for 24 steps: the
/// trainer ends after the stream's last batch, saying it trained 6 of the 24 steps
/// asked, well before its `--timeout-secs` (120 s), and the pipeline ends by itself.
#[test]
fn the_trainer_ends_at_the_end_of_the_stream_saying_how_many_steps_it_trained() {
    let p = prefix("ends");
    let out = scratch::vacant("trainer", "ends");
    let pipe = spawn(&mut quiet_pipeline(&p, "ends", "1"));
    let started = Instant::now();
    let (ok, _, err) = finish(trainer(SUBSCRIBER, &p, "ends", STEPS, &out, &[]), LIMIT);
    let took = started.elapsed();
    assert!(ok, "{err}");
    assert!(
        err.contains("trained 6 of the 24 steps asked"),
        "the end of the stream is said: {err}"
    );
    assert!(err.contains("done training"), "{err}");
    assert!(took < Duration::from_secs(100), "took {took:?}: {err}");
    let records = metrics::read(&out.join("metrics.jsonl")).unwrap();
    assert_eq!(records.len(), 6);
    assert!(out.join("checkpoints/step-00000006").exists(), "{err}");
    let (ok, _, err) = finish(pipe, LIMIT);
    assert!(ok, "the pipeline ends once the trainer left: {err}");
    no_shared_memory_left(&p);

    // The job requeued: the same pipeline again, the trainer with --resume. Its
    // checkpoint is at the end of the last epoch: the run is complete, it says so and
    // succeeds without a step, leaving the metrics as they were.
    let p = prefix("ends-again");
    let pipe = spawn(&mut quiet_pipeline(&p, "ends", "1"));
    let (ok, _, err) = finish(
        trainer(SUBSCRIBER, &p, "ends", STEPS, &out, &["--resume"]),
        LIMIT,
    );
    assert!(ok, "a finished run's resume is not a failure: {err}");
    assert!(
        err.contains("the run is complete (1 epochs): nothing left to train"),
        "{err}"
    );
    assert!(!err.contains("done training"), "no step: {err}");
    assert_eq!(metrics::read(&out.join("metrics.jsonl")).unwrap().len(), 6);
    stop_cleanly(pipe, LIMIT);
    no_shared_memory_left(&p);
    let _ = std::fs::remove_dir_all(&out);
}

/// A pipeline serving [`superflow_tests::replaceable_drives`] in `dir` (2 epochs, batches
/// of 1) as run `run`, once it has built its first batch and waits for a subscriber: the
/// drives, the pipeline, its stderr lines and the log read so far.
fn serve_replaceable_drives(
    dir: &Path,
    p: &str,
    run: &str,
) -> (
    Vec<PathBuf>,
    Proc,
    std::sync::mpsc::Receiver<String>,
    String,
) {
    let (drives, config) = superflow_tests::replaceable_drives(dir).unwrap();
    let mut pipe = spawn(
        pipeline_server(SUBSCRIBER, p)
            .arg("--mcap")
            .arg(&drives[0])
            .arg("--mcap")
            .arg(&drives[1])
            .arg("--config")
            .arg(&config)
            .args(["--run", run, "--batch-size", "1", "--epochs", "2"])
            .env("NO_COLOR", "1"),
    );
    let (rx, pipe_log) = wait_until_ready(&mut pipe, LIMIT);
    (drives, pipe, rx, pipe_log)
}

/// Both sample drives, copied into `dir`, replaced by truncated copies (a dataset re-sync
/// gone wrong) while a pipeline serves them: the pipeline reopens its files for every
/// read (`max_open_files = 1`, no index cache), so the samples it builds from then on
/// fail (unless its chunk caches still hold their data), and batches of nothing but
/// failed samples go out lost. The trainer counts each lost batch without a
/// step and says so, and the stream ends as usual: it does not wait for batches that
/// never come.
#[test]
fn lost_batches_are_counted_without_a_step_and_the_stream_still_ends() {
    let p = prefix("lost");
    let out = scratch::vacant("trainer", "lost");
    let dir = scratch::vacant("trainer", "lost-drives");
    // Its first batch is built (it waits for a subscriber to publish it): the drives are
    // replaced before the trainer comes.
    let (drives, pipe, rx, mut pipe_log) = serve_replaceable_drives(&dir, &p, "lost");
    superflow_tests::truncate_drives(&drives).unwrap();
    // 2 epochs of the drives' 12 keyframes: 24 batches, fewer steps.
    let (ok, _, err) = finish(trainer(SUBSCRIBER, &p, "lost", STEPS, &out, &[]), LIMIT);
    assert!(ok, "{err}");
    let lost = err
        .matches("batch lost: every sample failed in the pipeline")
        .count();
    let trained = metrics::read(&out.join("metrics.jsonl")).unwrap();
    // Which samples still build depends on what the pipeline's chunk caches hold.
    assert!(lost > 0, "{err}");
    assert!(
        !trained.is_empty(),
        "the first batch was built before: {err}"
    );
    assert_eq!(trained.len() + lost, 24, "{err}");
    assert!(
        err.contains(&format!("trained {} of the 24 steps asked", trained.len())),
        "the stream ended: {err}"
    );
    let steps: Vec<u64> = trained.iter().map(|r| r.step).collect();
    assert_eq!(steps, (1..=trained.len() as u64).collect::<Vec<_>>());
    let (ok, _, _) = finish(pipe, LIMIT);
    pipe_log.push_str(&drain(&rx, Duration::from_secs(2)));
    assert!(ok, "the pipeline ends once the trainer left: {pipe_log}");
    assert_eq!(
        pipe_log.matches("batch lost: all").count(),
        lost,
        "one error per lost batch: {pipe_log}"
    );
    no_shared_memory_left(&p);
    let _ = std::fs::remove_dir_all(&out);
    let _ = std::fs::remove_dir_all(&dir);
}

/// Both sample drives served by a pipeline that reopens its files for every read; after
/// its first batch, the first drive is replaced by an identical copy (a re-sync: new
/// inode, new times) and the second is deleted. Every sample of the first drive still
/// trains, in both epochs; the second drive's samples that no longer build are counted
/// (lost batches, the pipeline's `failed_samples`) and its missing file is one ERROR
/// line, not one per sample.
#[test]
fn a_resynced_drive_loses_nothing_and_a_deleted_one_is_one_counted_error() {
    let p = prefix("resync");
    let out = scratch::vacant("trainer", "resync");
    let dir = scratch::vacant("trainer", "resync-drives");
    let (drives, pipe, rx, mut pipe_log) = serve_replaceable_drives(&dir, &p, "resync");
    superflow_tests::resync_drives(&drives[..1]).unwrap();
    std::fs::remove_file(&drives[1]).unwrap();
    let (ok, _, err) = finish(trainer(SUBSCRIBER, &p, "resync", STEPS, &out, &[]), LIMIT);
    assert!(ok, "{err}");
    let lost = err
        .matches("batch lost: every sample failed in the pipeline")
        .count();
    let trained = metrics::read(&out.join("metrics.jsonl")).unwrap();
    assert_eq!(trained.len() + lost, 24, "{err}");
    let (ok, _, _) = finish(pipe, LIMIT);
    pipe_log.push_str(&drain(&rx, Duration::from_secs(2)));
    assert!(ok, "{pipe_log}");
    assert!(
        pipe_log.contains("replaced by a copy of the same content; reading the copy"),
        "{pipe_log}"
    );
    // The first drive's 6 keyframes train in both epochs: only the deleted drive's fail.
    let first = drives[0].display().to_string();
    let second = drives[1].display().to_string();
    let errors: Vec<&str> = pipe_log
        .lines()
        .filter(|l| l.contains("ERROR") && l.contains("sample lost"))
        .collect();
    assert!(
        errors.iter().all(|l| !l.contains(&first)),
        "a sample of the re-synced drive failed: {errors:#?}"
    );
    assert!(
        trained.len() >= 12,
        "{} trained:\n{pipe_log}",
        trained.len()
    );
    if lost > 0 {
        assert_eq!(
            errors.len(),
            1,
            "one line for the missing file: {errors:#?}"
        );
        assert!(errors[0].contains(&second), "{}", errors[0]);
        let failed = pipe_log
            .lines()
            .find(|l| l.contains("counters"))
            .and_then(|l| l.split("failed_samples=").nth(1))
            .and_then(|v| v.split_whitespace().next())
            .and_then(|v| v.parse::<usize>().ok());
        assert_eq!(failed, Some(lost), "every lost sample counted: {pipe_log}");
    }
    eprintln!(
        "{} trained, {lost} lost to the deleted drive",
        trained.len()
    );
    no_shared_memory_left(&p);
    let _ = std::fs::remove_dir_all(&out);
    let _ = std::fs::remove_dir_all(&dir);
}

/// Both sample drives served by a pipeline that keeps one file open
/// (`max_open_files = 1`); after its first batch, the drive whose file it holds open is
/// replaced by a truncated copy (other content, a new inode). Reading the other drive
/// makes the pool close a file: it keeps the replaced one open instead, past its limit,
/// and every sample of both drives trains in both epochs, from the content indexed.
#[test]
fn a_drive_replaced_while_open_is_read_on_from_its_descriptor() {
    let p = prefix("held");
    let out = scratch::vacant("trainer", "held");
    let dir = scratch::vacant("trainer", "held-drives");
    let (drives, pipe, rx, mut pipe_log) = serve_replaceable_drives(&dir, &p, "held");
    let fds = std::fs::read_dir(format!("/proc/{}/fd", pipe.id())).unwrap();
    let open: Vec<&PathBuf> = {
        let targets: Vec<PathBuf> = fds
            .filter_map(|fd| std::fs::read_link(fd.ok()?.path()).ok())
            .collect();
        drives.iter().filter(|d| targets.contains(d)).collect()
    };
    assert_eq!(open.len(), 1, "one drive open: {open:?}");
    let held = open[0].clone();
    superflow_tests::truncate_drives(std::slice::from_ref(&held)).unwrap();
    let (ok, _, err) = finish(trainer(SUBSCRIBER, &p, "held", STEPS, &out, &[]), LIMIT);
    assert!(ok, "{err}");
    let trained = metrics::read(&out.join("metrics.jsonl")).unwrap();
    let (ok, _, _) = finish(pipe, LIMIT);
    pipe_log.push_str(&drain(&rx, Duration::from_secs(2)));
    assert!(ok, "{pipe_log}");
    assert_eq!(trained.len(), 24, "every sample trained: {err}\n{pipe_log}");
    assert!(!pipe_log.contains("sample lost"), "{pipe_log}");
    let kept: Vec<&str> = pipe_log
        .lines()
        .filter(|l| l.contains("changed on disk while open: keeping"))
        .collect();
    assert_eq!(kept.len(), 1, "{pipe_log}");
    assert!(kept[0].contains(&held.display().to_string()), "{}", kept[0]);
    no_shared_memory_left(&p);
    let _ = std::fs::remove_dir_all(&out);
    let _ = std::fs::remove_dir_all(&dir);
}

/// `dir/batch.bin`: a batch of `samples` samples of the sample drive, written by
/// `superflow-pipeline batch`.
fn write_batch(dir: &Path, samples: usize) -> PathBuf {
    let batch = dir.join("batch.bin");
    let (ok, _, err) = finish(
        spawn(
            Command::new(pipeline_binary(SUBSCRIBER))
                .args(["batch", "--mcap", SAMPLE_DRIVE, "--batch-size"])
                .arg(samples.to_string())
                .arg("--out")
                .arg(&batch)
                .current_dir(workspace_root())
                .stdout(Stdio::null())
                .stderr(Stdio::piped()),
        ),
        LIMIT,
    );
    assert!(ok, "{err}");
    batch
}

/// `superflow-trainer check` of 2 steps on `batch` with the tiny presets on `backends`:
/// (success, stdout, stderr).
fn check_tiny(batch: &Path, backends: &str, extra: &[&OsStr]) -> (bool, String, String) {
    finish(
        spawn(
            Command::new(trainer_binary(SUBSCRIBER))
                .args(["check", "--batch"])
                .arg(batch)
                .args(["--backends", backends, "--steps", "2", "--unet", "tiny"])
                .args(["--vit", "tiny", "--pixel-stride", "4"])
                .args(extra)
                .stdout(Stdio::piped())
                .stderr(Stdio::piped()),
        ),
        LIMIT,
    )
}

#[test]
fn check_runs_the_same_steps_on_every_backend_and_compares_their_losses() {
    let dir = scratch::dir("trainer", "check");
    let batch = write_batch(&dir, 2);
    let json = dir.join("check.json");
    let (ok, out, err) = check_tiny(&batch, "flex,flex", &["--json".as_ref(), json.as_os_str()]);
    assert!(ok, "{out}\n{err}");
    assert!(
        out.contains("| flex |") && err.contains("the backends agree"),
        "{out}\n{err}"
    );
    let runs: serde_json::Value = serde_json::from_slice(&std::fs::read(&json).unwrap()).unwrap();
    let runs = runs.as_array().unwrap();
    assert_eq!(runs.len(), 2);
    let losses = |r: &serde_json::Value| r["losses"].as_array().unwrap().clone();
    assert_eq!(losses(&runs[0]).len(), 2, "2 steps");
    assert_eq!(
        losses(&runs[0]),
        losses(&runs[1]),
        "the same backend gives the same losses"
    );
    let total = |r: &serde_json::Value, i: usize| r["losses"][i]["total"].as_f64().unwrap();
    assert!(total(&runs[0], 0) > 0.0 && total(&runs[0], 0) != total(&runs[0], 1));

    // A batch file that is not one: an error naming it.
    std::fs::write(&batch, b"not a batch").unwrap();
    let (ok, _, err) = finish(
        spawn(
            Command::new(trainer_binary(SUBSCRIBER))
                .args(["check", "--backends", "flex", "--batch"])
                .arg(&batch)
                .stdout(Stdio::null())
                .stderr(Stdio::piped()),
        ),
        LIMIT,
    );
    assert!(
        !ok && err.contains("batch.bin") && err.contains("shorter than a batch header"),
        "{err}"
    );
    let _ = std::fs::remove_dir_all(&dir);
}

/// Whether a missing GPU backend is a failure (CI) rather than a skip.
fn in_ci() -> bool {
    std::env::var("CI").is_ok_and(|v| v == "true")
}

#[test]
fn check_agrees_on_wgpu_with_the_cpu_on_a_vulkan_device() {
    let dir = scratch::dir("trainer", "check-wgpu");
    // 4 samples: the sparse maps and the pooling have more rows than a GPU launches
    // workgroups in one dimension (65 535 on llvmpipe), where burn's own ops go wrong.
    let batch = write_batch(&dir, 4);
    let started = Instant::now();
    let (ok, out, err) = check_tiny(&batch, "flex,wgpu", &[]);
    let missing = ["is not compiled in", "no device on this machine"]
        .iter()
        .find(|m| err.contains(*m));
    if let (false, Some(missing)) = (ok, missing) {
        assert!(
            !in_ci(),
            "CI=true and wgpu cannot run ({missing}): build with --features \
             superflow-trainer/wgpu and install mesa-vulkan-drivers libvulkan1\n{err}"
        );
        eprintln!("SKIPPED: wgpu cannot run here ({missing})");
        return;
    }
    eprintln!(
        "{out}check flex,wgpu, 2 steps: {:.0} s",
        started.elapsed().as_secs_f64()
    );
    assert!(ok, "{out}\n{err}");
    assert!(
        out.contains("wgpu device: ")
            && out.contains("| wgpu |")
            && err.contains("the backends agree"),
        "{out}\n{err}"
    );
    let _ = std::fs::remove_dir_all(&dir);
}

/// `superflow-trainer features` of an untrained backbone on the sample drives: one cloud
/// per keyframe sweep (the drive's own sweep sizes), coloured by principal components and
/// by similarity to the query, which is 1 at the point nearest the query; every message
/// decoded by the reference reader with Foxglove's published classes; the bird's-eye PNG
/// beside it.
#[test]
fn features_of_a_backbone_open_as_foxglove_point_clouds() {
    use prost::Message as _;
    use superflow_pipeline::drive::{Dataset, IngestConfig};
    let out = scratch::dir("trainer", "features");
    let (file, bev) = (out.join("features.mcap"), out.join("features.png"));
    let (ok, stdout, err) = finish(
        spawn(
            Command::new(trainer_binary(SUBSCRIBER))
                .args([
                    "--unet",
                    "tiny",
                    "--vit",
                    "tiny",
                    "features",
                    "--mcap",
                    "recordings/drives",
                ])
                .args([
                    "--checkpoint",
                    "random",
                    "--query",
                    "12.5,-3,0.5",
                    "--images",
                    "--out",
                ])
                .arg(&file)
                .arg("--bev")
                .arg(&bev)
                .current_dir(workspace_root())
                .stdout(Stdio::piped())
                .stderr(Stdio::piped()),
        ),
        LIMIT,
    );
    assert!(ok, "{err}");
    // The keyframe sweeps of each drive, read here on their own: one per 0.5 s.
    let dataset = Dataset::open(
        &[superflow_recordings::sample_drives_dir()],
        &IngestConfig::default(),
    )
    .unwrap();
    let mut sizes = Vec::new();
    for drive in &dataset.drives {
        let lidar = drive.lidar.as_ref().unwrap();
        let mut cache = superflow_pipeline::source::ChunkCache::new(4);
        let mut last = None::<i64>;
        for frame in &lidar.sweeps {
            let t = frame.stamp.nanos();
            if last.is_some_and(|l| t - l < superflow_schemas::time::KEYFRAME_INTERVAL_NANOS) {
                continue;
            }
            last = Some(t);
            sizes.push(drive.read_sweep(frame, &mut cache).unwrap().cloud.xyz.len());
        }
    }
    assert!(
        stdout.contains(&format!(
            "{} sweeps, {} points",
            sizes.len(),
            sizes.iter().sum::<usize>()
        )),
        "{stdout}"
    );
    let bytes = std::fs::read(&file).unwrap();
    let mut clouds = Vec::new();
    let mut similarity_clouds = 0;
    let mut camera_messages: BTreeMap<String, usize> = BTreeMap::new();
    let mut camera_transforms = 0;
    for message in mcap::MessageStream::new(&bytes).unwrap() {
        let message = message.unwrap();
        let schema = message.channel.schema.as_ref().unwrap();
        let topic = message.channel.topic.as_str();
        match topic {
            "/superflow/features" => {
                assert_eq!(schema.name, "foxglove.PointCloud");
                clouds.push(foxglove::messages::PointCloud::decode(&message.data[..]).unwrap());
            }
            "/superflow/similarity" => similarity_clouds += 1,
            "/tf" => {
                assert_eq!(schema.name, "foxglove.FrameTransforms");
                let tf = foxglove::messages::FrameTransforms::decode(&message.data[..]).unwrap();
                camera_transforms += tf.transforms.len() - 1;
            }
            _ => {
                // The cameras' images, their ViT features and calibrations.
                let what = topic.rsplit('/').next().unwrap().to_string();
                assert!(
                    ["image", "vit_pca", "calibration"].contains(&what.as_str()),
                    "{topic}"
                );
                *camera_messages.entry(what).or_default() += 1;
            }
        }
    }
    // Every camera of both drives (6 each) at every keyframe sweep.
    let images = 6 * sizes.len();
    assert!(
        stdout.contains(&format!("images: {images} camera images")),
        "{stdout}"
    );
    for what in ["image", "vit_pca", "calibration"] {
        assert_eq!(camera_messages[what], images, "{what}");
    }
    assert_eq!(camera_transforms, images);
    let points: Vec<usize> = clouds
        .iter()
        .map(|c| c.data.len() / c.point_stride as usize)
        .collect();
    assert_eq!(points, sizes);
    assert_eq!(similarity_clouds, sizes.len());
    let field = |c: &foxglove::messages::PointCloud, name: &str| -> Vec<f32> {
        let f = c.fields.iter().find(|f| f.name == name).unwrap();
        c.data
            .chunks_exact(c.point_stride as usize)
            .map(|p| f32::from_le_bytes(p[f.offset as usize..][..4].try_into().unwrap()))
            .collect()
    };
    let names: Vec<&str> = clouds[0].fields.iter().map(|f| f.name.as_str()).collect();
    assert_eq!(
        names,
        [
            "x",
            "y",
            "z",
            "red",
            "green",
            "blue",
            "alpha",
            "pc1",
            "pc2",
            "pc3",
            "similarity"
        ]
    );
    // The point of the first sweep nearest the query is its own query: similarity 1.
    let (x, y, z) = (
        field(&clouds[0], "x"),
        field(&clouds[0], "y"),
        field(&clouds[0], "z"),
    );
    let nearest = (0..x.len())
        .min_by(|&a, &b| {
            let d = |i: usize| (x[i] - 12.5).powi(2) + (y[i] + 3.0).powi(2) + (z[i] - 0.5).powi(2);
            d(a).total_cmp(&d(b))
        })
        .unwrap();
    let sim = field(&clouds[0], "similarity");
    assert!((sim[nearest] - 1.0).abs() < 1e-5, "{}", sim[nearest]);
    for c in &clouds {
        assert!(
            field(c, "similarity")
                .iter()
                .all(|s| (-1.0001..=1.0001).contains(s))
        );
    }
    assert!(
        stdout.contains(&format!("query: point {nearest} of the first sweep")),
        "{stdout}"
    );
    // The reference reader with Foxglove's published classes decodes every message.
    let python = Command::new("python3")
        .args(["tests/python/check_sample_mcap.py"])
        .arg(&file)
        .current_dir(workspace_root())
        .output()
        .unwrap();
    let text = String::from_utf8_lossy(&python.stdout);
    assert!(
        python.status.success(),
        "{text}{}",
        String::from_utf8_lossy(&python.stderr)
    );
    assert!(text.trim_end().ends_with(" 0 failed"), "{text}");
    let png = std::fs::read(&bev).unwrap();
    assert_eq!(&png[..8], b"\x89PNG\r\n\x1a\n");
    assert_eq!(u32::from_be_bytes(png[16..20].try_into().unwrap()), 800);
    let _ = std::fs::remove_dir_all(&out);
}
