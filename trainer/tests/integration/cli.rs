//! `superflow-trainer` refuses bad arguments with a clear message (the end-to-end tests
//! in `tests/` run it against a real pipeline).

#![allow(clippy::unwrap_used, clippy::expect_used)] // tests fail loudly on purpose

use std::process::Command;

fn trainer(args: &[&str]) -> (Option<i32>, String) {
    let out = Command::new(env!("CARGO_BIN_EXE_superflow-trainer"))
        .args(args)
        .env(
            "SUPERFLOW_IOX_PREFIX",
            format!("sftcli{}", std::process::id()),
        )
        .output()
        .unwrap();
    (
        out.status.code(),
        String::from_utf8_lossy(&out.stderr).into_owned(),
    )
}

#[test]
fn bad_arguments_are_clear_errors() {
    let (code, err) = trainer(&["--run", "x", "--rank", "2", "--world-size", "2"]);
    assert_eq!(code, Some(1), "{err}");
    assert!(
        err.contains("--rank 2 is not below --world-size 2"),
        "{err}"
    );
    let (code, err) = trainer(&["--run", "a/b"]);
    assert_eq!(code, Some(1), "{err}");
    assert!(err.contains("a/b"), "{err}");
    let (code, err) = trainer(&["--run", "x", "--iox-prefix", "bad prefix!"]);
    assert_eq!(code, Some(1), "{err}");
    assert!(err.contains("prefix"), "{err}");
}

#[test]
fn backends_are_named_from_a_closed_list() {
    // clap's usage errors: exit 2, the flag and every value it takes.
    let (code, err) = trainer(&["--run", "x", "--backend", "tpu"]);
    assert_eq!(code, Some(2), "{err}");
    assert!(
        err.contains("'tpu'") && err.contains("--backend") && err.contains("flex, wgpu, cuda"),
        "{err}"
    );
    let (code, err) = trainer(&["check", "--batch", "b.bin", "--backends", "flex,tpu"]);
    assert_eq!(code, Some(2), "{err}");
    assert!(err.contains("'tpu'") && err.contains("--backends"), "{err}");
}
