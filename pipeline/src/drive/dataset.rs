//! A dataset: many drives, each one or more MCAP files (a recording split in parts),
//! grouped by [`super::files`] and each indexed by [`Drive::open`](super::Drive::open).
//! Drives are indexed in parallel (one per rayon thread at a time), the result in input
//! order and the first error in input order returned, as if one after the other.

use super::discover::IngestConfig;
use super::error::IngestError;
use super::files::drive_groups;
use super::index::Drive;
use crate::source::McapFile;
use rayon::prelude::*;
use std::path::PathBuf;
use std::sync::atomic::{AtomicU64, AtomicUsize, Ordering};

/// Every drive of a dataset.
#[derive(Debug)]
pub struct Dataset {
    /// The drives, in input order.
    pub drives: Vec<Drive>,
}

/// How far [`Dataset::open_with_progress`] has come.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub struct IndexProgress {
    /// Bytes indexed so far, over every drive.
    pub bytes_done: u64,
    /// Bytes of every input file.
    pub bytes_total: u64,
    /// Files of drives already indexed.
    pub files_done: usize,
    /// Every input file (drives and sidecars).
    pub files_total: usize,
}

impl Dataset {
    /// Indexes every drive of `inputs` (files, directories, rosbag2 directories).
    pub fn open(inputs: &[PathBuf], config: &IngestConfig) -> Result<Dataset, IngestError> {
        Self::open_with_progress(inputs, config, |_| {})
    }

    /// [`Dataset::open`], reporting its [`IndexProgress`] as it goes. Drives are indexed
    /// on several threads at once, so `progress` is called from several threads; the
    /// counts it gets only grow, though calls from two threads may arrive out of order.
    pub fn open_with_progress(
        inputs: &[PathBuf],
        config: &IngestConfig,
        progress: impl Fn(IndexProgress) + Sync,
    ) -> Result<Dataset, IngestError> {
        let groups = drive_groups(inputs)?;
        let sizes: Vec<u64> = groups
            .iter()
            .map(|files| {
                files
                    .iter()
                    .map(|f| std::fs::metadata(f).map_or(0, |m| m.len()))
                    .sum()
            })
            .collect();
        let bytes_total: u64 = sizes.iter().sum();
        let files_total: usize = groups.iter().map(Vec::len).sum();
        let bytes_done = AtomicU64::new(0);
        let files_done = AtomicUsize::new(0);
        let report = |bytes: u64, files: usize| {
            progress(IndexProgress {
                bytes_done: bytes,
                bytes_total,
                files_done: files,
                files_total,
            })
        };
        // The lowest input position that failed: drives after it are not indexed (their
        // result would be dropped), those before it still are (one of them may fail first).
        let first_failed = AtomicUsize::new(usize::MAX);
        let results: Vec<Option<Result<Drive, IngestError>>> = groups
            .par_iter()
            .enumerate()
            // One drive per task: a drive is large enough to share out.
            .with_max_len(1)
            .map(|(i, files)| {
                if i > first_failed.load(Ordering::Relaxed) {
                    return None;
                }
                let mut reported = 0u64;
                let opened = Drive::open_with_progress(files, config, |d, _| {
                    let grown = d.saturating_sub(reported);
                    reported = reported.max(d);
                    let bytes = bytes_done.fetch_add(grown, Ordering::Relaxed) + grown;
                    report(bytes, files_done.load(Ordering::Relaxed));
                });
                match &opened {
                    Ok(drive) => {
                        let len: u64 = drive.files.iter().map(McapFile::len).sum();
                        let grown = len.saturating_sub(reported);
                        let bytes = bytes_done.fetch_add(grown, Ordering::Relaxed) + grown;
                        let files =
                            files_done.fetch_add(files.len(), Ordering::Relaxed) + files.len();
                        report(bytes, files);
                    }
                    Err(_) => {
                        first_failed.fetch_min(i, Ordering::Relaxed);
                    }
                }
                Some(opened)
            })
            .collect();
        let mut drives = Vec::with_capacity(results.len());
        for result in results {
            // A skipped drive comes after a failed one, whose error returns first.
            let Some(result) = result else { break };
            drives.push(result?);
        }
        debug_assert_eq!(drives.len(), sizes.len());
        Ok(Dataset { drives })
    }

    /// Checks every drive ([`Drive::check_sensors`]).
    pub fn check_sensors(&self) -> Result<(), IngestError> {
        self.drives.iter().try_for_each(Drive::check_sensors)
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use std::path::Path;
    use std::sync::Mutex;

    fn sample_drive(name: &str) -> PathBuf {
        Path::new(env!("CARGO_MANIFEST_DIR")).join(format!("../recordings/drives/{name}.mcap"))
    }

    /// A directory with `names` as hard links of the sample drives (`ros2`, `foxglove`) or
    /// files that are not MCAP (`bad`): `<i>_<name>.mcap`, in input order.
    fn inputs(tag: &str, names: &[&str]) -> (PathBuf, Vec<PathBuf>) {
        let dir =
            std::env::temp_dir().join(format!("superflow-dataset-{tag}-{}", std::process::id()));
        let _ = std::fs::remove_dir_all(&dir);
        std::fs::create_dir_all(&dir).unwrap();
        let paths = names
            .iter()
            .enumerate()
            .map(|(i, name)| {
                let path = dir.join(format!("{i}_{name}.mcap"));
                match *name {
                    "bad" => std::fs::write(&path, b"not an mcap file").unwrap(),
                    drive => {
                        std::fs::hard_link(sample_drive(&format!("street_{drive}")), &path).unwrap()
                    }
                }
                path
            })
            .collect();
        (dir, paths)
    }

    fn on_threads<T: Send>(f: impl FnOnce() -> T + Send) -> T {
        rayon::ThreadPoolBuilder::new()
            .num_threads(4)
            .build()
            .unwrap()
            .install(f)
    }

    #[test]
    fn drives_keep_input_order_and_progress_reaches_the_total() {
        let names = ["foxglove", "ros2", "foxglove", "ros2", "ros2"];
        let (dir, paths) = inputs("order", &names);
        let seen = Mutex::new(Vec::new());
        let dataset = on_threads(|| {
            Dataset::open_with_progress(&paths, &IngestConfig::default(), |p| {
                seen.lock().unwrap().push(p)
            })
        })
        .unwrap();
        let opened: Vec<&Path> = dataset.drives.iter().map(|d| d.files[0].path()).collect();
        assert_eq!(
            opened,
            paths.iter().map(PathBuf::as_path).collect::<Vec<_>>()
        );
        for (drive, path) in dataset.drives.iter().zip(&paths) {
            let alone = Drive::open(std::slice::from_ref(path), &IngestConfig::default()).unwrap();
            assert_eq!(drive.skipped, alone.skipped);
            assert_eq!(
                drive.lidar.as_ref().map(|l| l.sweeps.len()),
                alone.lidar.as_ref().map(|l| l.sweeps.len())
            );
        }
        let seen = seen.into_inner().unwrap();
        let total: u64 = paths
            .iter()
            .map(|p| std::fs::metadata(p).unwrap().len())
            .sum();
        let last = seen
            .iter()
            .max_by_key(|p| (p.files_done, p.bytes_done))
            .unwrap();
        assert_eq!(
            *last,
            IndexProgress {
                bytes_done: total,
                bytes_total: total,
                files_done: names.len(),
                files_total: names.len(),
            }
        );
        assert!(seen.iter().all(|p| p.bytes_done <= total));
        std::fs::remove_dir_all(dir).unwrap();
    }

    #[test]
    fn the_first_error_in_input_order_wins() {
        let (dir, paths) = inputs("errors", &["ros2", "foxglove", "bad", "ros2", "bad"]);
        for _ in 0..3 {
            let err = on_threads(|| Dataset::open(&paths, &IngestConfig::default())).unwrap_err();
            let text = err.to_string();
            assert!(text.contains("2_bad.mcap"), "{text}");
            assert!(text.contains("not an MCAP file"), "{text}");
        }
        std::fs::remove_dir_all(dir).unwrap();
    }
}
