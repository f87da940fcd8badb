//! The `superflow` Python package (trainer/python), installed into a virtual environment
//! as a user installs it, against the real `superflow-pipeline`: the same sections as the
//! Rust reader, inside the shared memory; shards over `RANK`/`WORLD_SIZE`; resume; views
//! kept past their batch's release; a killed and restarted pipeline; no pipeline;
//! malformed batches. The
//! scenarios are `trainer/python/tests/check_stream.py`.
//!
//! With torch: `batch.torch()` shares the memory, `TorchIterable` feeds a `DataLoader`
//! one epoch per `iter()`, `superflow.torch.spconv_tensor` gives spconv its voxels,
//! and `torchrun` trains the example (trainer/python/examples/train_torch.py) on two
//! shards with DistributedDataParallel (gloo): the same parameters on both ranks, the loss
//! falling.
//!
//! The environment is `SUPERFLOW_PYTHON` (`.ci/run` makes a fresh one), else one made
//! here under the target directory (`python3 -m venv`, `pip install
//! "./trainer/python[torch,spconv]" safetensors`: PyPI's torch brings its CUDA libraries,
//! ~5 GB; spconv is its CPU build).

#![allow(clippy::unwrap_used, clippy::expect_used)] // tests fail loudly on purpose

use crate::SUBSCRIBER;
use serde_json::Value;
use std::path::{Path, PathBuf};
use std::process::{Command, Stdio};
use std::sync::OnceLock;
use std::time::Duration;
use superflow_recordings::Dialect;
use superflow_tests::process::{
    self, Proc, finish, free_port, no_shared_memory_left, prefix, serve, stop_cleanly,
};
use superflow_tests::{one_camera_rig, rig_drive, two_camera_rig, workspace_root};

/// Keyframes of the sample drive (its plan; `samples.rs` checks it).
const KEYFRAMES: u64 = 6;
const LIMIT: Duration = Duration::from_secs(180);
const SCENARIOS: &str = "trainer/python/tests/check_stream.py";

/// Runs `command` to completion; panics with its output when it fails.
fn run(command: &mut Command) {
    let out = command.output().unwrap();
    assert!(
        out.status.success(),
        "{command:?}: {}\n{}",
        String::from_utf8_lossy(&out.stdout),
        String::from_utf8_lossy(&out.stderr)
    );
}

/// The Python of a virtual environment holding the package (see the module docs).
fn package_python() -> PathBuf {
    static PYTHON: OnceLock<PathBuf> = OnceLock::new();
    PYTHON
        .get_or_init(|| {
            if let Some(python) = std::env::var_os("SUPERFLOW_PYTHON") {
                return python.into();
            }
            let venv = Path::new(env!("CARGO_TARGET_TMPDIR")).join("superflow-venv");
            let python = venv.join("bin").join("python");
            let fresh = !python.exists();
            if fresh {
                run(Command::new("python3").args(["-m", "venv"]).arg(&venv));
            }
            // Reinstalled every run so that the tests see the package's current sources.
            let mut pip = Command::new(&python);
            pip.args(["-m", "pip", "install", "-q", "--disable-pip-version-check"]);
            if fresh {
                pip.args(["./trainer/python[torch,spconv]", "safetensors"]);
            } else {
                pip.args(["--force-reinstall", "--no-deps", "./trainer/python"]);
            }
            run(pip.current_dir(workspace_root()));
            python
        })
        .clone()
}

/// A scenario of `check_stream.py` in the package's environment, outside the repository's
/// Python directory (so `import superflow` is the installed package).
fn scenario(prefix: &str, args: &[&str], env: &[(&str, &str)]) -> Proc {
    let script = workspace_root().join(SCENARIOS);
    Command::new(package_python())
        .arg(script)
        .args(args)
        .env("SUPERFLOW_IOX_PREFIX", prefix)
        .envs(env.iter().copied())
        .current_dir(env!("CARGO_TARGET_TMPDIR"))
        .stdout(Stdio::piped())
        .stderr(Stdio::piped())
        .spawn()
        .map(|c| Proc(Some(c)))
        .unwrap()
}

/// The JSON lines a process printed.
fn json_lines(stdout: &str) -> Vec<Value> {
    stdout
        .lines()
        .map(|l| serde_json::from_str(l).unwrap_or_else(|e| panic!("{e}: {l}")))
        .collect()
}

/// Finishes a scenario that must succeed; its JSON lines.
fn succeeded(proc: Proc) -> Vec<Value> {
    let (ok, out, err) = finish(proc, LIMIT);
    assert!(ok, "{err}\n{out}");
    json_lines(&out)
}

#[test]
fn python_sections_equal_the_rust_reader_and_lie_in_shared_memory() {
    let p = prefix("pyread");
    let python = scenario(&p, &["read", "--run", "pyread", "--count", "2"], &[]);
    let rust = process::subscriber(SUBSCRIBER, &p, "pyread", &["--count", "2", "--sections"]);
    let pipe = serve(
        SUBSCRIBER,
        &p,
        "pyread",
        &["--batch-size", "3", "--epochs", "1", "--subscribers", "2"],
    );
    let py = succeeded(python);
    let (ok, rust_out, err) = finish(rust, LIMIT);
    assert!(ok, "{err}");
    let (ok, _, err) = finish(pipe, LIMIT);
    assert!(ok, "{err}");
    let rs: Vec<Value> = json_lines(&rust_out)
        .into_iter()
        .filter(|v| v.get("sequence").is_some())
        .collect();
    assert_eq!(py.len(), 2);
    for (a, b) in py.iter().zip(&rs) {
        assert_eq!(a["sequence"], b["sequence"]);
        assert_eq!((&a["epoch"], &a["step"]), (&b["epoch"], &b["step"]));
        assert_eq!(a["zero_copy"], true, "arrays lie inside the shared memory");
        let (sa, sb) = (
            a["sections"].as_object().unwrap(),
            b["sections"].as_object().unwrap(),
        );
        assert_eq!(sa.len(), sb.len());
        assert!(sa.len() >= 40, "{} sections", sa.len());
        for (name, section) in sb {
            assert_eq!(&sa[name], section, "section {name}");
        }
        // sample_ids: the index in the epoch and the keyframe of each sample.
        let samples = b["samples"].as_array().unwrap();
        let index: Vec<&Value> = samples.iter().map(|s| &s[1]).collect();
        let keyframe: Vec<&Value> = samples.iter().map(|s| &s[2]).collect();
        assert_eq!(
            a["sample_ids"]
                .as_array()
                .unwrap()
                .iter()
                .collect::<Vec<_>>(),
            index
        );
        assert_eq!(
            a["keyframes"]
                .as_array()
                .unwrap()
                .iter()
                .collect::<Vec<_>>(),
            keyframe
        );
    }
    no_shared_memory_left(&p);
}

#[test]
fn python_shards_from_rank_and_world_size_cover_every_keyframe_once_per_epoch() {
    let p = prefix("pyshard");
    // 6 keyframes, 2 ranks, batches of 1: 3 batches per rank per epoch; 2 epochs.
    let readers: Vec<Proc> = (0..2)
        .map(|r| {
            let rank = r.to_string();
            let env = [("RANK", rank.as_str()), ("WORLD_SIZE", "2")];
            scenario(&p, &["read", "--run", "pyshard", "--count", "6"], &env)
        })
        .collect();
    let pipe = serve(
        SUBSCRIBER,
        &p,
        "pyshard",
        &["--world-size", "2", "--batch-size", "1", "--epochs", "2"],
    );
    let per_rank: Vec<Vec<Value>> = readers.into_iter().map(succeeded).collect();
    let (ok, _, err) = finish(pipe, LIMIT);
    assert!(ok, "{err}");
    let keys: Vec<Vec<(u64, u64)>> = per_rank
        .iter()
        .map(|batches| {
            batches
                .iter()
                .flat_map(|b| {
                    let epoch = b["epoch"].as_u64().unwrap();
                    let frames = b["keyframes"].as_array().unwrap().clone();
                    frames
                        .into_iter()
                        .map(move |k| (epoch, k.as_u64().unwrap()))
                })
                .collect()
        })
        .collect();
    process::assert_shards_cover(&keys, 2, KEYFRAMES);
    no_shared_memory_left(&p);
}

#[test]
fn python_resume_replays_the_following_batches_bit_identically() {
    let p = prefix("pyresume");
    let python = scenario(&p, &["resume", "--run", "pyresume"], &[]);
    let pipe = serve(
        SUBSCRIBER,
        &p,
        "pyresume",
        &["--batch-size", "1", "--epochs", "1"],
    );
    let out = succeeded(python);
    assert_eq!(out[0]["resume"], "identical", "{out:?}");
    assert_eq!(
        out[0]["positions"],
        serde_json::json!([[0, 1], [0, 2], [0, 3]])
    );
    assert_eq!(out[1]["refused"], true, "{out:?}");
    assert!(
        out[1]["message"]
            .as_str()
            .unwrap()
            .contains("the run is complete (1 epochs)"),
        "{out:?}"
    );
    stop_cleanly(pipe, LIMIT);
    no_shared_memory_left(&p);
}

/// Views outlive their batch's release: a tensor and a numpy view of the first batch,
/// kept while 10 later batches come, keep the bytes they had at receive; holding a third
/// batch (`max_held` 2) raises `TooManyBatchesHeld` naming the held ones; after `del` the
/// batches go back to the pipeline and the stream goes on; a view dropped on another
/// thread hands its batch back too.
#[test]
fn python_views_kept_past_release_keep_their_bytes_within_max_held() {
    let p = prefix("pykept");
    let python = scenario(&p, &["kept", "--run", "pykept"], &[]);
    let pipe = serve(
        SUBSCRIBER,
        &p,
        "pykept",
        &["--batch-size", "1", "--epochs", "3"],
    );
    let out = succeeded(python);
    let checks = out[0]["checks"].as_object().unwrap();
    assert!(checks.len() >= 8, "{checks:?}");
    assert!(checks.values().all(|v| v == true), "{out:?}");
    assert_eq!(
        out[0]["held"],
        serde_json::json!([[0, 0], [1, 4]]),
        "{out:?}"
    );
    // 1 + 10 + 3 batches in order: nothing lost or repeated around the refused receive.
    let positions: Vec<(u64, u64)> = out[0]["positions"]
        .as_array()
        .unwrap()
        .iter()
        .map(|p| (p[0].as_u64().unwrap(), p[1].as_u64().unwrap()))
        .collect();
    let expected: Vec<(u64, u64)> = (1..14).map(|i| (i / KEYFRAMES, i % KEYFRAMES)).collect();
    assert_eq!(positions, expected);
    stop_cleanly(pipe, LIMIT);
    no_shared_memory_left(&p);
}

/// `--epochs 2`, batches of 4 (2 per epoch: 4 and 2 keyframes): `stream.epoch()` gives
/// every keyframe once per epoch and stops, twice; then the stream has ended. Rewound,
/// `for batch in stream` (no `timeout_s`) stops by itself after epoch 1, and
/// `TorchIterable` in a `DataLoader` gives the same batches, one epoch per `iter()`,
/// nothing past the last. The pipeline then ends by itself.
#[test]
fn python_epochs_end_and_the_stream_stops_after_the_last() {
    let p = prefix("pyepochs");
    let python = scenario(&p, &["epochs", "--run", "pyepochs"], &[]);
    let pipe = serve(
        SUBSCRIBER,
        &p,
        "pyepochs",
        &["--batch-size", "4", "--epochs", "2"],
    );
    let out = succeeded(python);
    let (ok, _, err) = finish(pipe, LIMIT);
    assert!(ok, "{err}");
    let got = &out[0];
    assert_eq!(
        (&got["len"], &got["loader_len"]),
        (&2.into(), &2.into()),
        "{got}"
    );
    let epochs = got["epochs"].as_array().unwrap();
    let mut whole = Vec::new();
    for (e, batches) in epochs.iter().enumerate() {
        let batches = batches.as_array().unwrap();
        assert_eq!(batches.len(), 2, "{got}");
        let mut keyframes: Vec<u64> = Vec::new();
        for (step, b) in batches.iter().enumerate() {
            assert_eq!(
                (b[0].as_u64(), b[1].as_u64()),
                (Some(e as u64), Some(step as u64))
            );
            keyframes.extend(b[2].as_array().unwrap().iter().map(|k| k.as_u64().unwrap()));
            whole.push(b.clone());
        }
        keyframes.sort_unstable();
        assert_eq!(keyframes, (0..KEYFRAMES).collect::<Vec<_>>(), "epoch {e}");
    }
    assert_eq!(got["ended"], true, "{got}");
    assert_eq!(got["after_end"], serde_json::json!([]), "{got}");
    assert_eq!(got["whole"], serde_json::json!(whole), "{got}");
    let loaded: Vec<Value> = whole.iter().map(|b| b[2].clone()).collect();
    assert_eq!(
        got["loaded"],
        serde_json::json!([&loaded[..2], &loaded[2..], []]),
        "{got}"
    );
    assert_eq!(got["continued"], serde_json::json!(&loaded[..2]), "{got}");
    no_shared_memory_left(&p);
}

/// `superflow.torch.spconv_tensor` with the CPU `spconv` package (the `[spconv]` extra),
/// on the stream of a pipeline whose recipe builds no kernel maps (`kernel_maps =
/// "none"`, what a spconv user sets: spconv finds its own): the batch has level 0's
/// voxels and no map; the indices are its level-0 coordinates shifted to be
/// non-negative, in the batch's row order, `batch_size` the clouds, the features the
/// batch's own memory; a `SubMConv3d` forward keeps the rows. Beside it,
/// `examples/train_spconv.py` on the same batch: the spconv MinkUNet's forward pass and
/// the SuperFlow losses, then it stops, saying why (spconv's CPU build has no backward).
#[test]
fn python_spconv_tensor_holds_the_batch_voxels_and_runs_a_submanifold_convolution() {
    let p = prefix("pyspconv");
    let dir = Path::new(env!("CARGO_TARGET_TMPDIR")).join("pyspconv");
    std::fs::create_dir_all(&dir).unwrap();
    let config = dir.join("no-maps.toml");
    std::fs::write(&config, "[sample]\nkernel_maps = \"none\"\n").unwrap();
    let python = scenario(&p, &["spconv", "--run", "pyspconv"], &[]);
    let example = superflow_tests::process::spawn(
        Command::new(package_python())
            .arg(workspace_root().join("trainer/python/examples/train_spconv.py"))
            .args(["--run", "pyspconv", "--timeout", "120"])
            .env("SUPERFLOW_IOX_PREFIX", &p)
            .env("OMP_NUM_THREADS", "1")
            .current_dir(env!("CARGO_TARGET_TMPDIR"))
            .stdout(Stdio::piped())
            .stderr(Stdio::piped()),
    );
    let pipe = serve(
        SUBSCRIBER,
        &p,
        "pyspconv",
        &[
            "--config",
            config.to_str().unwrap(),
            "--batch-size",
            "2",
            "--epochs",
            "1",
            "--subscribers",
            "2",
        ],
    );
    let out = succeeded(python);
    let checks = out[0]["checks"].as_object().unwrap();
    assert_eq!(checks.len(), 9, "{out:?}");
    assert!(checks.values().all(|v| v == true), "{out:?}");
    assert!(out[0]["voxels"].as_u64().unwrap() > 1000, "{out:?}");
    let trained = succeeded(example);
    assert_eq!(trained.len(), 1, "{trained:?}");
    for term in ["total", "l_sc", "l_tc", "l_d2s"] {
        let loss = trained[0][term].as_f64().unwrap();
        assert!(loss.is_finite() && loss > 0.0, "{term}: {trained:?}");
    }
    assert!(
        trained[0]["stopped"]
            .as_str()
            .unwrap()
            .contains("forward passes only"),
        "{trained:?}"
    );
    stop_cleanly(pipe, LIMIT);
    no_shared_memory_left(&p);
}

/// 6 keyframes dealt to 4 ranks in batches of 1: ranks 0 and 1 get 2 batches an epoch,
/// ranks 2 and 3 get 1. `len(stream.epoch())` says so; `stream.epoch(drop_uneven=True)`
/// gives every rank 1 batch an epoch (the ranks stay in step), and every rank's stream
/// ends after epoch 1.
#[test]
fn python_uneven_shards_stay_in_step_with_drop_uneven() {
    let p = prefix("pyuneven");
    let readers: Vec<Proc> = (0..4)
        .map(|r| {
            let rank = r.to_string();
            let env = [("RANK", rank.as_str()), ("WORLD_SIZE", "4")];
            scenario(&p, &["uneven", "--run", "pyuneven"], &env)
        })
        .collect();
    let pipe = serve(
        SUBSCRIBER,
        &p,
        "pyuneven",
        &["--world-size", "4", "--batch-size", "1", "--epochs", "2"],
    );
    for (rank, reader) in readers.into_iter().enumerate() {
        let out = succeeded(reader);
        let got = &out[0];
        let steps = if rank < 2 { 2 } else { 1 };
        assert_eq!(got["rank"], rank, "{got}");
        assert_eq!(
            (&got["steps"], &got["min_steps"]),
            (&steps.into(), &1.into())
        );
        assert_eq!(got["lengths"], serde_json::json!([steps, 1]), "{got}");
        assert_eq!(
            got["epochs"],
            serde_json::json!([[[0, 0]], [[1, 0]]]),
            "{got}"
        );
    }
    let (ok, _, err) = finish(pipe, LIMIT);
    assert!(ok, "{err}");
    no_shared_memory_left(&p);
}

/// The drives of other rigs beside the sample drive: a 2-camera ROS 2 car and a 1-camera
/// Foxglove one.
fn other_rigs() -> [String; 2] {
    [
        rig_drive(Dialect::Ros2, &two_camera_rig()).unwrap(),
        rig_drive(Dialect::Foxglove, &one_camera_rig()).unwrap(),
    ]
    .map(|p| p.display().to_string())
}

/// An epoch of three rigs (6, 2 and 1 cameras) from Python: every sample carries its own
/// cameras as numpy and torch views, spconv takes the batch, nothing is an empty image.
#[test]
fn python_reads_an_epoch_of_mixed_rigs() {
    let p = prefix("pyfleet");
    let [two, one] = other_rigs();
    let reader = scenario(&p, &["fleet", "--run", "pyfleet"], &[]);
    let pipe = serve(
        SUBSCRIBER,
        &p,
        "pyfleet",
        &["--mcap", &two, &one, "--batch-size", "4", "--epochs", "1"],
    );
    let out = succeeded(reader);
    let got = &out[0];
    assert_eq!(got["ok"], true, "{got}");
    assert_eq!(got["frames"], 3);
    let samples = got["samples"].as_array().unwrap();
    assert_eq!(samples.len() as u64, 3 * KEYFRAMES, "{got}");
    for s in samples {
        let expected = [3, 2, 1][s["drive"].as_u64().unwrap() as usize];
        assert_eq!(s["cameras"], expected, "{s}");
    }
    let (ok, _, err) = finish(pipe, LIMIT);
    assert!(ok, "{err}");
    no_shared_memory_left(&p);
}

/// torchrun's habit after a preemption: the job comes back with another number of GPUs.
/// Two ranks read 2 batches each and save `stream.state_dict()`; three ranks of a new job
/// (a pipeline of 3 shards, started afresh) `load_state_dict` it and read the rest of
/// the epoch: every keyframe once, none skipped, none repeated.
#[test]
fn python_state_dict_resumes_a_job_on_another_number_of_ranks() {
    let [two, _] = other_rigs();
    let mcap = ["--mcap", two.as_str()];
    let shards =
        |world: &'static str| ["--world-size", world, "--batch-size", "1", "--epochs", "1"];
    let ranks = |p: &str, world: usize, args: &[&str]| -> Vec<Proc> {
        (0..world)
            .map(|r| {
                let (rank, size) = (r.to_string(), world.to_string());
                let env = [("RANK", rank.as_str()), ("WORLD_SIZE", size.as_str())];
                let mut all = vec!["elastic", "--run", "pyelastic"];
                all.extend(args);
                scenario(p, &all, &env)
            })
            .collect()
    };
    let p = prefix("pyelastic1");
    let first = ranks(&p, 2, &["--count", "2"]);
    let pipe = serve(
        SUBSCRIBER,
        &p,
        "pyelastic",
        &[&mcap[..], &shards("2")].concat(),
    );
    let mut seen: Vec<Value> = Vec::new();
    let mut states = Vec::new();
    for reader in first {
        let out = succeeded(reader);
        seen.extend(out[0]["samples"].as_array().unwrap().iter().cloned());
        states.push(out[0]["state"].clone());
    }
    stop_cleanly(pipe, LIMIT);
    no_shared_memory_left(&p);
    // Ranks step together: they agree on where the job stands.
    assert_eq!(states[0], states[1]);
    assert_eq!(states[0]["samples"], 4, "{}", states[0]);
    let state = states[0].to_string();
    let p = prefix("pyelastic2");
    let second = ranks(&p, 3, &["--count", "0", "--state", &state]);
    let pipe = serve(
        SUBSCRIBER,
        &p,
        "pyelastic",
        &[&mcap[..], &shards("3")].concat(),
    );
    for reader in second {
        let out = succeeded(reader);
        seen.extend(out[0]["samples"].as_array().unwrap().iter().cloned());
    }
    let (ok, _, err) = finish(pipe, LIMIT);
    assert!(ok, "{err}");
    no_shared_memory_left(&p);
    let mut positions: Vec<u64> = seen.iter().map(|s| s[0].as_u64().unwrap()).collect();
    positions.sort_unstable();
    assert_eq!(
        positions,
        (0..2 * KEYFRAMES).collect::<Vec<_>>(),
        "{seen:?}"
    );
    let mut keyframes: Vec<(u64, u64)> = seen
        .iter()
        .map(|s| (s[1].as_u64().unwrap(), s[2].as_u64().unwrap()))
        .collect();
    keyframes.sort_unstable();
    keyframes.dedup();
    assert_eq!(keyframes.len() as u64, 2 * KEYFRAMES, "{seen:?}");
}

/// SIGKILL the pipeline after 2 batches: the Python iterator waits, and when a new
/// pipeline comes up it asks for the position after the last batch it got, so the steps
/// go on without a gap or a repeat and every keyframe comes once. A view of the second
/// batch, kept through the kill, stays readable with its bytes.
#[test]
fn python_iteration_continues_across_a_restarted_pipeline() {
    let p = prefix("pyrestart");
    let reader = scenario(
        &p,
        &[
            "read",
            "--run",
            "pyrestart",
            "--count",
            "6",
            "--timeout",
            "120",
            "--keep",
        ],
        &[],
    );
    let args = ["--batch-size", "1", "--epochs", "1"];
    let first = serve(SUBSCRIBER, &p, "pyrestart", &args);
    let restart = || {
        std::thread::sleep(Duration::from_secs(2));
        serve(SUBSCRIBER, &p, "pyrestart", &args)
    };
    let lines = process::kill_and_restart(reader, first, 2, restart, LIMIT);
    let mut got = json_lines(&lines);
    let kept = got.pop().unwrap();
    assert_eq!(kept["kept_equal"], true, "{lines}");
    assert_eq!(kept["kept_returned"], false, "{lines}");
    let steps: Vec<u64> = got.iter().map(|b| b["step"].as_u64().unwrap()).collect();
    assert_eq!(steps, [0, 1, 2, 3, 4, 5], "{lines}");
    let mut keyframes: Vec<u64> = got
        .iter()
        .flat_map(|b| b["keyframes"].as_array().unwrap().clone())
        .map(|k| k.as_u64().unwrap())
        .collect();
    keyframes.sort_unstable();
    assert_eq!(keyframes, (0..KEYFRAMES).collect::<Vec<_>>());
    no_shared_memory_left(&p);
}

#[test]
fn python_without_a_pipeline_times_out_naming_run_and_service() {
    let p = prefix("pynone");
    let out = succeeded(scenario(
        &p,
        &["timeout", "--run", "pynone", "--timeout", "1"],
        &[],
    ));
    assert_eq!(out[0]["timeout"], true);
    assert_eq!(out[0]["run"], "pynone");
    assert_eq!(out[0]["service"], "superflow/pynone/batches");
    assert!(
        out[0]["message"]
            .as_str()
            .unwrap()
            .contains("no pipeline publishes on it"),
        "{out:?}"
    );
    no_shared_memory_left(&p);
}

#[test]
fn python_malformed_batches_raise_typed_errors_and_the_stream_goes_on() {
    let p = prefix("pybad");
    let out = succeeded(scenario(&p, &["malformed", "--run", "pybad"], &[]));
    assert_eq!(out[0]["version 1"], "FormatVersionMismatch", "{out:?}");
    assert_eq!(out[0]["overlapping sections"], "MalformedBatch", "{out:?}");
    assert_eq!(
        out[0]["dtype against the table"], "MalformedBatch",
        "{out:?}"
    );
    assert_eq!(out[0]["unknown section"], "MalformedBatch", "{out:?}");
    no_shared_memory_left(&p);
}

#[test]
fn python_torch_tensors_share_the_shared_memory_and_feed_a_data_loader() {
    let p = prefix("pytorch");
    let python = scenario(&p, &["torch_views", "--run", "pytorch"], &[]);
    let pipe = serve(
        SUBSCRIBER,
        &p,
        "pytorch",
        &["--batch-size", "1", "--epochs", "1"],
    );
    let out = succeeded(python);
    assert_eq!(out[0]["shared"], true, "{out:?}");
    assert_eq!(out[0]["inside"], true, "{out:?}");
    assert_eq!(out[0]["equal"], true, "{out:?}");
    assert!(out[0]["sections"].as_u64().unwrap() >= 40, "{out:?}");
    assert_eq!(out[0]["loader_sample_ids"], serde_json::json!([1, 2, 3]));
    assert_eq!(out[0]["loader_types"], serde_json::json!(["Tensor"]));
    stop_cleanly(pipe, LIMIT);
    no_shared_memory_left(&p);
}

/// `torchrun --nproc-per-node 2` of the example on a pipeline with 2 shards and 2
/// epochs, without a step count: each rank trains on its own keyframes, DDP keeps the
/// parameters equal, the loss falls, and both ranks end together when the stream ends
/// (after 2 epochs of 3 batches), as does the pipeline.
#[test]
fn torchrun_trains_the_example_with_ddp_on_two_shards() {
    let p = prefix("pyddp");
    let example = workspace_root().join("trainer/python/examples/train_torch.py");
    let trainer = superflow_tests::process::spawn(
        Command::new(package_python())
            .args([
                "-m",
                "torch.distributed.run",
                "--standalone",
                "--nproc-per-node",
                "2",
                "--",
            ])
            .arg(example)
            .args(["--run", "pyddp", "--timeout", "120"])
            .env("SUPERFLOW_IOX_PREFIX", &p)
            .env("OMP_NUM_THREADS", "1")
            .current_dir(env!("CARGO_TARGET_TMPDIR"))
            .stdout(Stdio::piped())
            .stderr(Stdio::piped()),
    );
    let pipe = serve(
        SUBSCRIBER,
        &p,
        "pyddp",
        &["--world-size", "2", "--batch-size", "1", "--epochs", "2"],
    );
    let out = succeeded(trainer);
    let (ok, _, err) = finish(pipe, LIMIT);
    assert!(ok, "{err}");
    let (ends, steps): (Vec<&Value>, Vec<&Value>) =
        out.iter().partition(|l| l.get("params_hash").is_some());
    assert_eq!(ends.len(), 2, "{out:?}");
    assert_eq!(ends[0]["params_hash"], ends[1]["params_hash"], "{ends:?}");
    for end in &ends {
        assert_eq!(
            (&end["steps"], &end["stream_ended"]),
            (&6.into(), &true.into())
        );
    }
    assert_eq!(steps.len(), 12, "{out:?}");
    // Every keyframe once per epoch over the two ranks (3 steps of 1 sample an epoch each).
    for epoch in 0..2u64 {
        let mut seen: Vec<u64> = steps
            .iter()
            .filter(|l| l["epoch"] == epoch)
            .flat_map(|l| l["sample_ids"].as_array().unwrap().clone())
            .map(|k| k.as_u64().unwrap())
            .collect();
        seen.sort_unstable();
        assert_eq!(seen, (0..KEYFRAMES).collect::<Vec<_>>(), "epoch {epoch}");
    }
    let mean_loss = |range: std::ops::Range<u64>| {
        let losses: Vec<f64> = steps
            .iter()
            .filter(|l| range.contains(&l["step"].as_u64().unwrap()))
            .map(|l| l["total"].as_f64().unwrap())
            .collect();
        losses.iter().sum::<f64>() / losses.len() as f64
    };
    let (first, last) = (mean_loss(0..2), mean_loss(4..6));
    assert!(last < first, "loss {first} -> {last}: {out:?}");
    no_shared_memory_left(&p);
}

/// A pipeline SIGKILLed mid-stream and not restarted: the iterator raises
/// `PipelineTimeout` after `timeout_s`, saying no pipeline publishes any more (the dead
/// pipeline's node was cleaned up on the way).
#[test]
fn python_iteration_times_out_when_the_pipeline_dies_for_good() {
    let p = prefix("pydead");
    // 6 batches in the epoch; after the kill at most the queued ones (2) still come.
    let args = ["read", "--run", "pydead", "--count", "6", "--timeout", "3"];
    let mut reader = scenario(&p, &args, &[]);
    let rx = superflow_tests::process::lines_of(reader.stdout.take().unwrap());
    let mut pipe = serve(
        SUBSCRIBER,
        &p,
        "pydead",
        &["--batch-size", "1", "--epochs", "1"],
    );
    for _ in 0..2 {
        rx.recv_timeout(LIMIT).expect("batches before the kill");
    }
    pipe.kill().unwrap(); // SIGKILL
    let _ = pipe.wait();
    let (ok, _, err) = finish(reader, LIMIT);
    assert!(!ok, "the reader went on without a pipeline: {err}");
    assert!(err.contains("PipelineTimeout"), "{err}");
    assert!(err.contains("no pipeline publishes on it"), "{err}");
    assert!(err.contains("superflow/pydead/batches"), "{err}");
}

/// The PyTorch habit of normalising and augmenting in place (`images.sub_`,
/// `points.mul_`, `x[:, :3] -= c`, a flip by `neg_`, numpy `*=`): each works on the
/// batch's own tensors, copies only the pages it writes (the batch is a copy-on-write
/// mapping of the shared memory), and another reader of the same batch sees the
/// pipeline's bytes, unchanged.
#[test]
fn python_in_place_ops_on_batch_tensors_change_only_this_process() {
    let p = prefix("pyinplace");
    let python = scenario(&p, &["in_place", "--run", "pyinplace"], &[]);
    let rust = process::subscriber(SUBSCRIBER, &p, "pyinplace", &["--count", "2", "--sections"]);
    let pipe = serve(
        SUBSCRIBER,
        &p,
        "pyinplace",
        &["--batch-size", "2", "--epochs", "1", "--subscribers", "2"],
    );
    let py = succeeded(python);
    let got = &py[0];
    for (check, ok) in got["checks"].as_object().unwrap() {
        assert_eq!(ok, true, "{check}: {got}");
    }
    assert_eq!(got["returned"], true, "{got}");
    let (ok, rust_out, err) = finish(rust, LIMIT);
    assert!(ok, "{err}");
    let theirs = json_lines(&rust_out)
        .into_iter()
        .find(|v| v["sequence"] == got["sequence"])
        .expect("the Rust reader got the same batch");
    for (name, section) in theirs["sections"].as_object().unwrap() {
        assert_eq!(got["pristine"][name], section["checksum"], "section {name}");
    }
    let (ok, _, err) = finish(pipe, LIMIT);
    assert!(ok, "{err}");
    no_shared_memory_left(&p);
}

/// `DataLoader(TorchIterable(stream), batch_size=None, num_workers=N)`: 2 and 4 forked
/// workers raise `WorkersUnsupported` in the training process, spawn and forkserver
/// `StreamNotPicklable`, each saying to use `num_workers=0`; the same stream then gives
/// the whole epoch with `num_workers=0` and `pin_memory=True`, every batch once.
#[test]
fn python_data_loader_workers_get_a_clear_error_and_lose_nothing() {
    let p = prefix("pyworkers");
    let python = scenario(&p, &["workers", "--run", "pyworkers"], &[]);
    let pipe = serve(
        SUBSCRIBER,
        &p,
        "pyworkers",
        &["--batch-size", "1", "--epochs", "1"],
    );
    let out = succeeded(python);
    let got = &out[0];
    let unsupported = serde_json::json!(["WorkersUnsupported", true]);
    let unpicklable = serde_json::json!(["StreamNotPicklable", true]);
    assert_eq!(got["outcomes"]["2 fork"], unsupported, "{got}");
    assert_eq!(got["outcomes"]["4 fork"], unsupported, "{got}");
    assert_eq!(got["outcomes"]["2 spawn"], unpicklable, "{got}");
    assert_eq!(got["outcomes"]["2 forkserver"], unpicklable, "{got}");
    assert_eq!(
        got["outcomes"]["pickle"],
        serde_json::json!(["StreamNotPicklable", true, true])
    );
    assert_eq!(got["len"], KEYFRAMES, "{got}");
    assert_eq!(got["batches"], KEYFRAMES, "{got}");
    assert_eq!(
        got["samples"],
        serde_json::json!((0..KEYFRAMES).collect::<Vec<_>>())
    );
    let (ok, _, err) = finish(pipe, LIMIT);
    assert!(ok, "{err}");
    no_shared_memory_left(&p);
}

/// The ranks of `torchrun --nnodes 2 --nproc-per-node 2`, simulated on one machine: each
/// node runs its own pipeline (`--host-rank h --host-count 2`, its own iceoryx2 prefix),
/// each rank has torchrun's environment (`RANK`, `LOCAL_RANK`, `WORLD_SIZE`,
/// `LOCAL_WORLD_SIZE`, `GROUP_RANK`). Returns every rank's JSON line and whether the
/// pipelines ended well. `host_config`: a configuration file per host, if any.
fn two_node_job(test: &str, host_config: [Option<&str>; 2]) -> Vec<Value> {
    let port = free_port();
    let prefixes = [prefix(&format!("{test}0")), prefix(&format!("{test}1"))];
    let readers: Vec<Proc> = (0..4usize)
        .map(|r| {
            let (rank, local, node) = (r.to_string(), (r % 2).to_string(), (r / 2).to_string());
            let env = [
                ("RANK", rank.as_str()),
                ("LOCAL_RANK", local.as_str()),
                ("GROUP_RANK", node.as_str()),
                ("WORLD_SIZE", "4"),
                ("LOCAL_WORLD_SIZE", "2"),
                ("MASTER_ADDR", "127.0.0.1"),
                ("MASTER_PORT", port.as_str()),
            ];
            scenario(&prefixes[r / 2], &["hosts", "--run", test], &env)
        })
        .collect();
    let pipes: Vec<Proc> = (0..2usize)
        .map(|h| {
            let host = h.to_string();
            let mut args = vec![
                "--world-size",
                "2",
                "--host-rank",
                host.as_str(),
                "--host-count",
                "2",
                "--batch-size",
                "1",
                "--epochs",
                "1",
            ];
            if let Some(config) = host_config[h] {
                args.extend(["--config", config]);
            }
            serve(SUBSCRIBER, &prefixes[h], test, &args)
        })
        .collect();
    let out: Vec<Value> = readers
        .into_iter()
        .map(|r| succeeded(r).remove(0))
        .collect();
    for pipe in pipes {
        stop_cleanly(pipe, LIMIT);
    }
    for p in &prefixes {
        no_shared_memory_left(p);
    }
    out
}

/// Multi-node torchrun with one pipeline per node: a rank finds its node's stream by
/// `LOCAL_RANK` (not the global `RANK`, which names no stream of its node's pipeline),
/// every rank is checked to be served the same plan, and the four ranks of the two
/// nodes cover the epoch's keyframes once.
#[test]
fn python_multi_node_torchrun_ranks_find_their_node_stream() {
    let out = two_node_job("pynodes", [None, None]);
    let mut samples: Vec<u64> = Vec::new();
    for (r, got) in out.iter().enumerate() {
        assert_eq!(got["rank"], r, "{got}");
        assert_eq!(
            got["service"],
            format!("superflow/pynodes/rank/{}", r % 2),
            "{got}"
        );
        assert_eq!(got["source"], "LOCAL_RANK/LOCAL_WORLD_SIZE", "{got}");
        assert_eq!(got["plan"], out[0]["plan"], "{got}");
        assert_eq!(got["plan"]["host_count"], 2, "{got}");
        assert_eq!(got["plan"]["keyframes"], KEYFRAMES, "{got}");
        samples.extend(
            got["samples"]
                .as_array()
                .unwrap()
                .iter()
                .map(|s| s[1].as_u64().unwrap()),
        );
    }
    samples.sort_unstable();
    assert_eq!(samples, (0..KEYFRAMES).collect::<Vec<_>>(), "{out:?}");
}

/// Two nodes whose pipelines were given other seeds: every rank's plan check fails,
/// naming the seed.
#[test]
fn python_multi_node_plans_that_differ_are_refused() {
    let dir = Path::new(env!("CARGO_TARGET_TMPDIR")).join("pyplans");
    std::fs::create_dir_all(&dir).unwrap();
    let config = dir.join("seed7.toml");
    std::fs::write(&config, "[sample]\nseed = 7\n").unwrap();
    let out = two_node_job("pyplans", [None, Some(config.to_str().unwrap())]);
    for got in &out {
        let message = got["mismatch"].as_str().unwrap_or_else(|| panic!("{got}"));
        assert!(message.contains("seed 7 vs 0"), "{message}");
    }
}

/// Both drives replaced on disk by truncated copies while the service runs, as a
/// dataset re-sync gone wrong does: later samples fail, and the batches they leave empty
/// are still announced (`batch.lost`, no sections, `{}` from `torch()`), so every epoch
/// yields `len(stream.epoch())` batches and the stream ends.
#[test]
fn python_epochs_with_lost_batches_still_end() {
    let dir = Path::new(env!("CARGO_TARGET_TMPDIR")).join("pylost");
    let _ = std::fs::remove_dir_all(&dir);
    std::fs::create_dir_all(&dir).unwrap();
    let (drives, config) = superflow_tests::replaceable_drives(&dir).unwrap();
    let signal = dir.join("replaced");
    let p = prefix("pylost");
    let mut reader = scenario(
        &p,
        &[
            "lost",
            "--run",
            "pylost",
            "--signal",
            signal.to_str().unwrap(),
        ],
        &[],
    );
    let rx = process::lines_of(reader.stdout.take().unwrap());
    let mcap: Vec<&str> = drives.iter().map(|d| d.to_str().unwrap()).collect();
    let pipe = process::pipeline(
        SUBSCRIBER,
        mcap[0],
        &p,
        "pylost",
        &[
            "--mcap",
            mcap[1],
            "--config",
            config.to_str().unwrap(),
            "--batch-size",
            "1",
            "--epochs",
            "2",
        ],
    );
    let paused = rx.recv_timeout(LIMIT).expect("the reader's first line");
    assert!(paused.contains("paused"), "{paused}");
    superflow_tests::truncate_drives(&drives).unwrap();
    std::fs::write(&signal, b"").unwrap();
    let (ok, _, err) = finish(reader, LIMIT);
    assert!(ok, "{err}");
    let last = rx.recv_timeout(Duration::from_secs(5)).unwrap();
    let got: Value = serde_json::from_str(&last).unwrap();
    let length = got["len"].as_u64().unwrap();
    assert_eq!(length, 2 * KEYFRAMES, "{got}");
    assert_eq!(got["ended"], true, "{got}");
    let epochs = got["epochs"].as_array().unwrap();
    assert_eq!(epochs.len(), 2, "{got}");
    let mut lost = 0;
    for epoch in epochs {
        let steps: Vec<u64> = epoch
            .as_array()
            .unwrap()
            .iter()
            .map(|b| b["step"].as_u64().unwrap())
            .collect();
        assert_eq!(steps, (0..length).collect::<Vec<_>>(), "{got}");
        for b in epoch.as_array().unwrap() {
            if b["lost"] == true {
                lost += 1;
                assert_eq!(
                    (&b["samples"], &b["tensors"]),
                    (&0.into(), &0.into()),
                    "{b}"
                );
            } else {
                assert_eq!(b["samples"], 1, "{b}");
            }
        }
    }
    // Samples whose chunks the pipeline still holds decoded, or that lie in the first
    // half of a file, may still build: some batches are lost, which ones varies.
    assert!(lost > 0, "{got}");
    let (ok, _, err) = finish(pipe, LIMIT);
    assert!(ok, "{err}");
    assert!(err.contains("lost"), "{err}");
    no_shared_memory_left(&p);
}

/// `stream.close()` while views of its batch are alive: the views keep their bytes and
/// the pipeline stops counting the subscriber at once, so another subscriber of the
/// same broadcast stream reads the whole epoch while the first process still holds its
/// views.
#[test]
fn python_close_with_live_views_leaves_the_publisher_at_once() {
    let p = prefix("pyclose");
    let holder = scenario(
        &p,
        &["close_live", "--run", "pyclose", "--keep", "--count", "40"],
        &[],
    );
    let other = scenario(&p, &["close_live", "--run", "pyclose"], &[]);
    let pipe = serve(
        SUBSCRIBER,
        &p,
        "pyclose",
        &["--batch-size", "1", "--epochs", "1", "--subscribers", "2"],
    );
    let out = succeeded(other);
    assert_eq!(
        out[0]["steps"],
        serde_json::json!((0..KEYFRAMES).collect::<Vec<_>>())
    );
    let mut holder = holder;
    assert!(
        holder.try_wait().unwrap().is_none(),
        "the other subscriber finished only once the holder was gone"
    );
    let out = succeeded(holder);
    for (check, ok) in out[0]["checks"].as_object().unwrap() {
        assert_eq!(ok, true, "{check}: {}", out[0]);
    }
    let (ok, _, err) = finish(pipe, LIMIT);
    assert!(ok, "{err}");
    no_shared_memory_left(&p);
}

/// A publisher without a schedule service (the stream's own, as in the malformed test):
/// `len(stream.epoch())` and `stream.epoch()` raise `ScheduleUnavailable` within seconds
/// instead of waiting forever; the batch itself is still read.
#[test]
fn python_epochs_without_a_schedule_service_raise_a_typed_error() {
    let p = prefix("pynosched");
    let out = succeeded(scenario(&p, &["no_schedule", "--run", "pynosched"], &[]));
    let got = &out[0];
    for what in ["len", "epoch"] {
        assert_eq!(got[what]["error"], "ScheduleUnavailable", "{got}");
        assert_eq!(got[what]["named"], true, "{got}");
        let seconds = got[what]["seconds"].as_f64().unwrap();
        assert!((4.0..15.0).contains(&seconds), "{got}");
    }
    assert_eq!(
        got["batch"],
        serde_json::json!([0.0, 1.0, 2.0, 3.0, 4.0, 5.0, 6.0, 7.0])
    );
    no_shared_memory_left(&p);
}

/// A final checkpoint resumed: at the end of the last epoch (by step, by epoch, by a
/// `state_dict`) the pipeline says the run is complete (`RunComplete`), and the last
/// batch itself can still be asked for.
#[test]
fn python_resume_past_the_end_says_the_run_is_complete() {
    let p = prefix("pypastend");
    let python = scenario(&p, &["past_end", "--run", "pypastend"], &[]);
    let pipe = serve(
        SUBSCRIBER,
        &p,
        "pypastend",
        &["--batch-size", "1", "--epochs", "1"],
    );
    let out = succeeded(python);
    let got = &out[0];
    assert_eq!(
        got["steps"],
        serde_json::json!((0..KEYFRAMES).collect::<Vec<_>>())
    );
    for what in ["step", "epoch", "state"] {
        assert_eq!(got[what]["epochs"], 1, "{what}: {got}");
        let message = got[what]["message"].as_str().unwrap();
        assert!(
            message.contains("the run is complete (1 epochs)"),
            "{message}"
        );
    }
    assert_eq!(got["last again"], KEYFRAMES - 1, "{got}");
    stop_cleanly(pipe, LIMIT);
    no_shared_memory_left(&p);
}
