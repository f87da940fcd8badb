//! Finding the files of each drive among the inputs: `.mcap` files, directories of them,
//! rosbag2 directories (one drive in parts) and sidecars (`<name>.<tag>.mcap` joining the
//! drive of `<name>.mcap`).

use super::error::IngestError;
use std::path::{Path, PathBuf};

/// Groups the inputs into drives: a rosbag2 directory (it holds `metadata.yaml`) is one
/// drive made of its `.mcap` files in name order; any other directory contributes each
/// of its `.mcap` files as a drive of its own; a file is a drive. A sidecar —
/// `<name>.<tag>.mcap` next to `<name>.mcap`, e.g. `drive.superpixels.mcap` with class
/// maps computed offline — joins the drive of `<name>.mcap` (found next to it even when
/// only the drive is named) instead of being a drive of its own; so does
/// `<name>.labels.mcap` with per-point labels ([`LABELS_SIDECAR_TAG`]).
pub fn drive_groups(inputs: &[PathBuf]) -> Result<Vec<Vec<PathBuf>>, IngestError> {
    let mut groups: Vec<Vec<PathBuf>> = Vec::new();
    let mut listings = Listings::default();
    for input in inputs {
        let files = mcap_files(std::slice::from_ref(input))?;
        if input.is_dir() && input.join("metadata.yaml").is_file() {
            groups.push(files);
        } else {
            for file in files {
                if sidecar_base(&file).is_some_and(|base| base.is_file()) {
                    continue; // joins its base drive below
                }
                let mut group = vec![file.clone()];
                group.extend(listings.sidecars_of(&file));
                groups.push(group);
            }
        }
    }
    for group in &mut groups {
        let mut seen = std::collections::BTreeSet::new();
        group.retain(|f| seen.insert(f.clone()));
    }
    Ok(groups)
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
/// thousands of drives is not listed again for each drive's sidecars.
#[derive(Default)]
struct Listings(std::collections::HashMap<PathBuf, Vec<String>>);

impl Listings {
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
        let names = self.0.entry(dir.to_path_buf()).or_insert_with(|| {
            let mut names: Vec<String> = std::fs::read_dir(dir)
                .map(|entries| {
                    entries
                        .filter_map(|e| e.ok()?.file_name().into_string().ok())
                        .filter(|n| n.ends_with(".mcap"))
                        .collect()
                })
                .unwrap_or_default();
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
        if input.is_dir() {
            let io = |source| IngestError::Io {
                path: input.clone(),
                source,
            };
            let mut found: Vec<PathBuf> = std::fs::read_dir(input)
                .map_err(io)?
                .filter_map(|e| e.ok().map(|e| e.path()))
                .filter(|p| p.extension().is_some_and(|e| e == "mcap"))
                .collect();
            found.sort();
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
