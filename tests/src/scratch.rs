//! Temporary directories of the end-to-end tests. Tests of every module run side by side
//! in one test process, and test processes may run at once: a directory is named by its
//! module, its test and the process id, `<tmp>/superflow-<module>-<name>-<pid>`, so no
//! two of them meet.

#![allow(clippy::unwrap_used, clippy::expect_used)] // test support fails loudly

use std::path::PathBuf;

/// `<tmp>/superflow-<module>-<name>-<pid>`: test `name`'s directory of the test module
/// `module` in this test process; nothing is done to it.
pub fn path(module: &str, name: &str) -> PathBuf {
    std::env::temp_dir().join(format!("superflow-{module}-{name}-{}", std::process::id()))
}

/// [`path`], created empty: whatever an earlier run left there is removed first.
pub fn dir(module: &str, name: &str) -> PathBuf {
    let dir = vacant(module, name);
    std::fs::create_dir_all(&dir).unwrap();
    dir
}

/// [`path`], removed if an earlier run left it and not created: for a directory that a
/// child process makes itself (a trainer's `--out`).
pub fn vacant(module: &str, name: &str) -> PathBuf {
    let dir = path(module, name);
    let _ = std::fs::remove_dir_all(&dir);
    dir
}

/// `bytes` written as the file `file` into `<tmp>/superflow-<module>-<pid>`, the
/// directory the tests of `module` share in this test process (created when missing,
/// never emptied: each test names its own files); the file's path.
pub fn file(module: &str, file: &str, bytes: &[u8]) -> PathBuf {
    let dir = std::env::temp_dir().join(format!("superflow-{module}-{}", std::process::id()));
    std::fs::create_dir_all(&dir).unwrap();
    let path = dir.join(file);
    std::fs::write(&path, bytes).unwrap();
    path
}
