//! `superflow-pipeline`'s subcommands run as a user runs them, one module each, and the
//! helpers that run the binary from the workspace root.

#![allow(clippy::unwrap_used, clippy::expect_used)] // tests fail loudly on purpose

mod flags;
mod inspect;
mod many_files;
mod sample;
mod superpixels;

use std::path::PathBuf;
use std::process::Command;

/// The workspace root.
pub fn root() -> PathBuf {
    PathBuf::from(env!("CARGO_MANIFEST_DIR"))
        .parent()
        .expect("the pipeline crate sits in the workspace")
        .to_path_buf()
}

/// `superflow-pipeline <subcommand> <args>` run from the workspace root: whether it
/// succeeded, its stdout and its stderr.
pub fn pipeline(subcommand: &str, args: &[&str]) -> (bool, String, String) {
    let out = Command::new(env!("CARGO_BIN_EXE_superflow-pipeline"))
        .arg(subcommand)
        .args(args)
        .current_dir(root())
        .output()
        .expect("the binary runs");
    (
        out.status.success(),
        String::from_utf8_lossy(&out.stdout).into_owned(),
        String::from_utf8_lossy(&out.stderr).into_owned(),
    )
}
