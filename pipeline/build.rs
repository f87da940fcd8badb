//! The index cache's build identity (`SUPERFLOW_INDEX_BUILD`): a hash of the code that
//! decides what an index entry holds — the pipeline's sources other than the binaries
//! and the publisher, the sensor schemas, and the locked dependency versions (the MCAP,
//! protobuf and image decoders). An entry written by a build of another identity is
//! never read, so a change to indexing cannot be served stale entries even when nobody
//! remembers to raise a format version by hand. A change anywhere else in those sources
//! also re-indexes once; that costs one scan per file, never a wrong index.

use std::path::{Path, PathBuf};

/// Folders of `src/` that cannot change what indexing learns from a file.
const NOT_INDEXING: [&str; 2] = ["bin", "publish"];

fn main() {
    let manifest = PathBuf::from(std::env::var_os("CARGO_MANIFEST_DIR").expect("set by cargo"));
    let mut sources = Vec::new();
    collect(&manifest.join("src"), &manifest, &mut sources);
    let workspace = manifest.parent().unwrap_or(&manifest);
    collect(
        &workspace.join("schemas").join("src"),
        workspace,
        &mut sources,
    );
    let lock = workspace.join("Cargo.lock");
    if lock.is_file() {
        sources.push((PathBuf::from("Cargo.lock"), lock));
    }
    sources.sort();
    let mut hash = xxhash_rust::xxh3::Xxh3::new();
    for (name, path) in &sources {
        hash.update(name.to_string_lossy().as_bytes());
        hash.update(&[0]);
        hash.update(&std::fs::read(path).unwrap_or_default());
        hash.update(&[0]);
    }
    println!(
        "cargo:rustc-env=SUPERFLOW_INDEX_BUILD={:016x}",
        hash.digest()
    );
    println!("cargo:rerun-if-changed=src");
    println!("cargo:rerun-if-changed=../schemas/src");
    println!("cargo:rerun-if-changed=../Cargo.lock");
}

/// Every file under `dir` (but the folders of [`NOT_INDEXING`] right under `src/`), with
/// its name relative to `root`.
fn collect(dir: &Path, root: &Path, out: &mut Vec<(PathBuf, PathBuf)>) {
    let Ok(entries) = std::fs::read_dir(dir) else {
        return;
    };
    for entry in entries.flatten() {
        let path = entry.path();
        let name = path.strip_prefix(root).unwrap_or(&path).to_path_buf();
        if path.is_dir() {
            let skipped = NOT_INDEXING
                .iter()
                .any(|n| name == Path::new("src").join(n));
            if !skipped {
                collect(&path, root, out);
            }
        } else {
            out.push((name, path));
        }
    }
}
