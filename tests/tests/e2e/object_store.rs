//! Drives in object storage, end to end: the real `superflow-pipeline` reading
//! `s3://bucket/prefix/` from a local S3 server (moto, [`S3Server`]), directly or
//! through the fault-injecting [`FaultProxy`]. Batches built from objects are the bytes
//! of batches built from the same files on disk (both dialects, a damaged drive, a drive
//! with sidecars); an epoch through throttling and cut bodies serves every keyframe
//! once; an object replaced mid-run costs its own samples only, counted, while an
//! identical re-upload costs nothing; refused credentials are one clear error naming
//! the variables to check; a prefix of 1 100 drives is listed past the first page; a
//! warm index cache opens remote drives without a GET; a local chunk cache serves a
//! second pass without one.
//!
//! Every pipeline gets the server's endpoint and credentials in its own environment
//! (`S3Server::env`), never this process's, and no index cache or one of its own.
//! moto missing fails these tests with the command that installs it.

#![allow(clippy::unwrap_used, clippy::expect_used)] // tests fail loudly on purpose

use crate::SUBSCRIBER;
use serde_json::Value;
use std::collections::BTreeMap;
use std::path::{Path, PathBuf};
use std::time::{Duration, Instant};
use superflow_recordings::{ClassMapStorage, Dialect, DriveOptions, LidarLabels};
use superflow_tests::process::{
    self, batches, counter, drain, finish, free_port, lines_of, no_shared_memory_left, prefix,
    run_pipeline, scrape, spawn, stop,
};
use superflow_tests::s3::{Credentials, FaultPlan, FaultProxy, FaultScope, S3Server};
use superflow_tests::{rig_drive, sample_drive, scratch, workspace_root};

const LIMIT: Duration = Duration::from_secs(300);
/// Keyframes of a sample drive.
const SAMPLE_KEYFRAMES: u64 = 6;
/// Keyframes of [`tiny_drive`] (1.5 s: one every 0.5 s). A sample's keyframe number is
/// its place in the plan: the drives' keyframes one after the other, in drive order.
const TINY_KEYFRAMES: u64 = 3;

/// The smallest drive the generator writes that still makes samples: a ROS 2 drive of
/// 1.5 s, one small camera, a sparse LiDAR, small chunks, no labels.
fn tiny_drive() -> PathBuf {
    let options = DriveOptions {
        name: "s3tiny_{dialect}".into(),
        cameras: 1,
        image_size: (96, 54),
        lidar_columns: 30,
        ..DriveOptions::short()
    };
    rig_drive(Dialect::Ros2, &options).unwrap()
}

/// A short ROS 2 drive with two sidecars beside it: its class maps as PNGs in
/// `<drive>.superpixels.mcap` and its per-point labels in `<drive>.labels.mcap`; all
/// three files.
fn drive_with_sidecars() -> Vec<PathBuf> {
    let options = DriveOptions {
        name: "s3sidecars_{dialect}".into(),
        class_maps: ClassMapStorage::PngSidecar,
        labels: LidarLabels::Sidecar,
        ..DriveOptions::short()
    };
    let drive = rig_drive(Dialect::Ros2, &options).unwrap();
    let dir = drive.parent().unwrap();
    let files = vec![
        drive.clone(),
        dir.join(options.sidecar_name(Dialect::Ros2).unwrap()),
        dir.join(options.labels_sidecar_name(Dialect::Ros2).unwrap()),
    ];
    assert!(files.iter().all(|f| f.is_file()), "{files:?}");
    files
}

/// `superflow-pipeline … batch --index 0 --batch-size 2` of `input` into `out`, no
/// index cache; the batch's bytes.
fn batch(input: &str, out: &Path, env: &[(String, String)]) -> Vec<u8> {
    batch_with(&[], input, out, env).0
}

/// [`batch`] with `options` (e.g. `--config FILE`) first; the batch's bytes and the
/// pipeline's stderr.
fn batch_with(
    options: &[&str],
    input: &str,
    out: &Path,
    env: &[(String, String)],
) -> (Vec<u8>, String) {
    let out_arg = out.to_str().unwrap();
    let mut args = options.to_vec();
    args.extend([
        "--index-cache",
        "off",
        "batch",
        "--index",
        "0",
        "--batch-size",
        "2",
        "--out",
        out_arg,
        "--mcap",
        input,
    ]);
    let (ok, _, err) = run_pipeline(SUBSCRIBER, &args, env, LIMIT);
    assert!(ok, "batch of {input} failed:\n{err}");
    (std::fs::read(out).unwrap(), err)
}

/// The line `name   value` of `index`'s summary, its value.
fn summary<'a>(stdout: &'a str, name: &str) -> &'a str {
    stdout
        .lines()
        .find_map(|l| l.strip_prefix(name).filter(|v| v.starts_with(' ')))
        .map(str::trim)
        .unwrap_or_else(|| panic!("no `{name}` in the summary:\n{stdout}"))
}

/// `server.env(endpoint)` with other credentials.
fn with_credentials(
    env: Vec<(String, String)>,
    credentials: &Credentials,
) -> Vec<(String, String)> {
    env.into_iter()
        .map(|(k, v)| match k.as_str() {
            "AWS_ACCESS_KEY_ID" => (k, credentials.access_key_id.clone()),
            "AWS_SECRET_ACCESS_KEY" => (k, credentials.secret_access_key.clone()),
            _ => (k, v),
        })
        .collect()
}

/// The sample drives of both dialects (the ROS 2 one with its labels sidecar), a damaged
/// drive (cut short: no summary, read from the front) and a drive with a class-map and
/// a labels sidecar, each uploaded under a prefix of its own: `batch` of the prefix
/// writes the same bytes as `batch` of the files on disk. `inspect` of the prefix of
/// the drive with sidecars reports what it reports of the files, sidecars included.
#[test]
fn batches_from_s3_are_the_bytes_of_batches_from_local_files() {
    let server = S3Server::start();
    server.create_bucket("drives");
    let env = server.env(&server.endpoint());
    let dir = scratch::dir("object-store", "same-batches");
    let ros2 = sample_drive(Dialect::Ros2).unwrap().path;
    let cases: Vec<(&str, Vec<PathBuf>)> = vec![
        (
            "ros2",
            vec![ros2.clone(), ros2.with_extension("labels.mcap")],
        ),
        (
            "foxglove",
            vec![sample_drive(Dialect::Foxglove).unwrap().path],
        ),
        (
            "damaged",
            vec![workspace_root().join("recordings/damaged/ros2_truncated.mcap")],
        ),
        ("sidecars", drive_with_sidecars()),
    ];
    for (name, files) in &cases {
        let url = server.upload("drives", name, files);
        assert_eq!(url, format!("s3://drives/{name}/"));
        // The drive alone: its sidecars are found beside it.
        let local = batch(
            files[0].to_str().unwrap(),
            &dir.join(format!("{name}-local.bin")),
            &[],
        );
        let remote = batch(&url, &dir.join(format!("{name}-s3.bin")), &env);
        assert!(!local.is_empty(), "{name}");
        assert!(
            local == remote,
            "{name}: the batch from {url} differs from the local one ({} and {} bytes)",
            remote.len(),
            local.len()
        );
    }

    // The drive with sidecars: the same report from the prefix as from the files, its
    // sidecars among the drive's files and its class maps found in the PNG sidecar.
    let files = &cases[3].1;
    let inspect = |input: &str, env: &[(String, String)]| {
        let (ok, out, err) = run_pipeline(
            SUBSCRIBER,
            &["--index-cache", "off", "inspect", "--json", "--mcap", input],
            env,
            LIMIT,
        );
        assert!(ok, "inspect {input}:\n{err}");
        out
    };
    let local_dir = format!("{}/", files[0].parent().unwrap().display());
    let local =
        inspect(files[0].to_str().unwrap(), &[]).replace(&local_dir, "s3://drives/sidecars/");
    let remote = inspect("s3://drives/sidecars/", &env);
    let (local, remote): (Value, Value) = (
        serde_json::from_str(&local).unwrap(),
        serde_json::from_str(&remote).unwrap(),
    );
    assert_eq!(
        remote, local,
        "inspect of the prefix and of the files differ"
    );
    let drive = &remote["drives"][0];
    let paths: Vec<&str> = drive["files"]
        .as_array()
        .unwrap()
        .iter()
        .map(|f| f["path"].as_str().unwrap())
        .collect();
    let expected: Vec<String> = files
        .iter()
        .map(|f| {
            format!(
                "s3://drives/sidecars/{}",
                f.file_name().unwrap().to_string_lossy()
            )
        })
        .collect();
    let mut sorted_paths = paths.clone();
    sorted_paths.sort_unstable();
    let mut sorted_expected: Vec<&str> = expected.iter().map(String::as_str).collect();
    sorted_expected.sort_unstable();
    assert_eq!(sorted_paths, sorted_expected, "{drive}");
    let cameras = drive["cameras"].as_array().unwrap();
    assert!(!cameras.is_empty(), "{drive}");
    assert!(
        cameras.iter().all(|c| c["superpixel_topic"].is_string()),
        "class maps of every camera from the sidecar: {drive}"
    );
    assert!(
        drive["labels"]["sweeps_labelled"].as_u64().unwrap_or(0) > 0,
        "labels from the sidecar: {drive}"
    );
    std::fs::remove_dir_all(&dir).unwrap();
}

/// One epoch served from two dataset groups in object storage (`--dataset NAME=URL:R`,
/// one naming an object, one a prefix) through a proxy that answers 10 % of the GETs
/// with `503 SlowDown` once and cuts 1 % of the bodies short: every keyframe is served
/// exactly once, no batch is lost, and the retries the pipeline counts are the faults
/// the proxy injected.
#[test]
fn one_epoch_through_faults_serves_every_keyframe_once() {
    let server = S3Server::start();
    server.create_bucket("faults");
    let ros2 = sample_drive(Dialect::Ros2).unwrap().path;
    server.upload(
        "faults",
        "street",
        &[ros2.clone(), ros2.with_extension("labels.mcap")],
    );
    let tiny = server.upload("faults", "tiny", &[tiny_drive()]);
    let proxy = FaultProxy::start(
        &server.endpoint(),
        FaultPlan {
            p_503: 0.1,
            p_cut: 0.01,
            fail_once: true,
            scope: FaultScope::ObjectGets,
            ..FaultPlan::default()
        },
    );
    let p = prefix("s3faults");
    let addr = format!("127.0.0.1:{}", free_port());
    // 6 + 3 keyframes in batches of 3: 3 batches. The reader then stops reading and
    // holds the pipeline (its epoch done) until the metrics are scraped.
    let mut reader = process::subscriber(
        SUBSCRIBER,
        &p,
        "s3faults",
        &["--count", "4", "--stall-after", "3", "--stall-secs", "0"],
    );
    let group = format!("tiny={tiny}:1");
    let mut pipe = spawn(
        process::pipeline_command(
            SUBSCRIBER,
            "s3://faults/street/street_ros2.mcap",
            &p,
            "s3faults",
            &[
                "--dataset",
                &group,
                "--index-cache",
                "off",
                "--batch-size",
                "3",
                "--epochs",
                "1",
                "--metrics-addr",
                &addr,
            ],
        )
        .envs(server.env(&proxy.endpoint())),
    );
    let log = lines_of(pipe.stderr.take().unwrap());
    let lines = lines_of(reader.stdout.take().unwrap());
    let mut out = String::new();
    for _ in 0..3 {
        let line = lines.recv_timeout(LIMIT).unwrap_or_else(|_| {
            let log: Vec<String> = log.try_iter().collect();
            panic!("3 batches:\n{out}\n{}", log.join("\n"))
        });
        out.push_str(&line);
        out.push('\n');
    }
    let started = Instant::now();
    let metrics = loop {
        match scrape(&addr) {
            Ok(text) if counter(&text, "superflow_batches_total") >= 3 => break text,
            attempt if started.elapsed() > Duration::from_secs(60) => {
                panic!("no metrics at {addr}: {attempt:?}")
            }
            _ => std::thread::sleep(Duration::from_millis(100)),
        }
    };
    reader.kill().unwrap();
    drop(reader);
    let (ok, _, _) = stop(pipe, LIMIT);
    let log = drain(&log, Duration::from_secs(5));
    assert!(ok, "{log}");
    assert!(!log.contains("panicked"), "{log}");

    let got = batches(&out);
    assert_eq!(got.len(), 3, "{out}");
    assert!(got.iter().all(|b| b.get("lost").is_none()), "{out}");
    let mut positions = BTreeMap::<u64, usize>::new();
    let mut keyframes = BTreeMap::<(u64, u64), usize>::new();
    for batch in &got {
        for s in batch["samples"].as_array().unwrap() {
            assert_eq!(s[0], 0, "epoch 0: {batch}");
            *positions.entry(s[1].as_u64().unwrap()).or_default() += 1;
            *keyframes
                .entry((s[3].as_u64().unwrap(), s[2].as_u64().unwrap()))
                .or_default() += 1;
        }
    }
    let expected: Vec<(u64, u64)> = (0..SAMPLE_KEYFRAMES)
        .map(|k| (0, k))
        .chain((0..TINY_KEYFRAMES).map(|k| (1, SAMPLE_KEYFRAMES + k)))
        .collect();
    assert_eq!(
        keyframes.keys().copied().collect::<Vec<_>>(),
        expected,
        "{out}"
    );
    assert!(keyframes.values().all(|n| *n == 1), "{keyframes:?}");
    assert_eq!(
        positions.keys().copied().collect::<Vec<_>>(),
        (0..SAMPLE_KEYFRAMES + TINY_KEYFRAMES).collect::<Vec<_>>()
    );
    assert!(positions.values().all(|n| *n == 1), "{positions:?}");

    let counters = proxy.counters();
    let faults = counters.faults;
    eprintln!("proxy counters {counters:?}");
    assert!(faults.status_503 > 0, "no GET was throttled: {counters:?}");
    assert_eq!(
        counter(&metrics, "superflow_failed_samples_total"),
        0,
        "{metrics}"
    );
    assert_eq!(
        counter(&metrics, "superflow_lost_batches_total"),
        0,
        "{metrics}"
    );
    assert_eq!(
        counter(
            &metrics,
            "superflow_remote_retries_total{cause=\"throttled\"}"
        ),
        faults.status_503,
        "every 503 the proxy sent was counted as a retry:\n{metrics}"
    );
    assert_eq!(
        counter(
            &metrics,
            "superflow_remote_retries_total{cause=\"body_cut\"}"
        ),
        faults.cut,
        "every body cut short was counted:\n{metrics}"
    );
    // Every attempt the pipeline counts is a request the proxy saw.
    for (name, seen) in [
        ("superflow_remote_gets_total", counters.gets()),
        ("superflow_remote_lists_total", counters.list),
        ("superflow_remote_heads_total", counters.head),
        ("superflow_remote_requests_total", counters.requests()),
    ] {
        assert_eq!(
            counter(&metrics, name),
            seen,
            "{name}: {counters:?}\n{metrics}"
        );
    }
    no_shared_memory_left(&p);
}

/// Two drives under one prefix, served for 2 epochs in batches of 1 with no read-ahead
/// (`remote_prefetch_mb = 0`, so that reads after the first batch go to the store).
/// Once the first batch is received, the first drive's object is replaced by other
/// bytes and the second one's is uploaded again unchanged (the same ETag): the samples
/// of the replaced drive that still need reads fail, each counted and published as a
/// lost batch, with the object's URL and "replaced" in the log; every sample of the
/// re-uploaded drive is served in both epochs; the pipeline ends as usual.
#[test]
fn an_object_replaced_mid_run_costs_its_own_samples_and_the_same_bytes_read_on() {
    let server = S3Server::start();
    server.create_bucket("replace");
    let street = sample_drive(Dialect::Ros2).unwrap().bytes;
    let tiny = std::fs::read(tiny_drive()).unwrap();
    server.put("replace", "run/a.mcap", &street);
    let etag = server.put("replace", "run/b.mcap", &tiny);
    let dir = scratch::dir("object-store", "replace");
    let config = dir.join("pipeline.toml");
    std::fs::write(&config, "[ingest]\nremote_prefetch_mb = 0\n").unwrap();
    let p = prefix("s3replace");
    let total = 2 * (SAMPLE_KEYFRAMES + TINY_KEYFRAMES);
    let mut reader = process::subscriber(
        SUBSCRIBER,
        &p,
        "s3replace",
        &["--count", &total.to_string()],
    );
    let mut pipe = spawn(
        process::pipeline_command(
            SUBSCRIBER,
            "s3://replace/run/",
            &p,
            "s3replace",
            &[
                "--config",
                config.to_str().unwrap(),
                "--index-cache",
                "off",
                "--batch-size",
                "1",
                "--epochs",
                "2",
            ],
        )
        .env("NO_COLOR", "1")
        .envs(server.env(&server.endpoint())),
    );
    let log = lines_of(pipe.stderr.take().unwrap());
    let lines = lines_of(reader.stdout.take().unwrap());
    let mut out = lines.recv_timeout(LIMIT).expect("the first batch");
    out.push('\n');
    let other =
        std::fs::read(workspace_root().join("recordings/damaged/ros2_flipped_chunk.mcap")).unwrap();
    server.put("replace", "run/a.mcap", &other);
    assert_eq!(server.put("replace", "run/b.mcap", &tiny), etag);
    let (ok, _, err) = finish(reader, LIMIT);
    assert!(ok, "{err}");
    out.push_str(&drain(&lines, Duration::from_secs(5)));
    let (ok, _, _) = finish(pipe, LIMIT);
    let log = drain(&log, Duration::from_secs(5));
    assert!(ok, "the pipeline ends once its reader left:\n{log}");
    assert!(!log.contains("panicked"), "{log}");

    let got = batches(&out);
    let sequences: Vec<u64> = got
        .iter()
        .map(|b| b["sequence"].as_u64().unwrap())
        .collect();
    assert_eq!(sequences, (0..total).collect::<Vec<_>>(), "{out}");
    assert!(
        got[0].get("lost").is_none(),
        "the first batch is whole: {out}"
    );
    let lost = got.iter().filter(|b| b["lost"] == true).count() as u64;
    let mut served = BTreeMap::<(u64, u64, u64), usize>::new();
    for b in &got {
        for s in b["samples"].as_array().unwrap() {
            let key = (
                s[0].as_u64().unwrap(),
                s[3].as_u64().unwrap(),
                s[2].as_u64().unwrap(),
            );
            *served.entry(key).or_default() += 1;
        }
    }
    assert!(served.values().all(|n| *n == 1), "{served:?}");
    assert_eq!(served.len() as u64 + lost, total, "{out}");
    for epoch in 0..2 {
        let same: Vec<u64> = served
            .keys()
            .filter(|k| k.0 == epoch && k.1 == 1)
            .map(|k| k.2)
            .collect();
        assert_eq!(
            same,
            (SAMPLE_KEYFRAMES..SAMPLE_KEYFRAMES + TINY_KEYFRAMES).collect::<Vec<_>>(),
            "epoch {epoch}: every sample of the re-uploaded drive:\n{out}\n{log}"
        );
    }
    assert!(
        lost > 0,
        "no sample of the replaced drive failed:\n{out}\n{log}"
    );
    let failures: Vec<&str> = log
        .lines()
        .filter(|l| l.contains("ERROR") || l.contains("WARN"))
        .filter(|l| l.contains(".mcap"))
        .collect();
    assert!(
        failures
            .iter()
            .any(|l| l.contains("s3://replace/run/a.mcap") && l.contains("replaced")),
        "the replaced object named:\n{log}"
    );
    assert!(
        failures.iter().all(|l| !l.contains("run/b.mcap")),
        "the re-uploaded object failed:\n{log}"
    );
    let last = log
        .lines()
        .rfind(|l| l.contains("counters"))
        .unwrap_or_else(|| panic!("no counters line:\n{log}"));
    let field = |name: &str| -> u64 {
        last.split(&format!("{name}="))
            .nth(1)
            .and_then(|v| v.split_whitespace().next())
            .and_then(|v| v.parse().ok())
            .unwrap_or_else(|| panic!("no {name} in {last}"))
    };
    assert_eq!(field("failed_samples"), lost, "{last}");
    assert_eq!(field("lost_batches"), lost, "{last}");
    assert_eq!(field("batches"), total, "{last}");
    no_shared_memory_left(&p);
    std::fs::remove_dir_all(&dir).unwrap();
}

/// With authentication on, a wrong secret and an unknown key each end `index` at once
/// with an error that says the store refused the credentials and names the variables
/// to check, without the secret; the right credentials index the drive.
#[test]
fn wrong_credentials_are_a_clear_error_at_start() {
    let (server, valid) = S3Server::start_with_auth();
    server.create_bucket("private");
    let url = server.upload("private", "drives", &[tiny_drive()]);
    let index = |credentials: &Credentials| {
        let env = with_credentials(server.env(&server.endpoint()), credentials);
        let started = Instant::now();
        let (ok, out, err) = run_pipeline(
            SUBSCRIBER,
            &["--index-cache", "off", "index", "--mcap", &url],
            &env,
            LIMIT,
        );
        (ok, out, err, started.elapsed())
    };
    for wrong in [
        Credentials {
            secret_access_key: "wrong-secret-0123456789".into(),
            ..valid.clone()
        },
        Credentials {
            access_key_id: "AKIAUNKNOWNKEY000000".into(),
            secret_access_key: "another-wrong-secret-42".into(),
        },
    ] {
        let (ok, out, err, took) = index(&wrong);
        assert!(!ok, "{wrong:?} indexed:\n{out}");
        assert!(
            took < Duration::from_secs(30),
            "{wrong:?}: refused after {took:?}"
        );
        for words in [
            "refused",
            "AWS_ACCESS_KEY_ID",
            "AWS_SECRET_ACCESS_KEY",
            "s3://private/drives/",
        ] {
            assert!(err.contains(words), "{wrong:?}: `{words}` not in:\n{err}");
        }
        for secret in [&wrong.secret_access_key, &valid.secret_access_key] {
            assert!(
                !err.contains(secret.as_str()) && !out.contains(secret.as_str()),
                "the secret is shown:\n{err}"
            );
        }
    }
    let (ok, out, err, _) = index(&valid);
    assert!(ok, "{err}");
    assert_eq!(summary(&out, "drives"), "1", "{out}");
    assert!(!err.contains(&valid.secret_access_key), "{err}");
}

/// 1 100 copies of a small drive under one prefix: `index` lists them all (two LIST
/// pages at least: S3 returns 1 000 keys a page) and indexes every one as a drive.
#[test]
fn a_prefix_of_1100_drives_is_listed_past_the_first_page() {
    const DRIVES: usize = 1_100;
    let server = S3Server::start();
    server.create_bucket("many");
    let bytes = std::fs::read(tiny_drive()).unwrap();
    server.put_many(
        "many",
        (0..DRIVES).map(|i| (format!("fleet/drive_{i:04}.mcap"), bytes.clone())),
    );
    let proxy = FaultProxy::start(&server.endpoint(), FaultPlan::default());
    let started = Instant::now();
    let (ok, out, err) = run_pipeline(
        SUBSCRIBER,
        &[
            "--index-cache",
            "off",
            "index",
            "--mcap",
            "s3://many/fleet/",
        ],
        &server.env(&proxy.endpoint()),
        LIMIT,
    );
    let took = started.elapsed();
    assert!(ok, "{err}");
    eprintln!(
        "indexed {DRIVES} drives in {took:?}; proxy counters {:?}",
        proxy.counters()
    );
    assert_eq!(summary(&out, "drives"), DRIVES.to_string(), "{out}");
    assert!(
        summary(&out, "files").starts_with(&format!("{DRIVES} (")),
        "{out}"
    );
    assert_eq!(
        summary(&out, "keyframes"),
        (DRIVES as u64 * TINY_KEYFRAMES).to_string(),
        "{out}"
    );
    assert_eq!(summary(&out, "not trainable"), "0 drives", "{out}");
    let counters = proxy.counters();
    assert!(counters.list >= 2, "{counters:?}");
}

/// A store that answers every GET with `503 SlowDown`: `index` fails once the
/// configured retries (`[ingest] remote_retries = 2`) are spent, with an error that
/// names the object and says what the store answered (not a verdict on the bytes it
/// never sent), well within the configured timeouts.
#[test]
fn a_store_that_keeps_failing_is_a_clear_error_after_the_configured_retries() {
    let server = S3Server::start();
    server.create_bucket("failing");
    let url = server.upload("failing", "drives", &[tiny_drive()]);
    let proxy = FaultProxy::start(
        &server.endpoint(),
        FaultPlan {
            p_503: 1.0,
            scope: FaultScope::ObjectGets,
            ..FaultPlan::default()
        },
    );
    let dir = scratch::dir("object-store", "failing");
    let config = dir.join("pipeline.toml");
    std::fs::write(
        &config,
        "[ingest]\nremote_retries = 2\nremote_timeout_secs = 2\n",
    )
    .unwrap();
    let started = Instant::now();
    let (ok, out, err) = run_pipeline(
        SUBSCRIBER,
        &[
            "--config",
            config.to_str().unwrap(),
            "--index-cache",
            "off",
            "index",
            "--mcap",
            &url,
        ],
        &server.env(&proxy.endpoint()),
        LIMIT,
    );
    let took = started.elapsed();
    assert!(!ok, "{out}");
    let counters = proxy.counters();
    assert!(
        (1..=3).contains(&counters.gets()),
        "one GET and at most 2 retries (remote_retries = 2): {counters:?}\n{err}"
    );
    assert!(took < Duration::from_secs(20), "failed after {took:?}");
    assert!(
        err.contains("s3://failing/drives/s3tiny_ros2.mcap"),
        "{err}"
    );
    assert!(
        err.contains("503") || err.contains("SlowDown"),
        "the store's answer is not in the error:\n{err}"
    );
    assert!(!err.contains("not an MCAP file"), "{err}");
    std::fs::remove_dir_all(&dir).unwrap();
}

/// `index` twice over a prefix with one index cache: the first indexes every file (its
/// GETs), the second opens them all from the cache after one listing: LIST requests,
/// no GET, no HEAD. An object uploaded again with the same bytes is still a cache hit;
/// one changed (same size, another ETag) is indexed again, alone, in one GET.
#[test]
fn a_warm_index_cache_over_s3_sends_no_get() {
    let server = S3Server::start();
    server.create_bucket("warm");
    let ros2 = sample_drive(Dialect::Ros2).unwrap().path;
    let url = server.upload(
        "warm",
        "drives",
        &[
            ros2.clone(),
            ros2.with_extension("labels.mcap"),
            tiny_drive(),
        ],
    );
    let proxy = FaultProxy::start(&server.endpoint(), FaultPlan::default());
    let env = server.env(&proxy.endpoint());
    let dir = scratch::dir("object-store", "warm");
    let cache = dir.join("cache");
    let index = || {
        let (ok, out, err) = run_pipeline(
            SUBSCRIBER,
            &[
                "--index-cache",
                cache.to_str().unwrap(),
                "index",
                "--mcap",
                &url,
            ],
            &env,
            LIMIT,
        );
        assert!(ok, "{err}");
        out
    };
    let cold = index();
    assert_eq!(summary(&cold, "drives"), "2", "{cold}");
    assert_eq!(summary(&cold, "cache hits"), "0 of 3", "{cold}");
    let first = proxy.counters();
    assert!(first.gets() > 0, "{first:?}");
    proxy.reset_counters();
    let warm = index();
    assert_eq!(summary(&warm, "drives"), "2", "{warm}");
    assert_eq!(summary(&warm, "cache hits"), "3 of 3", "{warm}");
    assert_eq!(
        summary(&warm, "keyframes"),
        summary(&cold, "keyframes"),
        "{cold}\n{warm}"
    );
    let second = proxy.counters();
    assert!(second.list >= 1, "{second:?}");
    assert_eq!(
        (second.gets(), second.head),
        (0, 0),
        "a warm start read objects: {second:?}\n{warm}"
    );

    // The same bytes uploaded again (the same ETag): still every file from the cache.
    // Other bytes of the same size (one byte changed): that object alone is read again.
    let tiny = std::fs::read(tiny_drive()).unwrap();
    let key = format!(
        "drives/{}",
        tiny_drive().file_name().unwrap().to_string_lossy()
    );
    let etag = server.put("warm", &key, &tiny);
    proxy.reset_counters();
    let again = index();
    assert_eq!(summary(&again, "cache hits"), "3 of 3", "{again}");
    assert_eq!(proxy.counters().gets(), 0, "{:?}", proxy.counters());
    let mut changed = tiny.clone();
    let middle = changed.len() / 2;
    changed[middle] ^= 0xFF;
    assert_ne!(server.put("warm", &key, &changed), etag);
    proxy.reset_counters();
    let after = index();
    assert_eq!(summary(&after, "cache hits"), "2 of 3", "{after}");
    let third = proxy.counters();
    // One GET of the whole (small) object: the sweep the plan times the cameras with
    // is kept from the scan, not asked for again.
    assert!(
        third.gets() == 1 && third.distinct_get_bytes <= tiny.len() as u64,
        "only the changed object is read, once: {third:?}"
    );
    std::fs::remove_dir_all(&dir).unwrap();
}

/// The local chunk cache (`[ingest] remote_cache_dir`): a second batch over drives the
/// cache holds sends no GET and writes the same bytes; a cache smaller than any chunk
/// reads through (the same bytes, nothing kept); a directory others may write is not
/// used, with a warning, and the batch is still built.
#[test]
fn a_local_chunk_cache_serves_a_second_pass_without_a_get() {
    let server = S3Server::start();
    server.create_bucket("chunks");
    let ros2 = sample_drive(Dialect::Ros2).unwrap().path;
    let url = server.upload("chunks", "drives", std::slice::from_ref(&ros2));
    let proxy = FaultProxy::start(&server.endpoint(), FaultPlan::default());
    let env = server.env(&proxy.endpoint());
    let dir = scratch::dir("object-store", "chunks");
    let local = batch(ros2.to_str().unwrap(), &dir.join("local.bin"), &env);
    let with_cache = |name: &str, bytes: u64| {
        let config = dir.join(format!("{name}.toml"));
        let chunks = dir.join(name);
        std::fs::write(
            &config,
            format!(
                "[ingest]\nremote_cache_dir = \"{}\"\nremote_cache_bytes = {bytes}\n",
                chunks.display()
            ),
        )
        .unwrap();
        (config, chunks)
    };
    let run = |config: &Path, out: &str| {
        let config = ["--config", config.to_str().unwrap()];
        batch_with(&config, &url, &dir.join(out), &env)
    };
    let ranges = |chunks: &Path| {
        std::fs::read_dir(chunks)
            .map(|d| d.flatten().count())
            .unwrap_or(0)
    };

    let (config, chunks) = with_cache("big", 1 << 30);
    let (first, _) = run(&config, "first.bin");
    assert_eq!(first, local);
    assert!(proxy.counters().gets() > 0);
    assert!(ranges(&chunks) > 0, "nothing kept in {}", chunks.display());
    proxy.reset_counters();
    let (second, _) = run(&config, "second.bin");
    assert_eq!(second, local);
    let counters = proxy.counters();
    assert_eq!(counters.gets(), 0, "the cache held it all: {counters:?}");
    assert!(counters.list >= 1, "{counters:?}");

    let (config, chunks) = with_cache("tiny", 16);
    proxy.reset_counters();
    let (through, _) = run(&config, "through.bin");
    assert_eq!(through, local);
    assert!(proxy.counters().gets() > 0);
    assert_eq!(ranges(&chunks), 0, "a range larger than the cache was kept");

    let (config, chunks) = with_cache("open", 1 << 30);
    std::fs::create_dir_all(&chunks).unwrap();
    std::fs::set_permissions(&chunks, std::os::unix::fs::PermissionsExt::from_mode(0o777)).unwrap();
    let (refused, err) = run(&config, "refused.bin");
    assert_eq!(refused, local);
    assert!(err.contains("chunk cache is not used"), "{err}");
    assert_eq!(ranges(&chunks), 0);
    std::fs::remove_dir_all(&dir).unwrap();
}
