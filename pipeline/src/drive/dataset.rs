//! A dataset: many drives, each one or more MCAP files (a recording split in parts),
//! grouped by [`super::files`], in named groups ([`super::groups`]: `[[dataset]]` of
//! `pipeline.toml`). Every file is indexed on its own ([`index_file`]: from the index
//! cache, or scanned), all files of all groups in parallel (one per rayon thread at a
//! time); each drive joins its files' indexes ([`Drive::join`]) as soon as they are all
//! there. Drives come in input order, group after group, and the first error in input
//! order is returned, as if one file after the other.

use super::discover::IngestConfig;
use super::error::IngestError;
use super::files::drive_groups;
use super::groups::{DatasetGroup, DriveGroup};
use super::index::{Drive, IndexedBy, index_file};
use crate::source::SourceError;
use rayon::prelude::*;
use std::path::PathBuf;
use std::sync::atomic::{AtomicU64, AtomicUsize, Ordering};

/// Every drive of a dataset.
#[derive(Debug)]
pub struct Dataset {
    /// The drives, in input order.
    pub drives: Vec<Drive>,
    /// The named groups the drives were listed in, in order; together they hold every
    /// drive once. A dataset opened from plain inputs is one group, [`DEFAULT_GROUP`].
    ///
    /// [`DEFAULT_GROUP`]: super::groups::DEFAULT_GROUP
    pub groups: Vec<DriveGroup>,
    /// How the files' indexes were had.
    pub indexed: IndexStats,
}

/// How many files' indexes came from the index cache and how many from a scan.
#[derive(Debug, Clone, Copy, Default, PartialEq, Eq)]
pub struct IndexStats {
    /// Read from the index cache.
    pub from_cache: usize,
    /// Scanned (and stored in the cache, if there is one).
    pub scanned: usize,
    /// Scanned and not cacheable (no footer and summary to fingerprint).
    pub uncacheable: usize,
    /// Bytes of the files scanned.
    pub bytes_scanned: u64,
}

impl IndexStats {
    /// Every file.
    pub fn files(&self) -> usize {
        self.from_cache + self.scanned + self.uncacheable
    }
}

/// How far [`Dataset::open_with_progress`] has come.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub struct IndexProgress {
    /// Bytes indexed so far, over every drive (a file read from the index cache counts
    /// whole).
    pub bytes_done: u64,
    /// Bytes of every input file.
    pub bytes_total: u64,
    /// Files already indexed.
    pub files_done: usize,
    /// Every input file (drives and sidecars).
    pub files_total: usize,
}

/// One drive of [`Dataset::open_with_progress`]: joined (with how each file's index was
/// had, and the file's size), its first file error, or not joined because an earlier
/// file failed.
enum Opened {
    Joined(Box<Drive>, Vec<(IndexedBy, u64)>),
    Failed(SourceError),
    Skipped,
}

impl Dataset {
    /// Indexes every drive of `inputs` (files, directories, rosbag2 directories).
    pub fn open(inputs: &[PathBuf], config: &IngestConfig) -> Result<Dataset, IngestError> {
        Self::open_with_progress(inputs, config, |_| {})
    }

    /// [`Dataset::open`], reporting its [`IndexProgress`] as it goes. Files are indexed
    /// on several threads at once, so `progress` is called from several threads; the
    /// counts it gets only grow, though calls from two threads may arrive out of order.
    pub fn open_with_progress(
        inputs: &[PathBuf],
        config: &IngestConfig,
        progress: impl Fn(IndexProgress) + Sync,
    ) -> Result<Dataset, IngestError> {
        let all = [DatasetGroup::default_of(inputs.to_vec())];
        Self::open_groups(&all, config, progress)
    }

    /// Indexes the drives of every group (see [`Dataset::open_with_progress`]); a group
    /// whose inputs hold no drive is an error naming it.
    pub fn open_groups(
        listed: &[DatasetGroup],
        config: &IngestConfig,
        progress: impl Fn(IndexProgress) + Sync,
    ) -> Result<Dataset, IngestError> {
        // Before the first request: listing the inputs is one.
        config.configure_remote();
        let mut groups = Vec::new();
        let mut drive_groups_of = Vec::with_capacity(listed.len());
        for group in listed {
            let drives = drive_groups(&group.mcap).map_err(|e| match e {
                IngestError::NoFiles if listed.len() > 1 => IngestError::EmptyGroup {
                    group: group.name.clone(),
                },
                other => other,
            })?;
            let first = groups.len();
            groups.extend(drives);
            drive_groups_of.push(DriveGroup {
                name: group.name.clone(),
                repeat: group.repeat,
                drives: first..groups.len(),
            });
        }
        if groups.is_empty() || groups.iter().any(Vec::is_empty) {
            return Err(IngestError::NoFiles);
        }
        crate::source::HandlePool::global().set_limit(config.max_open_files());
        let cache = config.index_cache();
        if let Some(cache) = &cache {
            cache.prepare()?;
        }
        let files: Vec<&PathBuf> = groups.iter().flatten().collect();
        let bytes_total: u64 = files
            .par_iter()
            .map(|f| crate::source::size_of(f).unwrap_or(0))
            .sum();
        let files_total = files.len();
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
        // The lowest input position that failed: files after it are not indexed (their
        // result would be dropped), those before it still are (one of them may fail first).
        let first_failed = AtomicUsize::new(usize::MAX);
        let index_one = |i: usize, path: &PathBuf| {
            if i > first_failed.load(Ordering::Relaxed) {
                return None;
            }
            let mut reported = 0u64;
            let mut grow = |to: u64| {
                let grown = to.saturating_sub(reported);
                reported = reported.max(to);
                bytes_done.fetch_add(grown, Ordering::Relaxed) + grown
            };
            let indexed = index_file(path, cache.as_ref(), |done| {
                report(grow(done), files_done.load(Ordering::Relaxed))
            });
            match &indexed {
                Ok(indexed) => {
                    let bytes = grow(indexed.file.len());
                    report(bytes, files_done.fetch_add(1, Ordering::Relaxed) + 1);
                }
                Err(_) => {
                    first_failed.fetch_min(i, Ordering::Relaxed);
                }
            }
            Some(indexed)
        };
        let starts: Vec<usize> = groups
            .iter()
            .scan(0, |next, group| {
                let start = *next;
                *next += group.len();
                Some(start)
            })
            .collect();
        // Each drive is joined as soon as its files are indexed, so that the indexes of
        // files never all live at once (memory, and the time to fault it in).
        let index_all = || -> Vec<Opened> {
            groups
                .par_iter()
                .zip(&starts)
                // One drive, and within it one file, per task: files differ too much in size
                // to share out in runs.
                .with_max_len(1)
                .map(|(group, &start)| {
                    let files: Vec<_> = group
                        .par_iter()
                        .enumerate()
                        .with_max_len(1)
                        .map(|(k, path)| index_one(start + k, path))
                        .collect();
                    let mut indexed = Vec::with_capacity(files.len());
                    for file in files {
                        match file {
                            Some(Ok(file)) => indexed.push(file),
                            Some(Err(e)) => return Opened::Failed(e),
                            None => return Opened::Skipped,
                        }
                    }
                    if first_failed.load(Ordering::Relaxed) < start {
                        return Opened::Skipped; // an earlier drive's error returns
                    }
                    let by = indexed.iter().map(|f| (f.by, f.file.len())).collect();
                    Opened::Joined(Box::new(Drive::join(indexed, config)), by)
                })
                .collect()
        };
        // Files in an object store wait on the network, not the CPUs: more at once.
        let results = crate::source::on_read_pool(files.iter().map(|f| f.as_path()), index_all);
        let mut indexed = IndexStats::default();
        let mut drives = Vec::with_capacity(groups.len());
        for result in results {
            let (drive, by) = match result {
                Opened::Joined(drive, by) => (drive, by),
                Opened::Failed(e) => return Err(e.into()),
                // A skipped file comes after a failed one, whose error returns first.
                Opened::Skipped => unreachable!("a drive is skipped only after one that failed"),
            };
            for (by, len) in by {
                match by {
                    IndexedBy::Cache => indexed.from_cache += 1,
                    IndexedBy::Scan => indexed.scanned += 1,
                    IndexedBy::ScanUncacheable => indexed.uncacheable += 1,
                }
                if by != IndexedBy::Cache {
                    indexed.bytes_scanned += len;
                }
            }
            drives.push(*drive);
        }
        if let Some(cache) = &cache {
            cache.upkeep_if_grown();
        }
        Ok(Dataset {
            drives,
            groups: drive_groups_of,
            indexed,
        })
    }

    /// The group of drive `drive`.
    pub fn group_of(&self, drive: usize) -> Option<&DriveGroup> {
        self.groups.iter().find(|g| g.drives.contains(&drive))
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

    /// A directory with `names` as copies of the sample drives (`ros2`, `foxglove`) or
    /// files that are not MCAP (`bad`): `<i>_<name>.mcap`, in input order. Copies, not
    /// hard links: a link changes the sample drive's status-change time, and with it the
    /// fingerprint that tests running beside this one compute of it.
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
                        let drive =
                            superflow_recordings::sample_drive_path(&format!("street_{drive}"));
                        std::fs::copy(drive, &path).unwrap();
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
