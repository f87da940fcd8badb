//! Running the `superflow-pipeline` binary from the workspace root, for the CLI tests.

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
