//! Finding the files of each drive among the inputs: `.mcap` files, directories of them,
//! rosbag2 directories (one drive in parts) and sidecars (`<name>.<tag>.mcap` joining the
//! drive of `<name>.mcap`). Inputs may be object URLs (`s3://bucket/prefix/`): a
//! prefix holds every `.mcap` object under it, and its sidecars are the objects beside
//! it (see [`crate::source::mcap_files_in`]).

use super::error::IngestError;
use crate::source::{self, SourceError};
use std::path::{Path, PathBuf};

/// Groups the inputs into drives: a rosbag2 directory (it holds `metadata.yaml`) is one
/// drive made of its `.mcap` files in name order; any other directory contributes each
/// of its `.mcap` files as a drive of its own; a file is a drive. Under a prefix of an
/// object store, each "directory" with a `metadata.yaml` is one rosbag2 drive. A sidecar —
/// `<name>.<tag>.mcap` next to `<name>.mcap`, e.g. `drive.superpixels.mcap` with class
/// maps computed offline — joins the drive of `<name>.mcap` (found next to it even when
/// only the drive is named) instead of being a drive of its own; so does
/// `<name>.labels.mcap` with per-point labels ([`LABELS_SIDECAR_TAG`]).
pub fn drive_groups(inputs: &[PathBuf]) -> Result<Vec<Vec<PathBuf>>, IngestError> {
    let mut groups: Vec<Vec<PathBuf>> = Vec::new();
    let mut listings = Listings::default();
    for input in inputs {
        let files = mcap_files(std::slice::from_ref(input))?;
        if !source::is_dir(input) {
            files_to_drives(files, &mut listings, &mut groups);
            continue;
        }
        listings.seed(&files);
        let mut bags: std::collections::BTreeMap<PathBuf, Vec<PathBuf>> = Default::default();
        let mut rest = Vec::new();
        for file in files {
            let dir = file.parent().map(Path::to_path_buf).unwrap_or_default();
            if listings.is_bag(&dir) {
                bags.entry(dir).or_default().push(file);
            } else {
                rest.push(file);
            }
        }
        groups.extend(bags.into_values());
        files_to_drives(rest, &mut listings, &mut groups);
    }
    for group in &mut groups {
        let mut seen = std::collections::BTreeSet::new();
        group.retain(|f| seen.insert(f.clone()));
    }
    Ok(groups)
}

/// Each of `files` a drive with its sidecars; the sidecars themselves join their base.
fn files_to_drives(files: Vec<PathBuf>, listings: &mut Listings, groups: &mut Vec<Vec<PathBuf>>) {
    for file in files {
        if sidecar_base(&file).is_some_and(|base| listings.is_file(&base)) {
            continue; // joins its base drive below
        }
        let mut group = vec![file.clone()];
        group.extend(listings.sidecars_of(&file));
        groups.push(group);
    }
}

/// The tag of a labels sidecar: `<drive>.labels.mcap` holds point clouds parallel to
/// the drive's LiDAR sweeps, one label field each (see [`super::labels`]).
pub const LABELS_SIDECAR_TAG: &str = "labels";

/// Whether `file` is a labels sidecar, `<name>.labels.mcap` (its point clouds are label
/// clouds, never a LiDAR).
pub fn is_labels_sidecar(file: &Path) -> bool {
    file.extension().is_some_and(|e| e == "mcap")
        && file
            .file_stem()
            .and_then(|s| s.to_str())
            .and_then(|stem| stem.rsplit_once('.'))
            .is_some_and(|(name, tag)| !name.is_empty() && tag == LABELS_SIDECAR_TAG)
}

/// `dir/<name>.mcap` for a sidecar `dir/<name>.<tag>.mcap`.
fn sidecar_base(file: &Path) -> Option<PathBuf> {
    let stem = file.file_stem()?.to_str()?; // <name>.<tag>
    let (name, tag) = stem.rsplit_once('.')?;
    (!name.is_empty() && !tag.is_empty()).then(|| file.with_file_name(format!("{name}.mcap")))
}

/// The `.mcap` file names of each directory, sorted, listed once: a directory of
/// thousands of drives (or a prefix of thousands of objects) is not listed again for
/// each drive's sidecars.
#[derive(Default)]
struct Listings {
    names: std::collections::HashMap<PathBuf, Vec<String>>,
    bags: std::collections::HashMap<PathBuf, bool>,
}

impl Listings {
    /// Takes in what listing an input found, directory by directory.
    fn seed(&mut self, files: &[PathBuf]) {
        for file in files {
            let (Some(dir), Some(name)) = (file.parent(), file.file_name()) else {
                continue;
            };
            let names = self.names.entry(dir.to_path_buf()).or_default();
            names.push(name.to_string_lossy().into_owned());
        }
        for names in self.names.values_mut() {
            names.sort();
            names.dedup();
        }
    }

    /// Whether `dir` is a rosbag2 directory (it holds `metadata.yaml`), asked once.
    fn is_bag(&mut self, dir: &Path) -> bool {
        *self
            .bags
            .entry(dir.to_path_buf())
            .or_insert_with(|| source::is_file(&dir.join("metadata.yaml")))
    }

    /// Whether the `.mcap` file `file` exists (from a listing when its directory was
    /// listed).
    fn is_file(&mut self, file: &Path) -> bool {
        match (file.parent(), file.file_name()) {
            (Some(dir), Some(name)) if self.names.contains_key(dir) => {
                let name = name.to_string_lossy();
                self.names[dir]
                    .binary_search_by(|n| n.as_str().cmp(&name))
                    .is_ok()
            }
            _ => source::is_file(file),
        }
    }

    /// Sidecars next to `file` (`<stem>.<tag>.mcap`), in name order.
    fn sidecars_of(&mut self, file: &Path) -> Vec<PathBuf> {
        let (Some(dir), Some(stem)) = (file.parent(), file.file_stem().and_then(|s| s.to_str()))
        else {
            return Vec::new();
        };
        let dir = if dir.as_os_str().is_empty() {
            Path::new(".")
        } else {
            dir
        };
        let names = self.names.entry(dir.to_path_buf()).or_insert_with(|| {
            let listed = source::mcap_files_in(dir).unwrap_or_else(|e| {
                // A store may allow GET but refuse LIST: the drive is still read.
                tracing::warn!(
                    "{e}: sidecars beside {} cannot be looked for",
                    file.display()
                );
                Vec::new()
            });
            let mut names: Vec<String> = listed
                .into_iter()
                .filter(|p| p.parent() == Some(dir))
                .filter_map(|p| Some(p.file_name()?.to_str()?.to_string()))
                .collect();
            names.sort();
            names
        });
        let prefix = format!("{stem}.");
        let first = names.partition_point(|n| n.as_str() < prefix.as_str());
        names[first..]
            .iter()
            .take_while(|n| n.starts_with(&prefix))
            .filter(|n| n.len() > prefix.len() + 5)
            .map(|n| file.with_file_name(n))
            .collect()
    }
}

/// All `.mcap` files named or inside the named directories, sorted per directory.
pub fn mcap_files(inputs: &[PathBuf]) -> Result<Vec<PathBuf>, IngestError> {
    let mut files = Vec::new();
    for input in inputs {
        if source::is_dir(input) {
            let found = source::mcap_files_in(input).map_err(|e| match e {
                SourceError::Io { path, source } => IngestError::Io { path, source },
                other => IngestError::Source(other),
            })?;
            if found.is_empty() && source::is_remote(input) {
                // A mistyped prefix lists nothing rather than failing: say which.
                return Err(IngestError::Io {
                    path: input.clone(),
                    source: std::io::Error::new(
                        std::io::ErrorKind::NotFound,
                        "no .mcap object under this prefix",
                    ),
                });
            }
            files.extend(found);
        } else {
            files.push(input.clone());
        }
    }
    if files.is_empty() {
        return Err(IngestError::NoFiles);
    }
    Ok(files)
}
