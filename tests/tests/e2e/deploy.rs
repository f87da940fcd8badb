//! The deployment files of `deploy/` are checked with the tools that check them for a
//! living — the Kubernetes manifests against the API schemas (`kubernetes-validate`; the
//! MPIJob, a custom resource, by its pod templates plus its own fields by hand), the
//! systemd units with `systemd-analyze verify`, the scripts with `bash -n` and
//! `shellcheck`, the Containerfile with `hadolint` — and for what matters to superflow:
//! every flag they pass exists in the binaries' `--help` (and `mpirun`'s options in Open
//! MPI's), the pipeline and the trainers share `/dev/shm` and iceoryx2's root path, the
//! host ranks are wired, restarts resume, `/dev/shm` is sized for the batches, and the
//! data-parallel variants run one MPI job of `--ddp` trainers over one shard pipeline
//! per host.
//!
//! The tools come from `pip install -r tests/python/requirements.txt`; a missing one
//! fails the test (it does not pass silently). `systemd-analyze` is the system's
//! (`apt-get install systemd`, which `.ci/run` does where it is missing).

#![allow(clippy::unwrap_used, clippy::expect_used)] // tests fail loudly on purpose

use serde_json::{Value, json};
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
/// The data-parallel Kubernetes manifest: an MPIJob (`kubeflow.org/v2beta1`).
const MPIJOB: &str = "k8s/superflow-mpijob.yaml";
/// The rank wrapper of the data-parallel deployments (GPU = local rank), in `deploy/`;
/// the image installs it as `/usr/local/bin/superflow-ddp-rank`.
const RANK_WRAPPER: &str = "superflow-ddp-rank.sh";
/// Open MPI's shared-memory transport (vader) maps a segment of this size per local rank
/// in `/dev/shm` (`btl_vader_segment_size`, 4 MiB).
const VADER_MIB_PER_RANK: u64 = 4;

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

/// The documents of a YAML file of `deploy/` as JSON (through PyYAML, a dependency of
/// kubernetes-validate).
fn yaml_docs(file: &str) -> Vec<Value> {
    let (ok, text) = output(Command::new("python3").args([
        "-c",
        "import json, sys, yaml; json.dump(list(yaml.safe_load_all(open(sys.argv[1]))), sys.stdout)",
        deploy(file).to_str().unwrap(),
    ]));
    assert!(ok, "reading {file} with PyYAML ({INSTALL}):\n{text}");
    serde_json::from_str(&text).unwrap()
}

/// The Kubernetes manifest as JSON.
fn manifest() -> Value {
    let docs = yaml_docs("k8s/superflow-job.yaml");
    assert_eq!(docs.len(), 1, "one Job in the manifest");
    docs.into_iter().next().unwrap()
}

/// The data-parallel manifest (an MPIJob of the MPI Operator) as JSON.
fn mpijob() -> Value {
    let docs = yaml_docs(MPIJOB);
    assert_eq!(docs.len(), 1, "one MPIJob in {MPIJOB}");
    docs.into_iter().next().unwrap()
}

/// The pod template of an MPIJob replica (`Launcher` or `Worker`).
fn replica_template<'a>(job: &'a Value, replica: &str) -> &'a Value {
    let template = &job["spec"]["mpiReplicaSpecs"][replica]["template"];
    assert!(template.is_object(), "{MPIJOB}: no {replica} template");
    template
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
    pod_containers(&job["spec"]["template"]["spec"])
}

/// Containers of a pod spec: init containers (the pipeline sidecar) and the rest.
fn pod_containers(spec: &Value) -> Vec<&Value> {
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

/// Volumes of a pod spec by name.
fn volumes_of(spec: &Value) -> BTreeMap<String, &Value> {
    spec["volumes"]
        .as_array()
        .into_iter()
        .flatten()
        .map(|v| (v["name"].as_str().unwrap().to_owned(), v))
        .collect()
}

/// An Open MPI tool (`mpirun`, `ompi_info`), allowed to run as root (CI runs as root).
fn open_mpi(program: &str) -> Command {
    let mut command = Command::new(program);
    command
        .env("OMPI_ALLOW_RUN_AS_ROOT", "1")
        .env("OMPI_ALLOW_RUN_AS_ROOT_CONFIRM", "1");
    command
}

/// `mpirun`'s options (`mpirun --help all`, every spelling) and how many values each
/// takes.
fn mpirun_options() -> BTreeMap<String, usize> {
    let (ok, text) = output(open_mpi("mpirun").args(["--help", "all"]));
    assert!(
        ok,
        "mpirun --help all (apt-get install openmpi-bin, as .ci/run does):\n{text}"
    );
    let mut options = BTreeMap::new();
    for line in text.lines() {
        let trimmed = line.trim_start();
        // Options start at most 3 columns in; their descriptions are indented further.
        if !trimmed.starts_with('-') || line.len() - trimmed.len() > 3 {
            continue;
        }
        let mut words = trimmed.split_whitespace();
        let names = words.next().unwrap();
        let arity = words.take_while(|w| w.starts_with("<arg")).count();
        for name in names.split('|') {
            options.insert(name.to_owned(), arity);
        }
    }
    assert!(
        options.contains_key("-np") && options.contains_key("--mca"),
        "parsed mpirun --help all: {options:?}"
    );
    options
}

/// Whether Open MPI knows the MCA parameter `name` (`ompi_info --all --parsable`).
fn mca_parameter_exists(ompi_info: &str, name: &str) -> bool {
    ompi_info.contains(&format!(":param:{name}:value:"))
}

/// The `mpirun` arguments in `args` before the program: every option is one of mpirun's,
/// with its values, and every `--mca NAME VALUE` names a parameter of this Open MPI.
/// Returns the index of the program.
fn check_mpirun_args(file: &str, args: &[String]) -> usize {
    let options = mpirun_options();
    let (ok, ompi_info) = output(open_mpi("ompi_info").args(["--all", "--parsable"]));
    assert!(ok, "ompi_info --all --parsable:\n{ompi_info}");
    let mut i = 0;
    while let Some(arg) = args.get(i) {
        if !arg.starts_with('-') {
            return i;
        }
        let arity = *options
            .get(arg)
            .unwrap_or_else(|| panic!("{file}: mpirun has no option {arg}"));
        if arg == "--mca" || arg == "-mca" {
            let name = &args[i + 1];
            assert!(
                mca_parameter_exists(&ompi_info, name),
                "{file}: Open MPI has no MCA parameter {name}"
            );
        }
        i += 1 + arity;
    }
    panic!("{file}: no program after mpirun's options: {args:?}")
}

/// The values of `--mca NAME VALUE` in mpirun's arguments.
fn mca_values(args: &[String]) -> BTreeMap<&str, &str> {
    args.windows(3)
        .filter(|w| w[0] == "--mca" || w[0] == "-mca")
        .map(|w| (w[1].as_str(), w[2].as_str()))
        .collect()
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
        "slurm/superflow-ddp.sbatch",
        "slurm/superflow-pipeline.sh",
        RANK_WRAPPER,
        "gpu/check.sh",
    ] {
        let path = deploy(script);
        let (ok, text) = output(Command::new("bash").arg("-n").arg(&path));
        assert!(ok, "bash -n {script}:\n{text}");
        let (ok, text) = output(Command::new(&shellcheck).arg("-x").arg(&path));
        assert!(ok, "shellcheck {script}:\n{text}");
    }
    // Run directly by srun, and copied into the image with their mode: executable.
    for script in [
        "slurm/superflow-ddp.sbatch",
        "slurm/superflow-pipeline.sh",
        RANK_WRAPPER,
    ] {
        use std::os::unix::fs::PermissionsExt;
        let mode = std::fs::metadata(deploy(script))
            .unwrap()
            .permissions()
            .mode();
        assert!(mode & 0o111 == 0o111, "{script} is executable: {mode:o}");
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
    // Data parallelism: the trainer's default `mpi` feature builds against Open MPI with
    // bindgen (libclang); the image carries mpirun/orted/libmpi, sshd and ssh for the
    // MPI Operator, and the rank wrapper.
    let (build, runtime) = text.split_at(text.find(froms[1]).unwrap());
    for package in ["libopenmpi-dev=", "libclang-dev="] {
        assert!(
            build.contains(package),
            "the build stage installs {package}"
        );
    }
    for package in ["openmpi-bin=", "openssh-server=", "openssh-client="] {
        assert!(
            runtime.contains(package),
            "the runtime stage installs {package}"
        );
    }
    assert!(
        runtime.contains(&format!(
            "COPY deploy/{RANK_WRAPPER} /usr/local/bin/superflow-ddp-rank"
        )),
        "the rank wrapper in the image"
    );
    // sshd runs mpirun's remote commands through the user's login shell.
    let useradd = runtime
        .replace("\\\n", " ")
        .lines()
        .find(|l| l.contains("useradd"))
        .expect("useradd")
        .to_owned();
    assert!(
        !useradd.contains("nologin") && useradd.contains("--shell /bin/bash"),
        "the user needs a login shell for ssh (MPI Operator): {useradd}"
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
    let sibling = env!("CARGO_BIN_EXE_superflow-subscriber");
    let pipeline = help_flags(&pipeline_binary(sibling));
    let trainer = help_flags(&workspace_binary(sibling, "superflow-trainer"));
    for needed in ["--host-rank", "--host-count", "--mode", "--world-size"] {
        assert!(
            pipeline.contains(needed),
            "superflow-pipeline --help lacks {needed}"
        );
    }
    for needed in ["--ddp", "--collective-timeout-secs", "--device-index"] {
        assert!(
            trainer.contains(needed),
            "superflow-trainer --help lacks {needed}"
        );
    }

    // Shell scripts and units: every invocation of either binary.
    let files = [
        "run-local.sh",
        "slurm/superflow-node.sh",
        "systemd/superflow-pipeline.service",
        "systemd/superflow-trainer@.service",
        "slurm/superflow-ddp.sbatch",
        "slurm/superflow-pipeline.sh",
        RANK_WRAPPER,
    ];
    let mut seen: BTreeMap<&str, BTreeSet<String>> = BTreeMap::new();
    for file in files {
        let text = read(&deploy(file));
        for (bin, known) in [
            ("superflow-pipeline", &pipeline),
            ("superflow-trainer", &trainer),
            // The rank wrapper passes its arguments on to the trainer.
            (RANK_WRAPPER, &trainer),
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
        "slurm/superflow-ddp.sbatch",
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
        (
            "slurm/superflow-ddp.sbatch",
            &[
                "--ddp",
                "--out",
                "--resume",
                "--iox-prefix",
                "--collective-timeout-secs",
            ][..],
        ),
        (
            "slurm/superflow-pipeline.sh",
            &[
                "--mode",
                "--world-size",
                "--host-rank",
                "--host-count",
                "--iox-prefix",
            ][..],
        ),
        (RANK_WRAPPER, &["--device-index"][..]),
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

    // The MPIJob: the workers' pipeline sidecar; the launcher's mpirun (its options in
    // Open MPI's) and the trainer flags after the rank wrapper; sshd is checked by
    // kubernetes_mpijob_runs_the_trainers_over_ssh_beside_the_pipelines.
    let job = mpijob();
    let mut launched = BTreeSet::new();
    for replica in ["Launcher", "Worker"] {
        for container in pod_containers(&replica_template(&job, replica)["spec"]) {
            let args = strings(&container["args"]);
            let flags = |args: &[String]| -> BTreeSet<String> {
                args.iter()
                    .filter(|a| a.starts_with("--"))
                    .cloned()
                    .collect()
            };
            match command_of(container).as_str() {
                "superflow-pipeline" => {
                    assert_flags_exist(MPIJOB, &flags(&args), &pipeline, "superflow-pipeline");
                }
                "mpirun" => {
                    let program = check_mpirun_args(MPIJOB, &args);
                    assert_eq!(args[program], "superflow-ddp-rank", "the rank wrapper");
                    let used = flags(&args[program + 1..]);
                    assert_flags_exist(MPIJOB, &used, &trainer, "superflow-trainer");
                    launched.extend(used);
                }
                "/usr/sbin/sshd" => {}
                other => panic!("{MPIJOB}: container {} runs {other}", container["name"]),
            }
        }
    }
    for flag in ["--ddp", "--out", "--resume", "--iox-prefix"] {
        assert!(launched.contains(flag), "{MPIJOB}: mpirun passes no {flag}");
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
    // The index cache lives on the shared, persistent runs volume.
    let cache = &env_of(pipeline)["SUPERFLOW_INDEX_CACHE"];
    assert_eq!(cache["value"], "/runs/index-cache");
    let runs = volume_at(pipeline, "/runs").expect("pipeline mounts /runs");
    assert_eq!(
        volumes_of(pod)[runs]["persistentVolumeClaim"]["claimName"],
        "superflow-runs"
    );
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
    let sibling = env!("CARGO_BIN_EXE_superflow-subscriber");
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

/// The `srun` steps of a batch script, continuation lines joined.
fn srun_steps(batch: &str) -> Vec<String> {
    batch
        .replace("\\\n", " ")
        .lines()
        .map(str::trim)
        .filter(|l| l.starts_with("srun "))
        .map(str::to_owned)
        .collect()
}

/// The first srun step indexes every drive once, as one task in the foreground, into
/// the shared index cache the pipelines then read (`SUPERFLOW_INDEX_CACHE`).
fn assert_index_step_first(steps: &[String]) {
    let index = &steps[0];
    assert!(
        index.contains("superflow-pipeline\" index --mcap"),
        "the first step indexes the drives: {index}"
    );
    assert!(index.contains("--ntasks=1"), "one task: {index}");
    assert!(!index.ends_with('&'), "the index step ends first: {index}");
    assert!(
        steps[1..].iter().all(|s| !s.contains(" index ")),
        "indexed once per job: {steps:?}"
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
    let steps = srun_steps(&batch);
    assert_eq!(steps.len(), 2, "index, then the nodes: {steps:?}");
    assert_index_step_first(&steps);
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

/// Fields of an MPIJob that the MPI Operator's `kubeflow.org/v2beta1` API defines
/// (`pkg/apis/kubeflow/v2beta1/types.go`: `MPIJobSpec`, `RunPolicy`, `ReplicaSpec`), and
/// the values of its enums: its CRD is not among kubernetes-validate's schemas.
const MPIJOB_SPEC_FIELDS: &[&str] = &[
    "slotsPerWorker",
    "runLauncherAsWorker",
    "runPolicy",
    "mpiReplicaSpecs",
    "sshAuthMountPath",
    "launcherCreationPolicy",
    "mpiImplementation",
];
const MPIJOB_RUN_POLICY_FIELDS: &[&str] = &[
    "cleanPodPolicy",
    "ttlSecondsAfterFinished",
    "activeDeadlineSeconds",
    "backoffLimit",
    "schedulingPolicy",
    "suspend",
    "managedBy",
];
const MPIJOB_REPLICA_FIELDS: &[&str] = &["replicas", "template", "restartPolicy"];

fn assert_fields_among(what: &str, value: &Value, known: &[&str]) {
    let object = value
        .as_object()
        .unwrap_or_else(|| panic!("{MPIJOB}: {what} is an object"));
    for key in object.keys() {
        assert!(
            known.contains(&key.as_str()),
            "{MPIJOB}: {what} has no field {key} in kubeflow.org/v2beta1 (known: {known:?})"
        );
    }
}

fn assert_one_of(what: &str, value: &Value, allowed: &[&str]) {
    assert!(
        value.as_str().is_some_and(|v| allowed.contains(&v)),
        "{MPIJOB}: {what} = {value}, one of {allowed:?}"
    );
}

#[test]
fn kubernetes_mpijob_pod_templates_validate_against_the_api_schemas() {
    let job = mpijob();
    let tool = python_tool("kubernetes-validate");
    let dir = std::env::temp_dir().join(format!("superflow-mpijob-{}", std::process::id()));
    std::fs::create_dir_all(&dir).unwrap();
    // Each replica's pod template as the v1 Pod the operator makes of it, strictly
    // validated at the same Kubernetes version as the Job.
    for replica in ["Launcher", "Worker"] {
        let template = replica_template(&job, replica);
        let mut metadata = template["metadata"].clone();
        if metadata.is_null() {
            metadata = json!({});
        }
        metadata["name"] = json!(format!(
            "{}-{}",
            job["metadata"]["name"].as_str().unwrap(),
            replica.to_lowercase()
        ));
        let pod = json!({
            "apiVersion": "v1",
            "kind": "Pod",
            "metadata": metadata,
            "spec": template["spec"],
        });
        let path = dir.join(format!("{}.yaml", replica.to_lowercase()));
        std::fs::write(&path, serde_json::to_string_pretty(&pod).unwrap()).unwrap();
        let (ok, text) = output(Command::new(&tool).args([
            "--strict",
            "--kubernetes-version",
            KUBERNETES_VERSION,
            path.to_str().unwrap(),
        ]));
        assert!(
            ok && text.contains("passed"),
            "kubernetes-validate of the {replica} pod template:\n{text}"
        );
    }
    std::fs::remove_dir_all(&dir).ok();

    // The MPIJob's own fields, by hand.
    assert_eq!(job["apiVersion"], "kubeflow.org/v2beta1");
    assert_eq!(job["kind"], "MPIJob");
    assert!(job["metadata"]["name"].is_string());
    let spec = &job["spec"];
    assert_fields_among("spec", spec, MPIJOB_SPEC_FIELDS);
    assert_fields_among(
        "spec.runPolicy",
        &spec["runPolicy"],
        MPIJOB_RUN_POLICY_FIELDS,
    );
    let replicas = spec["mpiReplicaSpecs"]
        .as_object()
        .expect("mpiReplicaSpecs");
    assert_eq!(
        replicas.keys().map(String::as_str).collect::<Vec<_>>(),
        ["Launcher", "Worker"],
        "a launcher and workers"
    );
    for (name, replica) in replicas {
        assert_fields_among(
            &format!("mpiReplicaSpecs.{name}"),
            replica,
            MPIJOB_REPLICA_FIELDS,
        );
        assert!(
            replica["replicas"].as_u64().is_some_and(|n| n >= 1),
            "{name}: replicas"
        );
        assert_one_of(
            &format!("{name}.restartPolicy"),
            &replica["restartPolicy"],
            &["Always", "OnFailure", "Never", "ExitCode"],
        );
        assert!(
            replica["template"]["spec"]["restartPolicy"].is_null(),
            "{name}: the restart policy belongs to the replica spec (the operator overrides the template's)"
        );
    }
    assert!(spec["slotsPerWorker"].as_u64().is_some_and(|n| n >= 1));
    assert_one_of(
        "runPolicy.cleanPodPolicy",
        &spec["runPolicy"]["cleanPodPolicy"],
        &["None", "Running", "All"],
    );
    assert_one_of(
        "launcherCreationPolicy",
        &spec["launcherCreationPolicy"],
        &["AtStartup", "WaitForWorkersReady"],
    );
    assert_one_of(
        "mpiImplementation",
        &spec["mpiImplementation"],
        &["OpenMPI", "Intel", "MPICH"],
    );
    assert!(
        spec["sshAuthMountPath"]
            .as_str()
            .is_some_and(|p| p.starts_with('/'))
    );
}

#[test]
fn kubernetes_mpijob_runs_the_trainers_over_ssh_beside_the_pipelines() {
    let job = mpijob();
    let spec = &job["spec"];
    let slots = spec["slotsPerWorker"].as_u64().unwrap();
    let hosts = spec["mpiReplicaSpecs"]["Worker"]["replicas"]
        .as_u64()
        .unwrap();
    assert_eq!(spec["mpiReplicaSpecs"]["Launcher"]["replicas"], 1);
    assert_eq!(spec["mpiImplementation"], "OpenMPI", "mpirun is Open MPI's");
    assert_eq!(
        spec["launcherCreationPolicy"], "WaitForWorkersReady",
        "mpirun starts once every worker's sshd (and pipeline) is up"
    );
    assert!(
        ["Running", "All"].contains(&spec["runPolicy"]["cleanPodPolicy"].as_str().unwrap()),
        "the workers (sshd and a pipeline that streams forever) go when the launcher is done"
    );
    // A failed mpirun (a rank died, or a hung one was aborted) restarts: every rank
    // resumes from rank 0's checkpoint.
    assert_eq!(
        spec["mpiReplicaSpecs"]["Launcher"]["restartPolicy"],
        "OnFailure"
    );
    assert!(spec["runPolicy"]["backoffLimit"].as_u64().unwrap() > 0);

    let launcher_pod = &replica_template(&job, "Launcher")["spec"];
    let worker_pod = &replica_template(&job, "Worker")["spec"];

    // Same user everywhere (iceoryx2's files are owner-only; ssh logs in as that user),
    // non-root, never overridden by a container; the same image (mpirun and orted of one
    // Open MPI).
    let user = &worker_pod["securityContext"];
    assert!(user["runAsUser"].as_u64().unwrap() > 0);
    assert_eq!(user["runAsNonRoot"], true);
    for field in ["runAsUser", "runAsGroup", "fsGroup"] {
        assert_eq!(
            launcher_pod["securityContext"][field], user[field],
            "launcher and workers: the same {field}"
        );
        assert_eq!(
            manifest()["spec"]["template"]["spec"]["securityContext"][field],
            user[field],
            "the same {field} as the Job (the image's user)"
        );
    }
    let mut images = BTreeSet::new();
    for pod in [launcher_pod, worker_pod] {
        for c in pod_containers(pod) {
            assert!(
                c["securityContext"]["runAsUser"].is_null()
                    && c["securityContext"]["runAsGroup"].is_null(),
                "{}: the pod's user",
                c["name"]
            );
            images.insert(c["image"].as_str().unwrap().to_owned());
        }
    }
    assert_eq!(images.len(), 1, "one image: {images:?}");

    // SSH: the operator mounts the keys into the first container of each pod, at
    // sshAuthMountPath, which must be the ~/.ssh of the image's user (ssh finds its key
    // there, sshd the authorized keys).
    let ssh_dir = spec["sshAuthMountPath"].as_str().unwrap();
    let containerfile = read(&deploy("Containerfile"));
    let home = containerfile
        .split_whitespace()
        .skip_while(|w| *w != "--home-dir")
        .nth(1)
        .expect("useradd --home-dir");
    assert_eq!(ssh_dir, format!("{home}/.ssh"), "sshAuthMountPath = ~/.ssh");
    let sshd = &worker_pod["containers"][0];
    assert_eq!(
        command_of(sshd),
        "/usr/sbin/sshd",
        "the workers' first container runs sshd (it gets the keys, the ranks run in it)"
    );
    let sshd_args = strings(&sshd["args"]);
    let port = flag_value(&sshd_args, "-p").expect("sshd -p PORT");
    assert!(
        port.parse::<u16>().unwrap() >= 1024,
        "a non-root sshd needs a port >= 1024"
    );
    assert!(
        sshd_args.iter().any(|a| a.starts_with("-De")),
        "sshd in the foreground"
    );
    assert_eq!(
        flag_value(&sshd_args, "-f"),
        Some("/dev/null"),
        "no system sshd_config (UsePAM yes: a non-root sshd cannot use PAM)"
    );
    let sshd_options: BTreeSet<&str> = sshd_args
        .windows(2)
        .filter(|w| w[0] == "-o")
        .map(|w| w[1].as_str())
        .collect();
    for option in [
        format!("HostKey={ssh_dir}/id_rsa"),
        format!("AuthorizedKeysFile={ssh_dir}/authorized_keys"),
        "StrictModes=no".to_owned(),
        "PasswordAuthentication=no".to_owned(),
    ] {
        assert!(
            sshd_options.contains(option.as_str()),
            "sshd -o {option} ({sshd_options:?})"
        );
    }
    assert_eq!(
        sshd["readinessProbe"]["tcpSocket"]["port"].to_string(),
        port,
        "ready = sshd answers (launcherCreationPolicy waits for it)"
    );

    // The launcher: mpirun over hosts x slots ranks, ssh to the workers' port, the rank
    // wrapper, the trainer in --ddp mode resuming into one directory on the claim.
    let launchers = pod_containers(launcher_pod);
    assert_eq!(launchers.len(), 1, "one launcher container");
    let launcher = launchers[0];
    assert_eq!(command_of(launcher), "mpirun");
    assert!(
        launcher["resources"]["limits"]["nvidia.com/gpu"].is_null(),
        "the launcher trains nothing"
    );
    let args = strings(&launcher["args"]);
    let program = args
        .iter()
        .position(|a| a == "superflow-ddp-rank")
        .expect("mpirun runs superflow-ddp-rank");
    let (mpirun_args, trainer) = (&args[..program], &args[program + 1..]);
    assert_eq!(
        flag_value(mpirun_args, "-np").and_then(|n| n.parse::<u64>().ok()),
        Some(hosts * slots),
        "-np = Worker.replicas x slotsPerWorker"
    );
    assert_eq!(
        flag_value(mpirun_args, "--bind-to"),
        Some("none"),
        "the trainer's threads are not pinned to one core"
    );
    let mca = mca_values(mpirun_args);
    let rsh = mca.get("plm_rsh_args").expect("--mca plm_rsh_args");
    assert!(
        rsh.contains(&format!("-p {port}")),
        "ssh to the workers' sshd port {port}: {rsh}"
    );
    assert!(
        rsh.contains("StrictHostKeyChecking=no") && rsh.contains("UserKnownHostsFile=/dev/null"),
        "new host keys with every pod, a read-only ~/.ssh: {rsh}"
    );
    assert_eq!(
        mca.get("btl_vader_single_copy_mechanism"),
        Some(&"none"),
        "no CMA without ptrace (capabilities dropped)"
    );
    for flag in ["--ddp", "--resume"] {
        assert!(trainer.iter().any(|a| a == flag), "the trainers get {flag}");
    }
    for flag in ["--rank", "--world-size", "--device-index"] {
        assert!(
            !trainer.iter().any(|a| a == flag),
            "{flag}: MPI gives the ranks (--ddp conflicts with --rank/--world-size), the wrapper the device"
        );
    }
    let collective: u64 =
        flag_value(trainer, "--collective-timeout-secs").map_or(900, |v| v.parse().unwrap());
    let batch_timeout: u64 =
        flag_value(trainer, "--timeout-secs").map_or(300, |v| v.parse().unwrap());
    assert!(
        collective > batch_timeout,
        "a rank may wait --timeout-secs for its batch: the collective timeout is longer"
    );
    let out = flag_value(trainer, "--out").expect("--out");
    assert!(
        !out.contains("$("),
        "one directory for the job (rank 0's checkpoints, rank-r/ of each rank): {out}"
    );

    // The workers: the pipeline sidecar and the ranks (in the sshd container) share
    // /dev/shm and /tmp/iceoryx2, one prefix, the host rank from the replica index.
    let volumes = volumes_of(worker_pod);
    let pipelines: Vec<&Value> = pod_containers(worker_pod)
        .into_iter()
        .filter(|c| command_of(c) == "superflow-pipeline")
        .collect();
    assert_eq!(pipelines.len(), 1, "one pipeline per worker");
    let pipeline = pipelines[0];
    assert!(
        worker_pod["initContainers"]
            .as_array()
            .unwrap()
            .iter()
            .any(|c| c == pipeline),
        "the pipeline is an init container"
    );
    assert_eq!(
        pipeline["restartPolicy"], "Always",
        "the pipeline is a native sidecar (restarted on its own, stopped with the pod)"
    );
    let shm = volume_at(pipeline, "/dev/shm").expect("pipeline mounts /dev/shm");
    let root = volume_at(pipeline, "/tmp/iceoryx2").expect("pipeline mounts /tmp/iceoryx2");
    assert_ne!(shm, root);
    assert_eq!(
        volume_at(sshd, "/dev/shm"),
        Some(shm),
        "the ranks' /dev/shm"
    );
    assert_eq!(
        volume_at(sshd, "/tmp/iceoryx2"),
        Some(root),
        "the ranks' iceoryx2 root"
    );
    let shm_volume = &volumes[shm]["emptyDir"];
    assert_eq!(shm_volume["medium"], "Memory", "/dev/shm is memory-backed");
    assert!(
        volumes[root]["emptyDir"].is_object(),
        "iceoryx2 root: emptyDir"
    );

    let p_args = strings(&pipeline["args"]);
    assert_eq!(flag_value(&p_args, "--mode"), Some("shard"));
    assert_eq!(
        flag_value(&p_args, "--world-size").and_then(|w| w.parse::<u64>().ok()),
        Some(slots),
        "one stream per local rank: --world-size = slotsPerWorker"
    );
    assert_eq!(
        flag_value(&p_args, "--host-rank"),
        Some("$(SUPERFLOW_HOST_RANK)")
    );
    assert_eq!(
        flag_value(&p_args, "--host-count"),
        Some("$(SUPERFLOW_HOST_COUNT)")
    );
    let p_env = env_of(pipeline);
    assert_eq!(
        p_env["SUPERFLOW_HOST_RANK"]["valueFrom"]["fieldRef"]["fieldPath"],
        "metadata.labels['training.kubeflow.org/replica-index']",
        "host rank = the worker's replica index (the operator's label on worker i)"
    );
    assert_eq!(
        p_env["SUPERFLOW_HOST_COUNT"]["value"]
            .as_str()
            .and_then(|v| v.parse().ok()),
        Some(hosts),
        "SUPERFLOW_HOST_COUNT = Worker.replicas"
    );
    // The ranks start in an ssh session, which does not inherit a container's
    // environment: the prefix is a flag of the launcher's command.
    assert_eq!(
        flag_value(trainer, "--iox-prefix"),
        p_env["SUPERFLOW_IOX_PREFIX"]["value"].as_str(),
        "the trainers' --iox-prefix = the pipeline's SUPERFLOW_IOX_PREFIX"
    );
    assert_eq!(
        sshd["resources"]["limits"]["nvidia.com/gpu"].as_u64(),
        Some(slots),
        "one GPU per local rank, all in the container the ranks run in"
    );

    // Claims: drives read-only for the pipeline; --out on the ReadWriteMany claim in the
    // ranks' container.
    assert_eq!(
        volumes[volume_at(pipeline, "/data").expect("pipeline mounts /data")]["persistentVolumeClaim"]
            ["claimName"],
        "superflow-data"
    );
    let runs = sshd["volumeMounts"]
        .as_array()
        .unwrap()
        .iter()
        .find(|m| out.starts_with(m["mountPath"].as_str().unwrap()))
        .expect("--out is under a mount of the ranks' container");
    assert_eq!(
        volumes[runs["name"].as_str().unwrap()]["persistentVolumeClaim"]["claimName"],
        "superflow-runs",
        "{out}: on the runs claim"
    );
    for (name, volume) in &volumes {
        if let Some(claim) = volume["persistentVolumeClaim"].as_object() {
            let expected = if claim["claimName"] == "superflow-data" {
                json!(true)
            } else {
                Value::Null
            };
            assert_eq!(
                claim.get("readOnly").cloned().unwrap_or(Value::Null),
                expected,
                "{name}"
            );
        }
    }

    // /dev/shm size: slots streams x 8 batches, x2 for a move to a larger segment, plus
    // Open MPI's shared-memory segments of the ranks.
    let limit = mib(shm_volume["sizeLimit"].as_str().expect("sizeLimit"));
    let needed = 2 * slots * BATCHES_PER_STREAM * BATCH_MIB + slots * VADER_MIB_PER_RANK;
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

#[test]
fn slurm_ddp_script_runs_one_mpi_job_over_one_pipeline_per_node() {
    let batch = read(&deploy("slurm/superflow-ddp.sbatch"));
    let node = read(&deploy("slurm/superflow-pipeline.sh"));
    let wrapper = read(&deploy(RANK_WRAPPER));
    let sbatch = |option: &str| -> Option<String> {
        batch
            .lines()
            .find_map(|l| l.strip_prefix(&format!("#SBATCH --{option}=")))
            .map(str::to_owned)
    };
    assert_eq!(
        sbatch("ntasks-per-node"),
        sbatch("gpus-per-node"),
        "one trainer rank per GPU"
    );
    assert!(batch.contains("#SBATCH --requeue"));
    assert!(batch.contains("#SBATCH --signal=B:TERM@"));
    assert!(
        batch.contains(
            r#"SUPERFLOW_LOCAL_WORLD_SIZE="${SUPERFLOW_LOCAL_WORLD_SIZE:-${SLURM_NTASKS_PER_NODE:"#
        ),
        "the pipelines' --world-size = the ranks per node"
    );
    assert!(batch.contains(r#"SUPERFLOW_IOX_PREFIX="sf${SLURM_JOB_ID}"#));

    let steps = srun_steps(&batch);
    assert_eq!(
        steps.len(),
        3,
        "three steps: index, pipelines, trainers: {steps:?}"
    );
    assert_index_step_first(&steps);
    let pipelines = steps
        .iter()
        .find(|s| s.contains("deploy/slurm/superflow-pipeline.sh"))
        .expect("a step runs deploy/slurm/superflow-pipeline.sh");
    let trainers = steps
        .iter()
        .find(|s| s.contains(&format!("deploy/{RANK_WRAPPER}")))
        .expect("a step runs the rank wrapper");
    for step in [pipelines, trainers] {
        assert!(
            step.contains("--overlap"),
            "the two steps share the nodes: {step}"
        );
        assert!(step.contains("--kill-on-bad-exit=1"), "{step}");
        assert!(step.ends_with('&'), "both steps in the background: {step}");
    }
    assert!(
        pipelines.contains("--ntasks-per-node=1") && pipelines.contains(r#"--ntasks="$nodes""#),
        "one pipeline per node: {pipelines}"
    );
    assert!(
        !pipelines.contains("--mpi="),
        "the pipelines are no MPI job"
    );
    assert!(
        trainers.contains("--mpi=pmix")
            && trainers.contains(r#"--ntasks-per-node="$world""#)
            && trainers.contains(r#"--ntasks="$((nodes * world))""#),
        "one MPI job of nodes x world ranks: {trainers}"
    );
    let ranks = flags_passed(&batch, RANK_WRAPPER);
    assert_eq!(ranks.len(), 1, "one trainer invocation");
    for flag in ["--ddp", "--resume", "--out", "--iox-prefix"] {
        assert!(ranks[0].contains(flag), "trainers {flag}");
    }
    for flag in ["--rank", "--world-size", "--device-index"] {
        assert!(!ranks[0].contains(flag), "trainers without {flag}");
    }
    assert!(
        trainers.contains(r#"--out "$SUPERFLOW_OUT""#),
        "one directory for the job: {trainers}"
    );
    // SIGTERM (before the time limit) goes to the trainers, which checkpoint; then the
    // pipelines stop.
    assert!(batch.contains("trap stop_trainers TERM"));
    assert!(batch.contains(r#"kill -TERM "$trainers""#));
    assert!(batch.contains(r#"kill -TERM "$pipelines""#));

    // The node's pipeline: host rank = the node's index, one stream per local rank,
    // the job's prefix, cleanup of what a killed process left.
    assert!(node.contains(r#"SUPERFLOW_HOST_RANK="${SLURM_NODEID:"#));
    assert!(node.contains(r#"SUPERFLOW_HOST_COUNT="${SLURM_NNODES:"#));
    assert!(node.contains(r#"world="${SUPERFLOW_LOCAL_WORLD_SIZE:"#));
    let pipeline = flags_passed(&node, "superflow-pipeline");
    assert_eq!(pipeline.len(), 1, "one pipeline invocation");
    for flag in [
        "--mode",
        "--world-size",
        "--host-rank",
        "--host-count",
        "--iox-prefix",
    ] {
        assert!(pipeline[0].contains(flag), "pipeline {flag}");
    }
    let invocation = node.replace("\\\n", " ");
    assert!(invocation.contains(r#"--mode shard --world-size "$world""#));
    assert!(node.contains("trap cleanup EXIT"));
    assert!(node.contains(r#"rm -f /dev/shm/"${SUPERFLOW_IOX_PREFIX}"_*"#));
    assert!(node.contains(r#"find /tmp/iceoryx2 -name "${SUPERFLOW_IOX_PREFIX}_*" -delete"#));

    // The wrapper: GPU = local rank (Open MPI's or Slurm's), for both GPU backends.
    assert!(wrapper.contains("${OMPI_COMM_WORLD_LOCAL_RANK:-${SLURM_LOCALID:-0}}"));
    assert!(wrapper.contains("CUBECL_WGPU_DEFAULT_DEVICE"));
    assert!(wrapper.contains(r#"exec "$bin/superflow-trainer" --device-index "$gpu" "$@""#));
}
