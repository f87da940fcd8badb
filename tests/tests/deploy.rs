//! The deployment files of `deploy/` are checked with the tools that check them for a
//! living — the Kubernetes manifest against the API schemas (`kubernetes-validate`), the
//! systemd units with `systemd-analyze verify`, the scripts with `bash -n` and
//! `shellcheck`, the Containerfile with `hadolint` — and for what matters to superflow:
//! every flag they pass exists in the binaries' `--help`, the pipeline and the trainers
//! share `/dev/shm` and iceoryx2's root path, the host ranks are wired, restarts resume,
//! and `/dev/shm` is sized for the batches.
//!
//! The tools come from `pip install -r tests/python/requirements.txt`; a missing one
//! fails the test (it does not pass silently). `systemd-analyze` is the system's
//! (`apt-get install systemd`, which `.ci/run` does where it is missing).

#![allow(clippy::unwrap_used, clippy::expect_used)] // tests fail loudly on purpose

use serde_json::Value;
use std::collections::{BTreeMap, BTreeSet};
use std::path::{Path, PathBuf};
use std::process::Command;
use superflow_tests::{pipeline_binary, workspace_binary, workspace_root};

/// Kubernetes version the manifest is validated against: native sidecars and the
/// completion-index annotation are GA there.
const KUBERNETES_VERSION: &str = "1.33.0";
/// Bytes of a batch of 4 samples in the loaned slice, rounded up (the pipeline's
/// `initial_max_slice_len`).
const BATCH_MIB: u64 = 32;
/// Batches one shard stream may hold in shared memory with one subscriber: subscriber
/// queue (4) + borrowed (2) (`schemas::service::qos`) + the publisher's loans (2,
/// iceoryx2's default `publisher_max_loaned_samples`).
const BATCHES_PER_STREAM: u64 = 4 + 2 + 2;

const INSTALL: &str = "pip install -r tests/python/requirements.txt";

fn deploy(path: &str) -> PathBuf {
    workspace_root().join("deploy").join(path)
}

fn read(path: &Path) -> String {
    std::fs::read_to_string(path).unwrap_or_else(|e| panic!("reading {}: {e}", path.display()))
}

/// Output (stdout + stderr) and success of `command`.
fn output(command: &mut Command) -> (bool, String) {
    let out = command
        .current_dir(workspace_root())
        .output()
        .unwrap_or_else(|e| panic!("running {command:?}: {e}"));
    let text = format!(
        "{}{}",
        String::from_utf8_lossy(&out.stdout),
        String::from_utf8_lossy(&out.stderr)
    );
    (out.status.success(), text)
}

/// A console script of a package of tests/python/requirements.txt: in python3's scripts
/// directories (system or user scheme), else on PATH. Missing: the test fails and says
/// how to install it.
fn python_tool(name: &str) -> PathBuf {
    let script = "import os, sysconfig\n\
                  print(sysconfig.get_path('scripts'))\n\
                  print(sysconfig.get_path('scripts', f'{os.name}_user'))";
    let mut dirs: Vec<PathBuf> = Command::new("python3")
        .args(["-c", script])
        .output()
        .map(|o| {
            String::from_utf8_lossy(&o.stdout)
                .lines()
                .map(PathBuf::from)
                .collect()
        })
        .unwrap_or_default();
    dirs.extend(std::env::split_paths(
        &std::env::var_os("PATH").unwrap_or_default(),
    ));
    dirs.into_iter()
        .map(|d| d.join(name))
        .find(|p| p.is_file())
        .unwrap_or_else(|| panic!("`{name}` not found: {INSTALL}"))
}

/// The Kubernetes manifest as JSON (through PyYAML, a dependency of kubernetes-validate).
fn manifest() -> Value {
    let (ok, text) = output(Command::new("python3").args([
        "-c",
        "import json, sys, yaml; json.dump(list(yaml.safe_load_all(open(sys.argv[1]))), sys.stdout)",
        deploy("k8s/superflow-job.yaml").to_str().unwrap(),
    ]));
    assert!(ok, "reading the manifest with PyYAML ({INSTALL}):\n{text}");
    let docs: Vec<Value> = serde_json::from_str(&text).unwrap();
    assert_eq!(docs.len(), 1, "one Job in the manifest");
    docs.into_iter().next().unwrap()
}

fn strings(value: &Value) -> Vec<String> {
    value
        .as_array()
        .map(|a| {
            a.iter()
                .map(|v| v.as_str().expect("string").to_owned())
                .collect()
        })
        .unwrap_or_default()
}

/// The value following `flag` in `args`.
fn flag_value<'a>(args: &'a [String], flag: &str) -> Option<&'a str> {
    args.iter()
        .position(|a| a == flag)
        .and_then(|i| args.get(i + 1))
        .map(String::as_str)
}

/// Long flags (`--name`) that a `--help` text lists.
fn help_flags(binary: &Path) -> BTreeSet<String> {
    let (ok, text) = output(Command::new(binary).arg("--help"));
    assert!(ok, "{} --help:\n{text}", binary.display());
    long_flags(&text)
}

/// Long flags in `text`; `${VAR:---flag}` (a shell default) counts as `--flag`.
fn long_flags(text: &str) -> BTreeSet<String> {
    text.split(|c: char| c.is_whitespace() || matches!(c, ',' | '=' | '"' | '\'' | ':'))
        .filter(|w| w.starts_with("--") && w.len() > 2)
        .map(|w| {
            let name = w
                .trim_start_matches('-')
                .trim_end_matches(|c: char| !c.is_ascii_alphanumeric());
            format!("--{name}")
        })
        .collect()
}

/// The long flags passed to `binary` in a shell script or unit file: the logical lines
/// (continuations joined, comments dropped) that run it, from its name to the end.
fn flags_passed(text: &str, binary: &str) -> Vec<BTreeSet<String>> {
    let joined = text.replace("\\\n", " ");
    joined
        .lines()
        .map(str::trim)
        .filter(|l| !l.starts_with('#'))
        .filter_map(|line| {
            let words: Vec<&str> = line.split_whitespace().collect();
            let at = words.iter().position(|w| {
                let w = w.trim_start_matches(['"', '\'', '[']);
                let w = w.trim_end_matches(['"', '\'', ',']);
                let w = w.rsplit(['/', '=']).next().unwrap_or(w);
                w == binary
            })?;
            Some(long_flags(&words[at + 1..].join(" ")))
        })
        .collect()
}

fn assert_flags_exist(file: &str, used: &BTreeSet<String>, known: &BTreeSet<String>, bin: &str) {
    let unknown: Vec<&String> = used.difference(known).collect();
    assert!(
        unknown.is_empty(),
        "{file}: {bin} has no {unknown:?} (its --help lists {known:?})"
    );
}

/// Containers of the pod template: init containers (the pipeline sidecar) and the rest.
fn containers(job: &Value) -> Vec<&Value> {
    let spec = &job["spec"]["template"]["spec"];
    let mut all: Vec<&Value> = Vec::new();
    for key in ["initContainers", "containers"] {
        all.extend(spec[key].as_array().into_iter().flatten());
    }
    all
}

fn command_of(container: &Value) -> String {
    strings(&container["command"]).join(" ")
}

fn env_of(container: &Value) -> BTreeMap<String, Value> {
    container["env"]
        .as_array()
        .into_iter()
        .flatten()
        .map(|e| (e["name"].as_str().unwrap().to_owned(), e.clone()))
        .collect()
}

/// Volume name mounted at `path` in `container`.
fn volume_at<'a>(container: &'a Value, path: &str) -> Option<&'a str> {
    container["volumeMounts"]
        .as_array()?
        .iter()
        .find(|m| m["mountPath"] == path)
        .and_then(|m| m["name"].as_str())
}

/// Kubernetes quantity in MiB (`Mi`/`Gi` binary suffixes).
fn mib(quantity: &str) -> u64 {
    if let Some(n) = quantity.strip_suffix("Gi") {
        n.parse::<u64>().unwrap() * 1024
    } else if let Some(n) = quantity.strip_suffix("Mi") {
        n.parse().unwrap()
    } else {
        panic!("quantity {quantity}: use Mi or Gi")
    }
}

#[test]
fn kubernetes_manifest_validates_against_the_api_schemas() {
    let tool = python_tool("kubernetes-validate");
    let (ok, text) = output(Command::new(tool).args([
        "--strict",
        "--kubernetes-version",
        KUBERNETES_VERSION,
        deploy("k8s/superflow-job.yaml").to_str().unwrap(),
    ]));
    assert!(
        ok && text.contains("passed"),
        "kubernetes-validate:\n{text}"
    );
}

#[test]
fn scripts_parse_and_pass_shellcheck() {
    let shellcheck = python_tool("shellcheck");
    for script in [
        "run-local.sh",
        "slurm/superflow.sbatch",
        "slurm/superflow-node.sh",
    ] {
        let path = deploy(script);
        let (ok, text) = output(Command::new("bash").arg("-n").arg(&path));
        assert!(ok, "bash -n {script}:\n{text}");
        let (ok, text) = output(Command::new(&shellcheck).arg("-x").arg(&path));
        assert!(ok, "shellcheck {script}:\n{text}");
    }
}

#[test]
fn containerfile_passes_hadolint_and_builds_what_runs() {
    let path = deploy("Containerfile");
    let (ok, text) = output(Command::new(python_tool("hadolint")).arg(&path));
    assert!(ok, "hadolint:\n{text}");

    let text = read(&path);
    let froms: Vec<&str> = text.lines().filter(|l| l.starts_with("FROM ")).collect();
    assert_eq!(froms.len(), 2, "multi-stage: build, runtime: {froms:?}");
    let rust_version = read(&workspace_root().join("Cargo.toml"))
        .lines()
        .find_map(|l| l.strip_prefix("rust-version = "))
        .map(|v| v.trim_matches('"').to_owned())
        .unwrap();
    assert!(
        froms[0].contains(&format!("rust:{rust_version}-")),
        "the build stage uses the workspace's toolchain {rust_version}: {}",
        froms[0]
    );
    assert!(text.contains("cargo build --release --locked"), "--locked");
    for bin in ["superflow-pipeline", "superflow-trainer"] {
        assert!(
            text.contains(&format!("-p {bin}")) && text.contains(&format!("/out/{bin}")),
            "{bin} built and copied"
        );
    }
    let user = text
        .lines()
        .rev()
        .find_map(|l| l.strip_prefix("USER "))
        .expect("a USER");
    assert!(
        !["root", "0", "0:0"].contains(&user.trim()),
        "non-root runtime user: {user}"
    );
    // The build stage's `COPY . .` sends the whole repository: the ignore file keeps
    // build outputs and runs out.
    let ignore = read(&deploy("Containerfile.dockerignore"));
    for entry in ["target", "runs", ".git"] {
        assert!(
            ignore.lines().any(|l| l.trim() == entry),
            "{entry} in Containerfile.dockerignore"
        );
    }
}

#[test]
fn flags_in_the_deploy_files_exist_in_the_binaries() {
    let sibling = env!("CARGO_BIN_EXE_superflow-probe");
    let pipeline = help_flags(&pipeline_binary(sibling));
    let trainer = help_flags(&workspace_binary(sibling, "superflow-trainer"));
    for needed in ["--host-rank", "--host-count", "--mode", "--world-size"] {
        assert!(
            pipeline.contains(needed),
            "superflow-pipeline --help lacks {needed}"
        );
    }

    // Shell scripts and units: every invocation of either binary.
    let files = [
        "run-local.sh",
        "slurm/superflow-node.sh",
        "systemd/superflow-pipeline.service",
        "systemd/superflow-trainer@.service",
    ];
    let mut seen: BTreeMap<&str, BTreeSet<String>> = BTreeMap::new();
    for file in files {
        let text = read(&deploy(file));
        for (bin, known) in [
            ("superflow-pipeline", &pipeline),
            ("superflow-trainer", &trainer),
        ] {
            for used in flags_passed(&text, bin) {
                assert_flags_exist(file, &used, known, bin);
                seen.entry(file).or_default().extend(used);
            }
        }
    }
    // Extra trainer flags given through TRAINER_ARGS (a default or the example value).
    for file in [
        "run-local.sh",
        "slurm/superflow-node.sh",
        "systemd/superflow.env",
    ] {
        let text = read(&deploy(file));
        let lines: Vec<&str> = text
            .lines()
            .filter(|l| !l.trim_start().starts_with('#') && l.contains("TRAINER_ARGS"))
            .collect();
        let used = long_flags(&lines.join("\n"));
        assert!(!used.is_empty(), "{file}: TRAINER_ARGS flags found");
        assert_flags_exist(file, &used, &trainer, "superflow-trainer");
    }
    // The parser found the invocations (it would pass on nothing otherwise).
    for (file, expected) in [
        ("run-local.sh", &["--mcap", "--run", "--plot"][..]),
        (
            "slurm/superflow-node.sh",
            &["--host-rank", "--host-count", "--rank", "--resume"][..],
        ),
        (
            "systemd/superflow-pipeline.service",
            &["--host-rank", "--host-count", "--world-size"][..],
        ),
        (
            "systemd/superflow-trainer@.service",
            &["--rank", "--out", "--resume"][..],
        ),
    ] {
        for flag in expected {
            assert!(
                seen.get(file).is_some_and(|s| s.contains(*flag)),
                "{file}: no {flag} found in its invocations ({:?})",
                seen.get(file)
            );
        }
    }

    // The manifest: each container's command and args.
    for container in containers(&manifest()) {
        let args: BTreeSet<String> = strings(&container["args"])
            .into_iter()
            .filter(|a| a.starts_with("--"))
            .collect();
        let (bin, known) = match command_of(container).as_str() {
            "superflow-pipeline" => ("superflow-pipeline", &pipeline),
            "superflow-trainer" => ("superflow-trainer", &trainer),
            other => panic!("container {} runs {other}", container["name"]),
        };
        assert_flags_exist("k8s/superflow-job.yaml", &args, known, bin);
    }
}

#[test]
fn kubernetes_pod_shares_shared_memory_and_wires_the_ranks() {
    let job = manifest();
    let spec = &job["spec"];
    assert_eq!(job["kind"], "Job");
    assert_eq!(
        spec["completionMode"], "Indexed",
        "host rank = completion index"
    );
    let hosts = spec["completions"].as_u64().expect("completions");
    assert_eq!(
        spec["parallelism"].as_u64(),
        Some(hosts),
        "all hosts at once"
    );
    let pod = &spec["template"]["spec"];
    assert_eq!(
        pod["restartPolicy"], "OnFailure",
        "containers restart in place (the memory volumes survive)"
    );

    // /dev/shm: one memory-backed emptyDir with a size limit; the iceoryx2 root: one
    // shared emptyDir.
    let volumes: BTreeMap<String, &Value> = pod["volumes"]
        .as_array()
        .unwrap()
        .iter()
        .map(|v| (v["name"].as_str().unwrap().to_owned(), v))
        .collect();
    let all = containers(&job);
    let pipelines: Vec<&Value> = all
        .iter()
        .copied()
        .filter(|c| command_of(c) == "superflow-pipeline")
        .collect();
    let trainers: Vec<&Value> = all
        .iter()
        .copied()
        .filter(|c| command_of(c) == "superflow-trainer")
        .collect();
    assert_eq!(pipelines.len(), 1, "one pipeline per pod");
    assert!(!trainers.is_empty(), "trainers");
    let pipeline = pipelines[0];
    assert_eq!(
        pipeline["restartPolicy"], "Always",
        "the pipeline is a native sidecar (stopped when the trainers are done)"
    );

    let shm = volume_at(pipeline, "/dev/shm").expect("pipeline mounts /dev/shm");
    let root = volume_at(pipeline, "/tmp/iceoryx2").expect("pipeline mounts /tmp/iceoryx2");
    assert_ne!(shm, root);
    for c in &all {
        assert_eq!(
            volume_at(c, "/dev/shm"),
            Some(shm),
            "{}: the same /dev/shm",
            c["name"]
        );
        assert_eq!(
            volume_at(c, "/tmp/iceoryx2"),
            Some(root),
            "{}: the same iceoryx2 root",
            c["name"]
        );
        assert!(
            c["securityContext"]["runAsUser"].is_null()
                && c["securityContext"]["runAsGroup"].is_null(),
            "{}: the pod's user (iceoryx2 files are owner-only)",
            c["name"]
        );
    }
    assert!(pod["securityContext"]["runAsUser"].as_u64().unwrap() > 0);
    let shm_volume = &volumes[shm]["emptyDir"];
    assert_eq!(shm_volume["medium"], "Memory", "/dev/shm is memory-backed");
    assert!(
        volumes[root]["emptyDir"].is_object(),
        "iceoryx2 root: emptyDir"
    );

    // Ranks: the host rank from the completion index, the host count = completions,
    // local ranks 0..W-1 with the pipeline's world size.
    let index_path = "metadata.annotations['batch.kubernetes.io/job-completion-index']";
    let prefixes: BTreeSet<String> = all
        .iter()
        .map(|c| {
            env_of(c)["SUPERFLOW_IOX_PREFIX"]["value"]
                .as_str()
                .unwrap()
                .to_owned()
        })
        .collect();
    assert_eq!(prefixes.len(), 1, "one iceoryx2 prefix in the pod");
    for c in &all {
        let args = strings(&c["args"]).join(" ");
        if args.contains("$(SUPERFLOW_HOST_RANK)") {
            assert_eq!(
                env_of(c)["SUPERFLOW_HOST_RANK"]["valueFrom"]["fieldRef"]["fieldPath"],
                index_path,
                "{}: SUPERFLOW_HOST_RANK from the completion index",
                c["name"]
            );
        }
    }
    let p_args = strings(&pipeline["args"]);
    assert_eq!(
        flag_value(&p_args, "--host-rank"),
        Some("$(SUPERFLOW_HOST_RANK)")
    );
    assert_eq!(
        flag_value(&p_args, "--host-count"),
        Some("$(SUPERFLOW_HOST_COUNT)")
    );
    assert_eq!(
        env_of(pipeline)["SUPERFLOW_HOST_COUNT"]["value"]
            .as_str()
            .and_then(|v| v.parse().ok()),
        Some(hosts),
        "SUPERFLOW_HOST_COUNT = completions"
    );
    assert_eq!(flag_value(&p_args, "--mode"), Some("shard"));
    let world: u64 = flag_value(&p_args, "--world-size")
        .unwrap()
        .parse()
        .unwrap();
    assert_eq!(trainers.len() as u64, world, "one trainer per local rank");
    let mut ranks = BTreeSet::new();
    let mut outs = BTreeSet::new();
    for t in &trainers {
        let args = strings(&t["args"]);
        assert_eq!(
            flag_value(&args, "--world-size"),
            Some(world.to_string().as_str())
        );
        ranks.insert(flag_value(&args, "--rank").unwrap().parse::<u64>().unwrap());
        assert!(
            args.iter().any(|a| a == "--resume"),
            "{}: --resume",
            t["name"]
        );
        let out = flag_value(&args, "--out").unwrap();
        assert!(
            out.contains("$(SUPERFLOW_HOST_RANK)"),
            "{out}: one directory per host"
        );
        // --out lies on a persistent volume claim.
        let claim = t["volumeMounts"]
            .as_array()
            .unwrap()
            .iter()
            .find(|m| out.starts_with(m["mountPath"].as_str().unwrap()))
            .and_then(|m| volumes.get(m["name"].as_str().unwrap()))
            .expect("--out is under a mount");
        assert!(
            claim["persistentVolumeClaim"].is_object(),
            "{out}: on a PVC"
        );
        outs.insert(out.to_owned());
    }
    assert_eq!(ranks, (0..world).collect(), "local ranks 0..W-1");
    assert_eq!(outs.len(), trainers.len(), "one --out per trainer");

    // /dev/shm size: W streams x 8 batches, x2 for a move to a larger segment.
    let limit = mib(shm_volume["sizeLimit"].as_str().expect("sizeLimit"));
    let needed = 2 * world * BATCHES_PER_STREAM * BATCH_MIB;
    assert!(
        limit >= needed,
        "/dev/shm sizeLimit {limit} MiB < {needed} MiB"
    );
    let pipeline_memory = mib(pipeline["resources"]["limits"]["memory"].as_str().unwrap());
    assert!(
        pipeline_memory > limit,
        "the pipeline's memory limit ({pipeline_memory} MiB) covers the shm it writes ({limit} MiB)"
    );
}

/// `Key=value` entries of a unit file (`[Section]` headers and comments dropped).
fn unit_entries(text: &str) -> Vec<(String, String)> {
    text.lines()
        .map(str::trim)
        .filter(|l| !l.is_empty() && !l.starts_with('#') && !l.starts_with('['))
        .map(|l| {
            let (k, v) = l
                .split_once('=')
                .unwrap_or_else(|| panic!("not Key=value: {l}"));
            (k.trim().to_owned(), v.trim().to_owned())
        })
        .collect()
}

fn unit_value<'a>(entries: &'a [(String, String)], key: &str) -> Option<&'a str> {
    entries
        .iter()
        .rev()
        .find(|(k, _)| k == key)
        .map(|(_, v)| v.as_str())
}

#[test]
fn systemd_units_verify_and_share_shared_memory() {
    let pipeline_unit = read(&deploy("systemd/superflow-pipeline.service"));
    let trainer_unit = read(&deploy("systemd/superflow-trainer@.service"));
    let env_file = read(&deploy("systemd/superflow.env"));
    let p = unit_entries(&pipeline_unit);
    let t = unit_entries(&trainer_unit);

    // Same user, nothing private between them, no IPC removal.
    for key in ["User", "Group"] {
        let value = unit_value(&p, key);
        assert!(value.is_some_and(|v| v != "root"), "{key}= set, not root");
        assert_eq!(value, unit_value(&t, key), "the same {key}=");
    }
    for entries in [&p, &t] {
        for key in [
            "PrivateTmp",
            "PrivateDevices",
            "PrivateIPC",
            "RemoveIPC",
            "DynamicUser",
        ] {
            assert!(
                unit_value(entries, key).is_none_or(|v| v == "no"),
                "{key}= would separate or remove the iceoryx2 files"
            );
        }
        assert_eq!(unit_value(entries, "Restart"), Some("on-failure"));
        assert_eq!(
            unit_value(entries, "EnvironmentFile"),
            Some("/etc/superflow/superflow.env")
        );
    }
    let trainer_exec = unit_value(&t, "ExecStart").unwrap();
    assert!(trainer_exec.contains("--resume"), "restarts resume");
    assert!(trainer_exec.contains("--rank %i"), "local rank = instance");
    let pipeline_exec = unit_value(&p, "ExecStart").unwrap();
    assert!(pipeline_exec.contains("--host-rank ${SUPERFLOW_HOST_RANK}"));
    assert!(pipeline_exec.contains("--host-count ${SUPERFLOW_HOST_COUNT}"));

    // Every variable the units use is set in the example environment file.
    let env = unit_entries(&env_file);
    for unit in [&pipeline_unit, &trainer_unit] {
        for name in unit.split('$').skip(1).filter_map(|s| {
            let s = s.trim_start_matches('{');
            let name: String = s
                .chars()
                .take_while(|c| c.is_ascii_uppercase() || *c == '_')
                .collect();
            (!name.is_empty()).then_some(name)
        }) {
            assert!(
                unit_value(&env, &name).is_some(),
                "{name} used by a unit but not in superflow.env"
            );
        }
    }
    let world: u64 = unit_value(&env, "SUPERFLOW_LOCAL_WORLD_SIZE")
        .unwrap()
        .parse()
        .unwrap();
    let shm: u64 = unit_value(&env, "SUPERFLOW_SHM_MIB")
        .unwrap()
        .parse()
        .unwrap();
    let needed = 2 * world * BATCHES_PER_STREAM * BATCH_MIB;
    assert!(shm >= needed, "SUPERFLOW_SHM_MIB {shm} < {needed}");

    // systemd's own check, with the binaries it would start pointing at the built ones.
    let (available, _) = output(Command::new("systemd-analyze").arg("--version"));
    assert!(
        available,
        "systemd-analyze is missing: `apt-get install systemd` (.ci/run does) to verify the units"
    );
    let sibling = env!("CARGO_BIN_EXE_superflow-probe");
    let bin_dir = pipeline_binary(sibling).parent().unwrap().to_owned();
    workspace_binary(sibling, "superflow-trainer");
    let dir = std::env::temp_dir().join(format!("superflow-units-{}", std::process::id()));
    std::fs::create_dir_all(&dir).unwrap();
    for (name, text) in [
        ("superflow-pipeline.service", &pipeline_unit),
        ("superflow-trainer@.service", &trainer_unit),
    ] {
        let text = text.replace("/usr/local/bin/", &format!("{}/", bin_dir.display()));
        std::fs::write(dir.join(name), text).unwrap();
    }
    let (ok, text) = output(Command::new("systemd-analyze").args([
        "verify",
        "--man=no",
        dir.join("superflow-pipeline.service").to_str().unwrap(),
        dir.join("superflow-trainer@0.service").to_str().unwrap(),
    ]));
    std::fs::remove_dir_all(&dir).ok();
    // verify exits 0 on unknown keys and bad values (it ignores them): any output fails.
    assert!(
        ok && text.trim().is_empty(),
        "systemd-analyze verify:\n{text}"
    );
}

#[test]
fn slurm_script_wires_the_ranks_and_resumes() {
    let batch = read(&deploy("slurm/superflow.sbatch"));
    let node = read(&deploy("slurm/superflow-node.sh"));
    assert!(
        batch.contains("#SBATCH --ntasks-per-node=1"),
        "one task (one pipeline) per node: SLURM_PROCID is the node rank"
    );
    assert!(batch.contains("#SBATCH --requeue"));
    assert!(batch.contains("srun --ntasks-per-node=1"));
    assert!(batch.contains("deploy/slurm/superflow-node.sh"));
    assert!(batch.contains(r#"SUPERFLOW_IOX_PREFIX="sf${SLURM_JOB_ID}""#));
    assert!(node.contains(r#"SUPERFLOW_HOST_RANK="${SLURM_PROCID:"#));
    assert!(node.contains(r#"SUPERFLOW_HOST_COUNT="${SLURM_NNODES:"#));
    let pipeline = flags_passed(&node, "superflow-pipeline");
    let trainer = flags_passed(&node, "superflow-trainer");
    assert_eq!((pipeline.len(), trainer.len()), (1, 1), "one of each");
    for flag in [
        "--host-rank",
        "--host-count",
        "--world-size",
        "--iox-prefix",
    ] {
        assert!(pipeline[0].contains(flag), "pipeline {flag}");
    }
    for flag in [
        "--rank",
        "--world-size",
        "--resume",
        "--out",
        "--iox-prefix",
    ] {
        assert!(trainer[0].contains(flag), "trainer {flag}");
    }
}
