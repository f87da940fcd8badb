//! Dataset groups: a training set is rarely one collection of drives. A fleet's own cars
//! (two rigs), nuScenes and KITTI are listed as named groups (`[[dataset]]` of
//! `pipeline.toml`, or `--dataset NAME=PATH[,PATH...][:REPEAT]`), each with a `repeat`:
//! how many times per epoch each of its keyframes is served (2: twice; 0.5: half of
//! them, another half each epoch). [`DatasetGroup`] is what the user lists;
//! [`DriveGroup`] is the opened group, its drives consecutive in the dataset.
//! How repeats become an epoch is `sample::epochs`.

use serde::{Deserialize, Serialize};
use std::ops::Range;
use std::path::{Path, PathBuf};
use superflow_common::InvalidSetting;

/// The name of the group made of `--mcap` inputs.
pub const DEFAULT_GROUP: &str = "default";

/// The largest `repeat`: a keyframe served a thousand times an epoch is surely a typo.
pub const MAX_REPEAT: f64 = 1000.0;

fn one() -> f64 {
    1.0
}

/// One group of drives as listed: `[[dataset]]` of `pipeline.toml`.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct DatasetGroup {
    /// Its name in logs, `inspect` and `index`: 1 to 63 of `A-Z a-z 0-9 - _ .`.
    pub name: String,
    /// MCAP files, directories of them, or rosbag2 directories; relative paths in a
    /// configuration file are relative to the file's directory.
    pub mcap: Vec<PathBuf>,
    /// How many times each keyframe of the group is served per epoch (1): 2 serves each
    /// twice, 0.5 half of them (another half each epoch), 1.5 each once and half of them
    /// again. Counts per epoch are exact.
    #[serde(default = "one")]
    pub repeat: f64,
}

impl DatasetGroup {
    /// The group of `--mcap` inputs: [`DEFAULT_GROUP`], served once per epoch.
    pub fn default_of(inputs: Vec<PathBuf>) -> Self {
        Self {
            name: DEFAULT_GROUP.into(),
            mcap: inputs,
            repeat: 1.0,
        }
    }

    /// Parses `NAME=PATH[,PATH...][:REPEAT]` (the `--dataset` flag). A last `:` part that
    /// is not a number belongs to the path.
    pub fn parse(text: &str) -> Result<Self, InvalidSetting> {
        let invalid = |rule: &str| InvalidSetting::new("--dataset", text, rule);
        let (name, rest) = text
            .split_once('=')
            .ok_or_else(|| invalid("must be NAME=PATH[,PATH...][:REPEAT]"))?;
        // `https://host:9000` ends in a port, not a repeat.
        let port = |paths: &str| {
            let last = paths.rsplit(',').next().unwrap_or_default();
            last.split_once("://").is_some_and(|(scheme, rest)| {
                scheme.to_ascii_lowercase().starts_with("http") && !rest.contains('/')
            })
        };
        let (paths, repeat) = match rest.rsplit_once(':') {
            Some((paths, _)) if port(paths) => (rest, 1.0),
            Some((paths, r)) => match r.trim().parse::<f64>() {
                Ok(repeat) => (paths, repeat),
                Err(_) => (rest, 1.0),
            },
            None => (rest, 1.0),
        };
        let mcap: Vec<PathBuf> = paths
            .split(',')
            .filter(|p| !p.is_empty())
            .map(PathBuf::from)
            .collect();
        let group = Self {
            name: name.trim().to_string(),
            mcap,
            repeat,
        };
        group.validate("--dataset")?;
        Ok(group)
    }

    /// Relative paths made relative to `dir` (a configuration file's directory); object
    /// URLs stay as they are.
    pub fn relative_to(mut self, dir: &Path) -> Self {
        for path in &mut self.mcap {
            // An object URL parses as a relative path; it names the same object anywhere.
            if path.is_relative() && !crate::source::is_remote(path) {
                *path = dir.join(&*path);
            }
        }
        self
    }

    /// Checks the name, the paths and the repeat; `at` names where the group was given
    /// (`dataset[1]`, `--dataset`).
    pub fn validate(&self, at: &str) -> Result<(), InvalidSetting> {
        let valid_name = !self.name.is_empty()
            && self.name.len() < 64
            && self
                .name
                .bytes()
                .all(|b| b.is_ascii_alphanumeric() || b"-_.".contains(&b));
        if !valid_name {
            return Err(InvalidSetting::new(
                format!("{at}.name"),
                &self.name,
                "must be 1 to 63 characters of A-Z a-z 0-9 - _ .",
            ));
        }
        if self.mcap.is_empty() {
            return Err(InvalidSetting::new(
                format!("{at}.mcap"),
                "[]",
                format!("lists no file or directory for group `{}`", self.name),
            ));
        }
        if !(self.repeat.is_finite() && self.repeat > 0.0 && self.repeat <= MAX_REPEAT) {
            return Err(InvalidSetting::new(
                format!("{at}.repeat"),
                self.repeat,
                format!("must be above 0 and at most {MAX_REPEAT}"),
            ));
        }
        Ok(())
    }
}

/// Checks every group and that their names differ.
pub fn validate_groups(groups: &[DatasetGroup]) -> Result<(), InvalidSetting> {
    for (i, group) in groups.iter().enumerate() {
        group.validate(&format!("dataset[{i}]"))?;
        if groups[..i].iter().any(|g| g.name == group.name) {
            return Err(InvalidSetting::new(
                format!("dataset[{i}].name"),
                &group.name,
                "is the name of an earlier group",
            ));
        }
    }
    Ok(())
}

/// An opened group: its drives are `drives` of the dataset.
#[derive(Debug, Clone, PartialEq)]
pub struct DriveGroup {
    /// The group's name.
    pub name: String,
    /// Serves per keyframe and epoch.
    pub repeat: f64,
    /// Its drives in the dataset.
    pub drives: Range<usize>,
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn the_flag_reads_name_paths_and_repeat() {
        let g = DatasetGroup::parse("kitti=/data/kitti,/data/more:2.5").unwrap();
        assert_eq!(g.name, "kitti");
        assert_eq!(
            g.mcap,
            [PathBuf::from("/data/kitti"), PathBuf::from("/data/more")]
        );
        assert_eq!(g.repeat, 2.5);
        let g = DatasetGroup::parse("fleet=drives").unwrap();
        assert_eq!((g.mcap.len(), g.repeat), (1, 1.0));
        // A colon that is not followed by a number is part of the path.
        let g = DatasetGroup::parse("odd=/mnt/a:b").unwrap();
        assert_eq!(g.mcap, [PathBuf::from("/mnt/a:b")]);
        for bad in [
            "noequals", "=x", "a=", "a=x:0", "a=x:-1", "a=x:inf", "sp ace=x",
        ] {
            assert!(DatasetGroup::parse(bad).is_err(), "{bad}");
        }
        let e = DatasetGroup::parse("a=x:0").unwrap_err();
        assert_eq!(e.setting, "--dataset.repeat");
    }

    #[test]
    fn names_are_unique_and_relative_paths_follow_the_file() {
        let a = DatasetGroup::parse("a=x").unwrap();
        let b = DatasetGroup::parse("b=/abs:0.5").unwrap();
        assert!(validate_groups(&[a.clone(), b.clone()]).is_ok());
        let e = validate_groups(&[a.clone(), b, a.clone()]).unwrap_err();
        assert_eq!(e.setting, "dataset[2].name");
        let moved = a.relative_to(Path::new("/etc/superflow"));
        assert_eq!(moved.mcap, [PathBuf::from("/etc/superflow/x")]);
        let absolute = DatasetGroup::parse("b=/abs").unwrap();
        assert_eq!(absolute.clone().relative_to(Path::new("/etc")), absolute);
    }
}
