//! The real `superflow-pipeline` streaming to `superflow-subscriber` processes over
//! iceoryx2 (each test with its own run name and iceoryx2 prefix, so tests run in
//! parallel): shard accounting, broadcast identity, backpressure without loss, a
//! SIGKILLed subscriber cleaned up, resume at a position, and a resume past the last
//! epoch told as the run being complete.

#![allow(clippy::unwrap_used, clippy::expect_used)] // tests fail loudly on purpose

use crate::SUBSCRIBER;
use std::time::{Duration, Instant};
use superflow_tests::process::{
    self, Proc, batches, counter, drain, finish, lines_of, no_shared_memory_left, prefix,
    sample_keys, scrape, send_signal, serve, stop_cleanly, subscriber, trainer, wait_until_ready,
};
use superflow_tests::scratch;

/// Keyframes of the sample drive (its plan; `samples.rs` checks it).
const KEYFRAMES: u64 = 6;

const LIMIT: Duration = Duration::from_secs(180);

#[test]
fn two_shards_receive_every_keyframe_once_per_epoch() {
    let p = prefix("shard");
    // 6 keyframes, 2 ranks, batches of 2: 2 batches per rank per epoch; 2 epochs.
    let subscribers: Vec<Proc> = (0..2)
        .map(|r| {
            subscriber(
                SUBSCRIBER,
                &p,
                "shard",
                &["--rank", &r.to_string(), "--count", "4"],
            )
        })
        .collect();
    let pipe = serve(
        SUBSCRIBER,
        &p,
        "shard",
        &["--world-size", "2", "--batch-size", "2", "--epochs", "2"],
    );
    let mut per_rank = Vec::new();
    for child in subscribers {
        let (ok, out, err) = finish(child, LIMIT);
        assert!(ok, "{err}");
        per_rank.push(sample_keys(&batches(&out)));
    }
    let (ok, _, err) = finish(pipe, LIMIT);
    assert!(ok, "{err}");
    process::assert_shards_cover(&per_rank, 2, KEYFRAMES);
    no_shared_memory_left(&p);
}

#[test]
fn broadcast_subscribers_receive_identical_batches() {
    let p = prefix("bcast");
    let subscribers: Vec<Proc> = (0..3)
        .map(|_| subscriber(SUBSCRIBER, &p, "bcast", &["--count", "3"]))
        .collect();
    let pipe = serve(
        SUBSCRIBER,
        &p,
        "bcast",
        &["--batch-size", "2", "--epochs", "1", "--subscribers", "3"],
    );
    let mut got = Vec::new();
    for child in subscribers {
        let (ok, out, err) = finish(child, LIMIT);
        assert!(ok, "{err}");
        got.push(batches(&out));
    }
    let (ok, _, err) = finish(pipe, LIMIT);
    assert!(ok, "{err}");
    let mut keys = sample_keys(&got[0]);
    keys.sort_unstable();
    assert_eq!(keys, (0..KEYFRAMES).map(|k| (0, k)).collect::<Vec<_>>());
    for other in &got[1..] {
        assert_eq!(
            other, &got[0],
            "broadcast subscribers saw different batches"
        );
    }
    assert_eq!(
        got[0]
            .iter()
            .map(|b| b["step"].as_u64().unwrap())
            .collect::<Vec<_>>(),
        [0, 1, 2]
    );
    no_shared_memory_left(&p);
}

/// A subscriber that stops reading for a while makes the publisher wait (its queue of
/// one batch is full); nothing is dropped, for it or for the other subscriber.
#[test]
fn a_stalled_subscriber_slows_the_stream_without_loss() {
    let p = prefix("stall");
    let slow = subscriber(
        SUBSCRIBER,
        &p,
        "stall",
        &[
            "--count",
            "6",
            "--buffer",
            "1",
            "--stall-after",
            "1",
            "--stall-secs",
            "3",
        ],
    );
    let fast = subscriber(SUBSCRIBER, &p, "stall", &["--count", "6"]);
    let started = Instant::now();
    let pipe = serve(
        SUBSCRIBER,
        &p,
        "stall",
        &["--batch-size", "2", "--epochs", "2", "--subscribers", "2"],
    );
    let (ok_fast, out_fast, err_fast) = finish(fast, LIMIT);
    let (ok_slow, out_slow, err_slow) = finish(slow, LIMIT);
    assert!(ok_fast && ok_slow, "{err_fast}\n{err_slow}");
    let (ok, _, err) = finish(pipe, LIMIT);
    assert!(ok, "{err}");
    let (fast, slow) = (batches(&out_fast), batches(&out_slow));
    assert_eq!(fast, slow, "both received the same 6 batches");
    let sequences: Vec<u64> = fast
        .iter()
        .map(|b| b["sequence"].as_u64().unwrap())
        .collect();
    assert_eq!(sequences, (0..6).collect::<Vec<_>>());
    // The stall held the stream back (the whole run took at least the stall).
    assert!(started.elapsed() >= Duration::from_secs(3));
    no_shared_memory_left(&p);
}

/// A subscriber killed with SIGKILL while its queue is full is found dead, cleaned up,
/// and the other subscriber receives the whole stream.
#[test]
fn a_killed_subscriber_is_cleaned_up_and_the_stream_goes_on() {
    let p = prefix("kill");
    let mut doomed = subscriber(
        SUBSCRIBER,
        &p,
        "kill",
        &["--count", "9", "--buffer", "1", "--stall-after", "1"],
    );
    let survivor = subscriber(SUBSCRIBER, &p, "kill", &["--count", "9"]);
    let pipe = serve(
        SUBSCRIBER,
        &p,
        "kill",
        &["--batch-size", "2", "--epochs", "3", "--subscribers", "2"],
    );
    // Kill it once it has received its first batch (it then stops reading, its queue
    // of one fills up and the publisher waits on it).
    let rx = lines_of(doomed.stdout.take().unwrap());
    let first = rx
        .recv_timeout(LIMIT)
        .expect("the doomed subscriber got a batch");
    assert!(first.contains("\"sequence\":0"), "{first}");
    std::thread::sleep(Duration::from_secs(1));
    doomed.kill().unwrap(); // SIGKILL
    let _ = doomed.wait();
    let (ok, out, err) = finish(survivor, LIMIT);
    assert!(ok, "{err}");
    let got = batches(&out);
    assert_eq!(got.len(), 9);
    let mut keys = sample_keys(&got);
    keys.sort_unstable();
    let expected: Vec<(u64, u64)> = (0..3)
        .flat_map(|e| (0..KEYFRAMES).map(move |k| (e, k)))
        .collect();
    assert_eq!(keys, expected);
    let (ok, _, err) = finish(pipe, LIMIT);
    assert!(ok, "{err}");
    assert!(err.contains("a subscriber died"), "{err}");
    no_shared_memory_left(&p);
}

/// A subscriber that asks to resume at (epoch, step) receives exactly the batches from
/// there on, bit-identical to the first time round; a pipeline started at a position
/// publishes the same batches without building the ones before it.
#[test]
fn resuming_at_a_position_replays_exactly_the_following_batches() {
    let p = prefix("resume");
    // Read steps 0, 1, 2 of epoch 0, then rewind to (0, 1): expect 1, 2 again, then all
    // of epoch 1 (the pipeline publishes until its epochs are done, so the reader reads
    // them all).
    let reader = subscriber(
        SUBSCRIBER,
        &p,
        "resume",
        &[
            "--count",
            "8",
            "--resume-after",
            "3",
            "--resume-to",
            "0",
            "1",
        ],
    );
    let pipe = serve(
        SUBSCRIBER,
        &p,
        "resume",
        &["--batch-size", "2", "--epochs", "2"],
    );
    let (ok, out, err) = finish(reader, LIMIT);
    assert!(ok, "{err}\n{out}");
    let (ok, _, err) = finish(pipe, LIMIT);
    assert!(ok, "{err}");
    assert!(out.contains("\"resume\":[0,1],\"accepted\":1"), "{out}");
    let got = batches(&out);
    let positions: Vec<(u64, u64)> = got
        .iter()
        .map(|b| (b["epoch"].as_u64().unwrap(), b["step"].as_u64().unwrap()))
        .collect();
    assert_eq!(
        positions,
        [
            (0, 0),
            (0, 1),
            (0, 2),
            (0, 1),
            (0, 2),
            (1, 0),
            (1, 1),
            (1, 2)
        ]
    );
    assert_eq!(got[1]["hash"], got[3]["hash"]);
    assert_eq!(got[2]["hash"], got[4]["hash"]);
    assert_eq!(got[1]["samples"], got[3]["samples"]);

    // A pipeline started at (0, 2) publishes that batch first, the same bits (it is the
    // last batch of the one epoch asked for, so the pipeline then ends).
    let p2 = prefix("start");
    let reader = subscriber(SUBSCRIBER, &p2, "start", &["--count", "1"]);
    let pipe = serve(
        SUBSCRIBER,
        &p2,
        "start",
        &[
            "--batch-size",
            "2",
            "--epochs",
            "1",
            "--start-epoch",
            "0",
            "--start-step",
            "2",
        ],
    );
    let (ok, out2, err) = finish(reader, LIMIT);
    assert!(ok, "{err}");
    let (ok, _, err) = finish(pipe, LIMIT);
    assert!(ok, "{err}");
    let first = &batches(&out2)[0];
    assert_eq!(
        (first["epoch"].as_u64(), first["step"].as_u64()),
        (Some(0), Some(2))
    );
    assert_eq!(first["hash"], got[2]["hash"]);
    no_shared_memory_left(&p);
    no_shared_memory_left(&p2);
}

/// A resume at the end of the last epoch (by step or by sample) or past it is refused
/// as the run being complete (reason 4, the reply's epoch the run's epochs); a step
/// beyond an epoch's end is still a position that does not exist (reason 2).
#[test]
fn a_resume_past_the_last_epoch_is_run_complete() {
    let p = prefix("complete");
    // A subscriber that never reads keeps the pipeline serving (it would end once its
    // one epoch is published and its subscribers gone).
    let mut holder = subscriber(
        SUBSCRIBER,
        &p,
        "complete",
        &["--count", "1", "--stall-after", "0"],
    );
    // 6 keyframes in batches of 2: 3 steps, one epoch.
    let pipe = serve(
        SUBSCRIBER,
        &p,
        "complete",
        &["--batch-size", "2", "--epochs", "1"],
    );
    for (ask, expected) in [
        (
            ["--resume", "0", "3"],
            "\"accepted\":0,\"reason\":4,\"at\":[1,0]",
        ),
        (
            ["--resume-sample", "0", "6"],
            "\"accepted\":0,\"reason\":4,\"at\":[1,0]",
        ),
        (
            ["--resume", "4", "0"],
            "\"accepted\":0,\"reason\":4,\"at\":[1,0]",
        ),
        (["--resume", "0", "4"], "\"accepted\":0,\"reason\":2"),
        (
            ["--resume", "0", "2"],
            "\"accepted\":1,\"reason\":0,\"at\":[0,2]",
        ),
    ] {
        let args: Vec<&str> = ask.iter().copied().chain(["--count", "0"]).collect();
        let (ok, out, err) = finish(subscriber(SUBSCRIBER, &p, "complete", &args), LIMIT);
        assert!(ok, "{ask:?}: {err}");
        assert!(out.contains(expected), "{ask:?}: {out}");
    }
    holder.kill().unwrap();
    let _ = holder.wait();
    stop_cleanly(pipe, LIMIT);
    no_shared_memory_left(&p);
}

/// A pipeline killed with SIGKILL mid-epoch: the subscriber waits; a new pipeline comes
/// up, the subscriber asks for its position and receives exactly the rest of the epoch.
#[test]
fn a_restarted_pipeline_continues_where_the_subscriber_is() {
    let p = prefix("restart");
    // 6 batches of 1; read 2, pause 5 s (the pipeline is killed and restarted meanwhile),
    // then ask for (0, 2) and read the remaining 4.
    let reader = subscriber(
        SUBSCRIBER,
        &p,
        "restart",
        &[
            "--count",
            "6",
            "--buffer",
            "1",
            "--stall-after",
            "2",
            "--stall-secs",
            "5",
            "--resume-after",
            "2",
            "--resume-to",
            "0",
            "2",
        ],
    );
    let args = ["--batch-size", "1", "--epochs", "1"];
    let first = serve(SUBSCRIBER, &p, "restart", &args);
    // Kill the first pipeline once the subscriber has its first 2 batches (it then
    // pauses before asking for its position).
    let restart = || serve(SUBSCRIBER, &p, "restart", &args);
    let out = process::kill_and_restart(reader, first, 2, restart, LIMIT);
    assert!(out.contains("\"resume\":[0,2],\"accepted\":1"), "{out}");
    let got = batches(&out);
    let steps: Vec<u64> = got.iter().map(|b| b["step"].as_u64().unwrap()).collect();
    assert_eq!(steps, [0, 1, 2, 3, 4, 5], "{out}");
    let mut keys = sample_keys(&got);
    keys.sort_unstable();
    assert_eq!(keys, (0..KEYFRAMES).map(|k| (0, k)).collect::<Vec<_>>());
    no_shared_memory_left(&p);
}

/// `--metrics-addr` serves Prometheus text; SIGTERM stops the pipeline cleanly (exit 0,
/// shared memory released) even while it waits for subscribers.
#[test]
fn metrics_endpoint_and_sigterm() {
    let p = prefix("metrics");
    let port = 20_000 + (std::process::id() % 20_000) as u16;
    let addr = format!("127.0.0.1:{port}");
    let reader = subscriber(SUBSCRIBER, &p, "metrics", &["--count", "1"]);
    let pipe = serve(
        SUBSCRIBER,
        &p,
        "metrics",
        &["--batch-size", "2", "--metrics-addr", &addr],
    );
    let (ok, _, err) = finish(reader, LIMIT);
    assert!(ok, "{err}");
    // The pipeline now waits for a subscriber for its next batch: scrape it.
    let started = Instant::now();
    let text = loop {
        let attempt = scrape(&addr);
        match attempt {
            Ok(text) if counter(&text, "superflow_batches_total") >= 1 => break text,
            _ if started.elapsed() > Duration::from_secs(60) => {
                panic!("no metrics at {addr}: {attempt:?}")
            }
            _ => std::thread::sleep(Duration::from_millis(100)),
        }
    };
    assert!(text.starts_with("HTTP/1.1 200 OK"), "{text}");
    assert_eq!(
        counter(&text, "superflow_samples_total"),
        2 * counter(&text, "superflow_batches_total")
    );
    for name in [
        "superflow_backpressure_seconds_total",
        "superflow_stage_voxels_seconds_total",
    ] {
        assert!(text.contains(name), "{name} missing:\n{text}");
    }
    let err = stop_cleanly(pipe, LIMIT);
    assert!(err.contains("SIGTERM"), "{err}");
    no_shared_memory_left(&p);
}

/// The trainer started before any pipeline says so and waits; when the pipeline comes
/// up it receives its batches and trains on them.
#[test]
fn the_trainer_waits_for_a_pipeline() {
    let p = prefix("trainer");
    let out = scratch::vacant("service", "waits");
    let trainer = trainer(SUBSCRIBER, &p, "trainer", 2, &out, &[]);
    std::thread::sleep(Duration::from_secs(3));
    let pipe = serve(
        SUBSCRIBER,
        &p,
        "trainer",
        &["--batch-size", "3", "--epochs", "1"],
    );
    let (ok, _, err) = finish(trainer, LIMIT);
    assert!(ok, "{err}");
    assert!(err.contains("no pipeline is publishing"), "{err}");
    assert!(err.contains("a pipeline is publishing again"), "{err}");
    assert!(err.contains("done training"), "{err}");
    let (ok, _, err) = finish(pipe, LIMIT);
    assert!(ok, "{err}");
    no_shared_memory_left(&p);
    let _ = std::fs::remove_dir_all(&out);
}

/// SIGINT while waiting for subscribers: the handler is in place before anything is
/// published, the pipeline exits 0 and releases its shared memory.
#[test]
fn sigint_stops_a_waiting_pipeline_cleanly() {
    let p = prefix("sigint");
    let mut pipe = serve(SUBSCRIBER, &p, "sigint", &["--batch-size", "2"]);
    let (rx, mut log) = wait_until_ready(&mut pipe, LIMIT);
    send_signal(&pipe, "-INT");
    let (ok, _, _) = finish(pipe, LIMIT);
    log.push_str(&drain(&rx, Duration::from_secs(2)));
    assert!(ok, "{log}");
    assert!(log.contains("SIGINT"), "{log}");
    no_shared_memory_left(&p);
}
