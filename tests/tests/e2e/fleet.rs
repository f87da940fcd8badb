//! Fleets, end to end with the real `superflow-pipeline` and `superflow-subscriber`:
//! drives of different rigs (6, 2 and 1 cameras; 16- and 32-beam LiDARs; two image
//! sizes) in one run and one batch; weighted dataset groups (`--dataset NAME=PATH:REPEAT`)
//! serving each keyframe exactly as often as their repeat says; and a job resumed on
//! another number of ranks or hosts (`--start-sample`, or a resume request by sample)
//! serving every sample of the epoch exactly once across the change, in the `global`
//! and the `blocks` order.

#![allow(clippy::unwrap_used, clippy::expect_used)] // tests fail loudly on purpose

use crate::SUBSCRIBER;
use serde_json::Value;
use std::collections::BTreeMap;
use std::path::PathBuf;
use std::process::{Command, Stdio};
use std::time::Duration;
use superflow_recordings::Dialect;
use superflow_tests::process::{
    self, Proc, finish, no_shared_memory_left, pipeline_server, prefix, stop, subscriber,
};
use superflow_tests::{
    rig_drive, sample_drive, scratch, trainer_binary, two_camera_rig, workspace_root,
};

const LIMIT: Duration = Duration::from_secs(300);

/// The batches a subscriber printed, after checking it succeeded.
fn batches_of(proc: Proc) -> Vec<Value> {
    let (ok, out, err) = finish(proc, LIMIT);
    assert!(ok, "subscriber failed:\n{err}\n{out}");
    out.lines()
        .map(|l| serde_json::from_str::<Value>(l).unwrap())
        .filter(|v| v.get("sequence").is_some())
        .collect()
}

/// One served sample: `(epoch, position in the epoch, drive, keyframe)` and its cameras.
#[derive(Debug, Clone, Copy, PartialEq, Eq, PartialOrd, Ord)]
struct Served {
    epoch: u64,
    position: u64,
    drive: u64,
    keyframe: u64,
    cameras: u64,
}

fn served(batches: &[Value]) -> Vec<Served> {
    batches
        .iter()
        .flat_map(|b| {
            let samples = b["samples"].as_array().unwrap();
            let cameras = b["cameras"].as_array().unwrap();
            assert_eq!(samples.len(), cameras.len());
            samples
                .iter()
                .zip(cameras)
                .map(|(s, k)| Served {
                    epoch: s[0].as_u64().unwrap(),
                    position: s[1].as_u64().unwrap(),
                    keyframe: s[2].as_u64().unwrap(),
                    drive: s[3].as_u64().unwrap(),
                    cameras: k.as_u64().unwrap(),
                })
                .collect::<Vec<_>>()
        })
        .collect()
}

fn path(p: PathBuf) -> String {
    p.display().to_string()
}

/// The small 2-camera drive served twice per epoch, half of the big 6-camera drive's
/// keyframes (another half each epoch): exact counts, each sample with its own cameras.
#[test]
fn weighted_groups_of_two_rigs_serve_each_keyframe_as_their_repeat_says() {
    let p = prefix("weights");
    let big = path(sample_drive(Dialect::Ros2).unwrap().path);
    let small = path(rig_drive(Dialect::Ros2, &two_camera_rig()).unwrap());
    // 6 keyframes × 0.5 + 6 × 2 = 15 samples an epoch, batches of 5: 3 a epoch.
    let reader = subscriber(SUBSCRIBER, &p, "weights", &["--count", "6"]);
    let pipe = process::spawn(
        pipeline_server(SUBSCRIBER, &p)
            .args(["--run", "weights", "--index-cache", "off"])
            .args([
                "--dataset".into(),
                format!("big={big}:0.5"),
                "--dataset".into(),
                format!("small={small}:2"),
                "--batch-size".into(),
                "5".into(),
                "--epochs".into(),
                "2".into(),
            ]),
    );
    let got = served(&batches_of(reader));
    let (ok, _, err) = finish(pipe, LIMIT);
    assert!(ok, "{err}");
    assert!(
        err.contains("group small: 1 drive(s), 6 keyframes × repeat 2 = 12 samples"),
        "{err}"
    );
    assert!(err.contains("rig 2: 2 camera(s)"), "{err}");
    let mut halves = Vec::new();
    for epoch in 0..2 {
        let mine: Vec<&Served> = got.iter().filter(|s| s.epoch == epoch).collect();
        assert_eq!(mine.len(), 15, "epoch {epoch}");
        let mut positions: Vec<u64> = mine.iter().map(|s| s.position).collect();
        positions.sort_unstable();
        assert_eq!(positions, (0..15).collect::<Vec<_>>());
        let mut count = BTreeMap::<(u64, u64), usize>::new();
        for s in &mine {
            *count.entry((s.drive, s.keyframe)).or_default() += 1;
            // A sample takes min(3, its rig's cameras).
            assert_eq!(s.cameras, if s.drive == 0 { 3 } else { 2 }, "{s:?}");
        }
        let big: Vec<u64> = count.keys().filter(|k| k.0 == 0).map(|k| k.1).collect();
        assert_eq!(big.len(), 3, "half of the big drive: {count:?}");
        assert!(count.iter().filter(|(k, _)| k.0 == 0).all(|(_, n)| *n == 1));
        let small: Vec<usize> = count
            .iter()
            .filter(|(k, _)| k.0 == 1)
            .map(|(_, n)| *n)
            .collect();
        assert_eq!(small, [2; 6], "the small drive twice: {count:?}");
        halves.push(big);
    }
    assert_ne!(
        halves[0], halves[1],
        "another half of the big drive each epoch"
    );
    no_shared_memory_left(&p);
}

/// A job stopped after `steps` batches of each of its `before` ranks (on `hosts_before`
/// hosts), resumed with `after` ranks on one host by `--start-sample` (or, `by_request`,
/// by its subscribers asking to resume at that sample on a pipeline started afresh):
/// every sample of the epoch served exactly once, in the epoch's `order`.
fn resumed_on_another_size(
    tag: &str,
    (before, hosts_before): (u32, u32),
    steps: usize,
    after: u32,
    by_request: bool,
    order: &str,
) {
    let drives = [
        path(sample_drive(Dialect::Ros2).unwrap().path),
        path(rig_drive(Dialect::Ros2, &two_camera_rig()).unwrap()),
    ];
    const KEYFRAMES: u64 = 12;
    const BATCH: u64 = 2;
    let common = |world: u32| -> Vec<String> {
        let mut args = vec!["--mcap".into()];
        args.extend(drives.iter().cloned());
        args.extend(
            [
                "--world-size",
                &world.to_string(),
                "--mode",
                "shard",
                "--batch-size",
                &BATCH.to_string(),
                "--epochs",
                "1",
                "--order",
                order,
            ]
            .map(String::from),
        );
        args
    };
    // The first job: every rank reads `steps` batches, then the job stops.
    let mut first = Vec::new();
    for host in 0..hosts_before {
        let p = prefix(&format!("{tag}h{host}"));
        let readers: Vec<Proc> = (0..before)
            .map(|r| {
                let rank = r.to_string();
                let count = steps.to_string();
                subscriber(SUBSCRIBER, &p, tag, &["--rank", &rank, "--count", &count])
            })
            .collect();
        let mut args = common(before);
        args.extend(
            [
                "--host-rank",
                &host.to_string(),
                "--host-count",
                &hosts_before.to_string(),
            ]
            .map(String::from),
        );
        let pipe = process::spawn(
            pipeline_server(SUBSCRIBER, &p)
                .args(["--run", tag, "--index-cache", "off"])
                .args(&args),
        );
        for reader in readers {
            first.extend(served(&batches_of(reader)));
        }
        let (_, _, err) = stop(pipe, LIMIT);
        assert!(!err.contains("panicked"), "{err}");
        no_shared_memory_left(&p);
    }
    let consumed = steps as u64 * BATCH * u64::from(before * hosts_before);
    let mut positions: Vec<u64> = first.iter().map(|s| s.position).collect();
    positions.sort_unstable();
    assert_eq!(
        positions,
        (0..consumed).collect::<Vec<_>>(),
        "the first job consumed the epoch's first samples"
    );
    // The job resumed on another size.
    let p = prefix(&format!("{tag}2"));
    let rest = KEYFRAMES - consumed;
    let world = u64::from(after);
    let resume = consumed.to_string();
    let readers: Vec<Proc> = (0..after)
        .map(|r| {
            let share = rest / world + u64::from(u64::from(r) < rest % world);
            let count = share.div_ceil(BATCH).to_string();
            let rank = r.to_string();
            let mut args = vec!["--rank", rank.as_str(), "--count", count.as_str()];
            if by_request {
                args.extend(["--resume-sample", "0", resume.as_str()]);
            }
            subscriber(SUBSCRIBER, &p, tag, &args)
        })
        .collect();
    let mut args = common(after);
    if !by_request {
        args.extend(["--start-sample".into(), resume.clone()]);
    }
    let pipe = process::spawn(
        pipeline_server(SUBSCRIBER, &p)
            .args(["--run", tag, "--index-cache", "off"])
            .args(&args),
    );
    let mut second = Vec::new();
    for reader in readers {
        second.extend(served(&batches_of(reader)));
    }
    let (ok, _, err) = finish(pipe, LIMIT);
    assert!(ok, "{err}");
    no_shared_memory_left(&p);
    let mut all: Vec<(u64, u64)> = first
        .iter()
        .chain(&second)
        .map(|s| (s.drive, s.keyframe))
        .collect();
    all.sort_unstable();
    let mut unique = all.clone();
    unique.dedup();
    assert_eq!(all, unique, "a keyframe served twice: {all:?}");
    assert_eq!(
        all.len() as u64,
        KEYFRAMES,
        "a keyframe never served: {all:?}"
    );
    let mut positions: Vec<u64> = first.iter().chain(&second).map(|s| s.position).collect();
    positions.sort_unstable();
    assert_eq!(positions, (0..KEYFRAMES).collect::<Vec<_>>());
}

#[test]
fn a_job_of_two_ranks_resumed_on_three_serves_every_keyframe_once() {
    resumed_on_another_size("el23", (2, 1), 1, 3, false, "global");
}

#[test]
fn a_job_of_two_ranks_in_blocks_resumed_on_three_serves_every_keyframe_once() {
    resumed_on_another_size("elb23", (2, 1), 1, 3, false, "blocks");
}

#[test]
fn a_job_of_three_ranks_resumed_on_two_by_request_serves_every_keyframe_once() {
    resumed_on_another_size("el32", (3, 1), 1, 2, true, "global");
}

#[test]
fn a_job_of_two_hosts_resumed_on_one_serves_every_keyframe_once() {
    resumed_on_another_size("elh21", (1, 2), 2, 1, false, "global");
}

/// One epoch of three rigs (6, 2 and 1 cameras) through the service to the Rust trainer:
/// every sample trained once with finite losses, the trainer ends with the stream; then
/// `probe` scores the trained backbone on the same mixed, labelled drives.
#[test]
fn the_trainer_trains_an_epoch_of_three_rigs_and_probe_scores_them() {
    let p = prefix("fleettrain");
    let out = scratch::vacant("fleet", "train");
    let drives: Vec<String> = superflow_tests::fleet_drives()
        .unwrap()
        .into_iter()
        .map(path)
        .collect();
    let mut args = vec!["--mcap".to_string()];
    args.extend(drives.iter().cloned());
    args.extend(["--batch-size", "3", "--epochs", "1"].map(String::from));
    let pipe = process::spawn(
        pipeline_server(SUBSCRIBER, &p)
            .args(["--run", "fleettrain", "--index-cache", "off"])
            .args(&args),
    );
    let trainer = process::trainer(SUBSCRIBER, &p, "fleettrain", 20, &out, &[]);
    let (ok, _, err) = finish(trainer, LIMIT);
    assert!(ok, "{err}");
    assert!(err.contains("trained 6 of the 20 steps asked"), "{err}");
    let (ok, _, perr) = finish(pipe, LIMIT);
    assert!(ok, "{perr}");
    no_shared_memory_left(&p);
    let records = superflow_trainer::metrics::read(&out.join("metrics.jsonl")).unwrap();
    let mut positions: Vec<u64> = records
        .iter()
        .flat_map(|r| r.sample_ids.iter().map(|&[_, position]| position))
        .collect();
    positions.sort_unstable();
    assert_eq!(positions, (0..18).collect::<Vec<_>>());
    assert!(
        records.iter().all(|r| r.loss.is_finite() && r.loss > 0.0),
        "{records:?}"
    );

    let checkpoint = out.join("checkpoints");
    let (ok, report, err) = finish(
        process::spawn(
            Command::new(trainer_binary(SUBSCRIBER))
                .arg("probe")
                .arg("--mcap")
                .args(&drives)
                .arg("--checkpoint")
                .arg(&checkpoint)
                .args(["--unet", "tiny", "--json", "--val-fraction", "0.3"])
                .args(["--gap-secs", "0.5", "--epochs", "3"])
                .current_dir(workspace_root())
                .stdout(Stdio::piped())
                .stderr(Stdio::piped()),
        ),
        LIMIT,
    );
    assert!(ok, "probe on three rigs:\n{err}");
    let report: Value = serde_json::from_str(report.lines().last().unwrap()).unwrap();
    let miou = report["miou"].as_f64().unwrap();
    assert!((0.0..=1.0).contains(&miou), "{report}");
    assert!(report["points"]["val"].as_u64().unwrap() > 1000, "{report}");
    let _ = std::fs::remove_dir_all(&out);
}
