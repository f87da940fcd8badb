//! `pipeline.toml`: one serde struct with documented defaults (the paper's), validated
//! before use. Its sections:
//!
//! * `[ingest]` ([`IngestConfig`]): which channels and frames a drive is read with;
//! * `[sample]` with `[sample.slic]`, `[sample.augment]` and `[sample.voxel]`
//!   ([`SampleConfig`]): the sample recipe;
//! * `[service]` ([`ServiceConfig`]): the stream — mode, ranks and hosts, batch size,
//!   prefetch, epochs, subscriber waits;
//! * `[labels]` ([`LabelConfig`]): per-point semantic labels — field, mask, raw id →
//!   training class mapping, ignore index, class names (read only by `inspect` and by
//!   whoever asks for labels, e.g. a linear probe; samples never read them);
//! * `[[dataset]]` ([`DatasetGroup`]), any number: named groups of drives, each with
//!   its `repeat` per epoch (`--dataset` on the command line replaces them; `--mcap`
//!   adds a group of its own).
//!
//! `pipeline/pipeline.toml` lists every setting with its default and a comment.
//!
//! The command line's settings ([`Overrides`]) are laid over the file's in one place,
//! [`PipelineConfig::apply`], and the result is validated after.

use crate::drive::groups::validate_groups;
use crate::drive::{DatasetGroup, IngestConfig, LabelConfig};
use crate::publish::{Mode, Order, ServiceConfig};
use crate::sample::SampleConfig;
use serde::{Deserialize, Serialize};
use std::path::Path;
use superflow_common::InvalidSetting;

/// The pipeline's configuration file.
#[derive(Debug, Clone, Default, PartialEq, Serialize, Deserialize)]
#[serde(default, deny_unknown_fields)]
pub struct PipelineConfig {
    /// Channel and frame choices (`[ingest]`).
    pub ingest: IngestConfig,
    /// The sample recipe (`[sample]`, `[sample.augment]`, `[sample.slic]`,
    /// `[sample.voxel]`).
    pub sample: SampleConfig,
    /// The stream (`[service]`): mode, world size, batch size, prefetch, epochs.
    pub service: ServiceConfig,
    /// Per-point labels (`[labels]`, `[labels.mapping]`).
    pub labels: LabelConfig,
    /// Named groups of drives with their repeats (`[[dataset]]`); none by default.
    #[serde(skip_serializing_if = "Vec::is_empty")]
    pub dataset: Vec<DatasetGroup>,
}

/// `[service]` settings given on the command line: each one present replaces the file's
/// value, each one absent (`None`) keeps it.
#[derive(Debug, Clone, Copy, Default, PartialEq, Eq)]
pub struct Overrides {
    /// `[service] mode`.
    pub mode: Option<Mode>,
    /// `[service] world_size`; above 1 without a `mode` it also selects shard mode.
    pub world_size: Option<u32>,
    /// `[service] host_rank`.
    pub host_rank: Option<u32>,
    /// `[service] host_count`.
    pub host_count: Option<u32>,
    /// `[service] batch_size`.
    pub batch_size: Option<u32>,
    /// `[service] epochs`.
    pub epochs: Option<u64>,
    /// `[service] min_subscribers`.
    pub min_subscribers: Option<u32>,
    /// `[service] order`.
    pub order: Option<Order>,
}

/// A configuration file that cannot be used.
#[derive(Debug, thiserror::Error)]
pub enum ConfigError {
    /// Reading failed.
    #[error("reading {path}: {source}")]
    Io {
        /// The file.
        path: String,
        /// The error.
        source: std::io::Error,
    },
    /// Not valid TOML for this struct.
    #[error("{path}: {source}")]
    Parse {
        /// The file.
        path: String,
        /// The parser's message (line, column, field).
        source: toml::de::Error,
    },
    /// A value out of range.
    #[error("{path}: {source}")]
    Invalid {
        /// The file.
        path: String,
        /// The setting and what is wrong with it.
        source: InvalidSetting,
    },
}

impl PipelineConfig {
    /// Loads and validates a TOML file.
    pub fn load(path: &Path) -> Result<Self, ConfigError> {
        let name = path.display().to_string();
        let text = std::fs::read_to_string(path).map_err(|source| ConfigError::Io {
            path: name.clone(),
            source,
        })?;
        let mut config: PipelineConfig =
            toml::from_str(&text).map_err(|source| ConfigError::Parse {
                path: name.clone(),
                source,
            })?;
        config
            .validate()
            .map_err(|source| ConfigError::Invalid { path: name, source })?;
        let dir = path.parent().unwrap_or(Path::new(""));
        config.dataset = std::mem::take(&mut config.dataset)
            .into_iter()
            .map(|group| group.relative_to(dir))
            .collect();
        Ok(config)
    }

    /// Lays the command line's `overrides` over this (the file's) configuration: the low
    /// settings (file, defaults) give way to the high ones (flags). A `world_size` above 1
    /// with no `mode` given selects shard mode. Nothing is validated here: validate the
    /// result ([`ServiceConfig::validate`]) before use.
    pub fn apply(&mut self, overrides: &Overrides) {
        let service = &mut self.service;
        if let Some(mode) = overrides.mode {
            service.mode = mode;
        }
        if let Some(w) = overrides.world_size {
            service.world_size = w;
            if w > 1 && overrides.mode.is_none() {
                service.mode = Mode::Shard;
            }
        }
        if let Some(b) = overrides.batch_size {
            service.batch_size = b;
        }
        if let Some(h) = overrides.host_rank {
            service.host_rank = h;
        }
        if let Some(n) = overrides.host_count {
            service.host_count = n;
        }
        if let Some(e) = overrides.epochs {
            service.epochs = e;
        }
        if let Some(n) = overrides.min_subscribers {
            service.min_subscribers = n;
        }
        if let Some(order) = overrides.order {
            service.order = order;
        }
    }

    /// Checks ranges.
    pub fn validate(&self) -> Result<(), InvalidSetting> {
        let tol = self.ingest.tf_tolerance_ms;
        if !(tol.is_finite() && (0.0..=10_000.0).contains(&tol)) {
            return Err(InvalidSetting::new(
                "ingest.tf_tolerance_ms",
                tol,
                "is not in 0..=10000",
            ));
        }
        if self.ingest.max_open_files == Some(0) {
            return Err(InvalidSetting::new(
                "ingest.max_open_files",
                0,
                "must be at least 1",
            ));
        }
        if let Some(mode) = self.ingest.index_cache_mode
            && (mode > 0o7777 || mode & 0o700 != 0o700 || mode & 0o002 != 0)
        {
            return Err(InvalidSetting::new(
                "ingest.index_cache_mode",
                format!("0o{mode:o}"),
                "must give its owner rwx and others no write (e.g. 0o700, 0o2750, 0o2770)",
            ));
        }
        if let Some(owner) = &self.ingest.index_cache_owner
            && crate::drive::index_cache::uid_of(owner).is_none()
        {
            return Err(InvalidSetting::new(
                "ingest.index_cache_owner",
                owner,
                "names no user",
            ));
        }
        if self.ingest.index_cache_max_mb == Some(0) {
            return Err(InvalidSetting::new(
                "ingest.index_cache_max_mb",
                0,
                "must be at least 1",
            ));
        }
        self.sample.validate()?;
        self.service.validate()?;
        self.labels.validate()?;
        validate_groups(&self.dataset)
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::sample::KernelMaps;
    use std::path::PathBuf;

    #[test]
    fn parses_overrides_and_rejects_unknown_fields() {
        let config: PipelineConfig = toml::from_str(
            "[ingest]\nlidar_topic = \"/velodyne_points\"\ncamera_topics = [\"/cam/image\"]\ntf_tolerance_ms = 20.0\n",
        )
        .unwrap();
        assert_eq!(
            config.ingest.lidar_topic.as_deref(),
            Some("/velodyne_points")
        );
        assert_eq!(config.ingest.tf_tolerance_ms, 20.0);
        assert!(toml::from_str::<PipelineConfig>("[ingest]\nlidar = \"x\"\n").is_err());
        let mut bad = PipelineConfig::default();
        bad.ingest.tf_tolerance_ms = -1.0;
        assert!(bad.validate().is_err());
        let recipe: PipelineConfig = toml::from_str(
            "[sample]\ndelta_t_secs = 1.0\ntemporal_frames = 2\nedge = \"skip\"\nsuperpixels = \"slic\"\n\
             [sample.augment]\nshared = true\n[sample.voxel]\nkind = \"cartesian\"\nsize_m = [0.05, 0.05, 0.05]\n",
        )
        .unwrap();
        assert_eq!(recipe.sample.frame_offsets(), [-1, 0]);
        assert!(recipe.sample.augment.shared && recipe.sample.augment.scale_min == 0.95);
        assert_eq!(recipe.sample.kernel_maps, KernelMaps::Unet);
        let bare: PipelineConfig = toml::from_str("[sample]\nkernel_maps = \"none\"\n").unwrap();
        assert_eq!(bare.sample.kernel_maps, KernelMaps::None);
        let e = toml::from_str::<PipelineConfig>("[sample]\nkernel_maps = \"level0\"\n")
            .unwrap_err()
            .to_string();
        assert!(e.contains("unet") && e.contains("none"), "{e}");
        assert!(recipe.validate().is_ok());
        let mut bad = PipelineConfig::default();
        bad.sample.temporal_frames = 4;
        assert!(
            bad.validate()
                .unwrap_err()
                .to_string()
                .contains("temporal_frames")
        );
        bad.sample.temporal_frames = 3;
        bad.sample.augment.scale_min = 2.0;
        assert!(
            bad.validate()
                .unwrap_err()
                .to_string()
                .contains("scale_min")
        );
        // SLIC ids of a frame's images share 16 bits.
        bad.sample.augment.scale_min = 0.95;
        assert!(bad.validate().is_ok());
        bad.sample.slic.n_segments = 20_000;
        let e = bad.validate().unwrap_err().to_string();
        assert!(
            e.contains("slic.n_segments") && e.contains("cameras"),
            "{e}"
        );
        bad.sample.cameras = 1;
        assert!(bad.validate().is_ok());
    }

    #[test]
    fn the_example_file_holds_the_defaults_and_typos_are_errors() {
        let path = Path::new(env!("CARGO_MANIFEST_DIR")).join("pipeline.toml");
        assert_eq!(
            PipelineConfig::load(&path).expect("example parses"),
            PipelineConfig::default()
        );
        // Every setting is in the file (those without a default commented out).
        let text = std::fs::read_to_string(&path).unwrap();
        let file: toml::Table = toml::from_str(&text).unwrap();
        let defaults = toml::Table::try_from(PipelineConfig::default()).unwrap();
        assert_eq!(keys(&file, ""), keys(&defaults, ""));
        for optional in [
            "lidar_topic",
            "map_frame",
            "ego_frame",
            "field",
            "label_mask",
        ] {
            assert!(text.contains(&format!("\n# {optional} = ")), "{optional}");
        }
        let err =
            toml::from_str::<PipelineConfig>("[service]\nbatch_sise = 8\n").expect_err("typo");
        assert!(err.to_string().contains("batch_sise"), "{err}");
        let mut bad = PipelineConfig::default();
        bad.service.host_rank = 1;
        let err = bad.validate().unwrap_err();
        assert_eq!(err.setting, "service.host_rank");
        assert_eq!(
            err.to_string(),
            "service.host_rank = 1 must be below service.host_count = 1"
        );
    }

    #[test]
    fn the_labels_section_reads_a_mapping_and_a_mask() {
        let config: PipelineConfig = toml::from_str(
            "[labels]\nfield = \"label\"\nlabel_mask = 0xFFFF\nclasses = [\"car\", \"road\"]\n\
             [labels.mapping]\n10 = 0\n40 = 1\n0x30 = 255\n",
        )
        .unwrap();
        assert!(config.validate().is_ok());
        let labels = &config.labels;
        assert_eq!(labels.label_mask, Some(0xFFFF));
        assert_eq!(labels.ignore_index, 255);
        let map = labels.label_map().unwrap();
        assert_eq!(map.classes_of(&[10, 40, 48, 11]), Ok(vec![0, 1, 255, 255]));
        let bad: PipelineConfig =
            toml::from_str("[labels]\nclasses = [\"car\"]\n[labels.mapping]\n10 = 3\n").unwrap();
        let e = bad.validate().unwrap_err();
        assert_eq!(e.setting, "labels.mapping.10");
    }

    #[test]
    fn a_flag_overrides_the_files_value_and_an_absent_flag_keeps_it() {
        let mut config: PipelineConfig =
            toml::from_str("[service]\nbatch_size = 8\nepochs = 3\nmin_subscribers = 2\n").unwrap();
        config.apply(&Overrides {
            batch_size: Some(4),
            ..Overrides::default()
        });
        assert_eq!(config.service.batch_size, 4);
        assert_eq!(config.service.epochs, 3);
        assert_eq!(config.service.min_subscribers, 2);
        assert_eq!(config.service.mode, Mode::Broadcast);
        config.apply(&Overrides::default());
        assert_eq!(config.service.batch_size, 4);
        assert_eq!(config.service.epochs, 3);
        // A world size above 1 alone selects shard mode; given with a mode, the mode stands.
        let mut sharded = config.clone();
        sharded.apply(&Overrides {
            world_size: Some(2),
            ..Overrides::default()
        });
        assert_eq!(sharded.service.mode, Mode::Shard);
        assert!(sharded.service.validate().is_ok());
        config.apply(&Overrides {
            mode: Some(Mode::Broadcast),
            world_size: Some(2),
            ..Overrides::default()
        });
        assert_eq!(config.service.mode, Mode::Broadcast);
        assert_eq!(
            config.service.validate().unwrap_err().setting,
            "service.world_size"
        );
    }

    #[test]
    fn blocks_must_give_each_batch_distinct_blocks() {
        let mut config = PipelineConfig::default();
        config.apply(&Overrides {
            order: Some(Order::Blocks),
            world_size: Some(8),
            ..Overrides::default()
        });
        // 8 ranks of 4 over 16 open blocks: rank r's batch would take 2 blocks.
        let e = config.service.validate().unwrap_err();
        assert_eq!(e.setting, "service.open_blocks");
        assert!(e.to_string().contains("use 32"), "{e}");
        config.service.open_blocks = 32;
        assert!(config.service.validate().is_ok());
        // Any count prime to the ranks spreads a batch as well.
        config.service.open_blocks = 33;
        assert!(config.service.validate().is_ok());
        config.service.world_size = 1;
        config.service.open_blocks = 3;
        assert_eq!(
            config.service.validate().unwrap_err().setting,
            "service.open_blocks"
        );
    }

    #[test]
    fn dataset_groups_read_with_paths_relative_to_the_file() {
        let dir = std::env::temp_dir().join(format!("superflow-groups-{}", std::process::id()));
        std::fs::create_dir_all(&dir).unwrap();
        let path = dir.join("pipeline.toml");
        std::fs::write(
            &path,
            "[[dataset]]\nname = \"fleet\"\nmcap = [\"drives/fleet\", \"/abs/x.mcap\"]\n\n\
             [[dataset]]\nname = \"kitti\"\nmcap = [\"kitti\"]\nrepeat = 2.0\n",
        )
        .unwrap();
        let config = PipelineConfig::load(&path).unwrap();
        let groups: Vec<(&str, f64)> = config
            .dataset
            .iter()
            .map(|g| (g.name.as_str(), g.repeat))
            .collect();
        assert_eq!(groups, [("fleet", 1.0), ("kitti", 2.0)]);
        assert_eq!(
            config.dataset[0].mcap,
            [dir.join("drives/fleet"), PathBuf::from("/abs/x.mcap")]
        );
        std::fs::write(
            &path,
            "[[dataset]]\nname = \"a\"\nmcap = [\"x\"]\nrepeat = 0.0\n",
        )
        .unwrap();
        let e = PipelineConfig::load(&path).unwrap_err().to_string();
        assert!(e.contains("dataset[0].repeat"), "{e}");
        std::fs::remove_dir_all(dir).unwrap();
    }

    /// The dotted paths of every key of `table`.
    fn keys(table: &toml::Table, prefix: &str) -> Vec<String> {
        let mut out = Vec::new();
        for (key, value) in table {
            let path = format!("{prefix}{key}");
            if let toml::Value::Table(inner) = value {
                out.extend(keys(inner, &format!("{path}.")));
            }
            out.push(path);
        }
        out.sort();
        out
    }
}
