//! One command-line vocabulary: a service flag means the same to every subcommand that
//! reads it and is refused (usage error, exit code 2) by one that does not, wherever it
//! stands on the line: by the check of the service's flags, or, for a flag that is not
//! global after the subcommand's name, by clap itself (the subcommand has no such flag).
//! One test per subcommand.

use std::path::PathBuf;
use std::process::Command;

const DRIVE: &str = "recordings/drives/street_ros2.mcap";

/// `superflow-pipeline <args>` from the workspace root: exit code, stdout, stderr.
fn run(args: &[&str], env: &[(&str, &str)]) -> (Option<i32>, String, String) {
    let out = Command::new(env!("CARGO_BIN_EXE_superflow-pipeline"))
        .args(args)
        .envs(env.iter().copied())
        .env("SUPERFLOW_INDEX_CACHE", "off")
        .current_dir(super::root())
        .output()
        .unwrap();
    (
        out.status.code(),
        String::from_utf8_lossy(&out.stdout).into_owned(),
        String::from_utf8_lossy(&out.stderr).into_owned(),
    )
}

/// `subcommand` refuses each of the service's flags it does not read, before and after
/// its name, naming the flag and itself.
fn refuses_service_flags(subcommand: &str, rest: &[&str], flags: &[(&str, &str)]) {
    for &(flag, value) in flags {
        for before in [true, false] {
            let mut args: Vec<&str> = Vec::new();
            if before {
                args.extend([flag, value, subcommand]);
            } else {
                args.extend([subcommand, flag, value]);
            }
            args.extend(rest);
            let (code, _, err) = run(&args, &[]);
            assert_eq!(code, Some(2), "{args:?} is a usage error: {err}");
            // `--run` and `--batch-size` are global (`batch` reads them after its name).
            let global = matches!(flag, "--run" | "--batch-size");
            let why = if before || global {
                format!("`{subcommand}` does not read it")
            } else {
                "unexpected argument".to_owned()
            };
            assert!(err.contains(flag) && err.contains(&why), "{args:?}: {err}");
        }
    }
}

/// Every service flag with a value it would take.
const SERVICE_FLAGS: &[(&str, &str)] = &[
    ("--run", "other"),
    ("--mode", "shard"),
    ("--world-size", "2"),
    ("--host-rank", "0"),
    ("--host-count", "1"),
    ("--batch-size", "8"),
    ("--epochs", "2"),
    ("--subscribers", "2"),
    ("--start-epoch", "1"),
    ("--start-step", "1"),
    ("--start-sample", "1"),
    ("--metrics-addr", "127.0.0.1:9464"),
    ("--iox-prefix", "x"),
];

#[test]
fn index_refuses_the_service_flags() {
    refuses_service_flags("index", &["--mcap", DRIVE], SERVICE_FLAGS);
}

#[test]
fn inspect_refuses_the_service_flags_but_not_a_jobs_environment() {
    refuses_service_flags("inspect", &["--mcap", DRIVE], SERVICE_FLAGS);
    // A job's environment sets the service's rank for every command it runs.
    let env = [("SUPERFLOW_HOST_RANK", "1"), ("SUPERFLOW_HOST_COUNT", "2")];
    let (code, out, err) = run(&["inspect", "--mcap", DRIVE], &env);
    assert_eq!(code, Some(0), "{err}");
    assert!(out.contains("street_ros2"), "{out}");
}

#[test]
fn sample_refuses_the_service_flags() {
    let out = std::env::temp_dir().join(format!("superflow-flags-sample-{}", std::process::id()));
    let out = out.to_str().unwrap();
    refuses_service_flags("sample", &["--mcap", DRIVE, "--out", out], SERVICE_FLAGS);
    assert!(!std::path::Path::new(out).exists(), "nothing was written");
}

#[test]
fn superpixels_refuses_the_service_flags() {
    refuses_service_flags("superpixels", &["--mcap", DRIVE], SERVICE_FLAGS);
}

#[test]
fn batch_reads_batch_size_and_run_wherever_they_stand_and_refuses_the_rest() {
    let dir = std::env::temp_dir().join(format!("superflow-flags-batch-{}", std::process::id()));
    std::fs::create_dir_all(&dir).unwrap();
    let file = |name: &str| -> PathBuf { dir.join(name) };
    let (before, after) = (file("before.bin"), file("after.bin"));
    let (b, a) = (before.to_str().unwrap(), after.to_str().unwrap());
    let runs: [&[&str]; 2] = [
        &[
            "--batch-size",
            "3",
            "--run",
            "flagged",
            "batch",
            "--mcap",
            DRIVE,
            "--out",
            b,
        ],
        &[
            "batch",
            "--mcap",
            DRIVE,
            "--out",
            a,
            "--batch-size",
            "3",
            "--run",
            "flagged",
        ],
    ];
    for args in runs {
        let (code, out, err) = run(args, &[]);
        assert_eq!(code, Some(0), "{args:?}: {err}");
        assert!(
            out.contains("wrote a batch of 3 samples"),
            "{args:?}: {out}"
        );
    }
    let bytes = std::fs::read(&before).unwrap();
    assert_eq!(bytes, std::fs::read(&after).unwrap(), "the same batch");
    assert!(
        bytes.windows(7).any(|w| w == b"flagged"),
        "--run names the batch's run in its header"
    );
    // The service's checks apply to the batch size as they do for the service.
    let (code, _, err) = run(
        &["batch", "--mcap", DRIVE, "--out", b, "--batch-size", "0"],
        &[],
    );
    assert_eq!(code, Some(1), "{err}");
    assert!(err.contains("service.batch_size"), "{err}");
    let others: Vec<(&str, &str)> = SERVICE_FLAGS
        .iter()
        .copied()
        .filter(|(flag, _)| !matches!(*flag, "--batch-size" | "--run"))
        .collect();
    refuses_service_flags("batch", &["--mcap", DRIVE, "--out", b], &others);
    std::fs::remove_dir_all(&dir).unwrap();
}

#[test]
fn the_service_reads_its_flags() {
    // Refused by the service's own checks, so each flag reached them: nothing is served.
    for (args, setting) in [
        (["--batch-size", "0"], "service.batch_size"),
        (["--world-size", "0"], "service.world_size"),
        (["--host-count", "0"], "service.host_count"),
    ] {
        let mut line = vec!["--mcap", DRIVE];
        line.extend(args);
        let (code, _, err) = run(&line, &[]);
        assert_eq!(code, Some(1), "{line:?}: {err}");
        assert!(err.contains(setting), "{line:?}: {err}");
    }
}
