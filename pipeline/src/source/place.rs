//! Where files are: the questions drive discovery asks of a path — is it a directory,
//! is it a file, what `.mcap` files are in it, how large is it — answered alike for a
//! local path and an object URL. Object stores have no directories: a URL that does not
//! name an `.mcap` object is a prefix, and a prefix holds every object under it.

use super::error::SourceError;
use super::remote::{self, ObjectUrl};
use std::path::{Path, PathBuf};

/// Whether `path` names a directory (a local one, or a prefix in an object store).
pub fn is_dir(path: &Path) -> bool {
    match ObjectUrl::parse(path) {
        Some(url) => !url.key.ends_with(".mcap"),
        None => path.is_dir(),
    }
}

/// Whether `path` names a file (a local one, or an object: from its listing, or one
/// HEAD).
pub fn is_file(path: &Path) -> bool {
    if remote::is_remote(path) {
        return remote::object_size(path).is_some();
    }
    path.is_file()
}

/// The size of the file or object at `path`, if it can be had.
pub fn size_of(path: &Path) -> Option<u64> {
    if remote::is_remote(path) {
        return remote::object_size(path);
    }
    std::fs::metadata(path).ok().map(|m| m.len())
}

/// The `.mcap` files of the directory `dir`, sorted: a local directory's own (not its
/// subdirectories'), every `.mcap` object under a prefix (all listing pages).
pub fn mcap_files_in(dir: &Path) -> Result<Vec<PathBuf>, SourceError> {
    let is_mcap = |p: &Path| p.extension().is_some_and(|e| e == "mcap");
    if remote::is_remote(dir) {
        let listed = remote::list_dir(dir)?;
        return Ok(listed
            .into_iter()
            .map(|(p, _)| p)
            .filter(|p| is_mcap(p))
            .collect());
    }
    let io = |source| SourceError::Io {
        path: dir.to_path_buf(),
        source,
    };
    let mut found: Vec<PathBuf> = std::fs::read_dir(dir)
        .map_err(io)?
        .filter_map(|e| e.ok().map(|e| e.path()))
        .filter(|p| is_mcap(p))
        .collect();
    found.sort();
    Ok(found)
}

/// Runs `f`, whose rayon jobs read the files at `paths`, on a pool as wide as reads of
/// them should go: the current pool for local files (they keep the CPUs busy), one of
/// [`remote_concurrency`](super::remote::RemoteSettings::concurrency) threads when an
/// object is among them (its reads wait on the network).
pub fn on_read_pool<'p, T: Send>(
    mut paths: impl Iterator<Item = &'p Path>,
    f: impl FnOnce() -> T + Send,
) -> T {
    let threads = remote::settings().concurrency;
    if threads <= rayon::current_num_threads() || !paths.any(remote::is_remote) {
        return f();
    }
    match rayon::ThreadPoolBuilder::new()
        .num_threads(threads)
        .thread_name(|i| format!("read-{i}"))
        .build()
    {
        Ok(pool) => pool.install(f),
        Err(_) => f(),
    }
}
