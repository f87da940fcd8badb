//! Channel discovery: which channel is the LiDAR, which are cameras (images paired with
//! their calibration and, when recorded, a per-pixel class map), where the transforms
//! are — decided from schema names, encodings and topic structure, never from fixed
//! topic names. [`IngestConfig`] overrides any choice by topic.
//!
//! The schema recognition it starts from ([`schema_kind`]: [`SchemaKind`] and
//! [`Dialect`](crate::decode::Dialect)) lives in [`crate::decode::schema`], below both the decoders and this
//! module.

use super::index_cache::{CacheAccess, uid_of};
use crate::decode::{SchemaKind, schema_kind};
use crate::source::ChannelInfo;
use serde::{Deserialize, Serialize};
use std::path::PathBuf;

/// Overrides of the automatic choices (the `[ingest]` section of `pipeline.toml`).
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(default, deny_unknown_fields)]
pub struct IngestConfig {
    /// The LiDAR topic; by default the point-cloud channel with the most messages whose
    /// topic does not mention radar.
    pub lidar_topic: Option<String>,
    /// Image topics to use as cameras; by default every colour image channel.
    pub camera_topics: Vec<String>,
    /// Map (world) frame; by default the root of the ego frame's chain.
    pub map_frame: Option<String>,
    /// Ego frame; by default the first of `base_link`, `ego`, `ego_vehicle`, `vehicle`,
    /// `base_footprint` that the transforms mention.
    pub ego_frame: Option<String>,
    /// How far a transform lookup may extrapolate past the recorded samples, ms.
    pub tf_tolerance_ms: f64,
    /// The most input files kept open at once ([`HandlePool`](crate::source::HandlePool));
    /// by default the process's soft `RLIMIT_NOFILE` less 64 and one per rayon thread,
    /// at least 16
    /// ([`default_max_open_files`](crate::source::default_max_open_files)).
    pub max_open_files: Option<usize>,
    /// Where the index of every file indexed is kept for the next opening
    /// ([`IndexCache`](super::IndexCache)); `"off"` keeps none. By default the per-user
    /// cache directory (`$XDG_CACHE_HOME/superflow/index`, else `~/.cache/...`).
    pub index_cache: Option<PathBuf>,
    /// The permission bits of the index cache directory when the pipeline makes it, and
    /// the most it may grant: `0o700` by default. A cache shared by a group sets e.g.
    /// `0o2750` (the owner indexes, the group reads) or `0o2770`; a directory writable
    /// by every user is always refused.
    pub index_cache_mode: Option<u32>,
    /// The user (name or uid) whose entries are read besides this user's: the owner of
    /// a shared cache. By default only this user's entries are read.
    pub index_cache_owner: Option<String>,
    /// The most megabytes of entries the index cache keeps; the least recently used are
    /// evicted beyond it (default 8192).
    pub index_cache_max_mb: Option<u64>,
    /// Retries of one object-store request (503 SlowDown, 429, 5xx, timeouts, resets,
    /// bodies cut short), with exponential backoff and jitter, before the read fails
    /// (default 10).
    pub remote_retries: Option<usize>,
    /// The longest one object-store request may take, body included, in seconds; four
    /// times it bounds the retries of one request (default 30).
    pub remote_timeout_secs: Option<u64>,
    /// Object-store requests in flight at once, reads and prefetches (default 32).
    pub remote_concurrency: Option<usize>,
    /// Megabytes of chunks read from an object store ahead of the samples that need
    /// them (default 256; 0 turns prefetching off).
    pub remote_prefetch_mb: Option<u64>,
    /// A local directory that keeps the chunks read from object stores, keyed by URL,
    /// ETag and byte range, so that later epochs (and later runs) read them from disk;
    /// private to this user (made `0700`). Off by default.
    pub remote_cache_dir: Option<PathBuf>,
    /// The most bytes [`remote_cache_dir`](Self::remote_cache_dir) keeps, the least
    /// recently used evicted first (default 16 GiB). A read larger than it goes through.
    pub remote_cache_bytes: Option<u64>,
}

impl IngestConfig {
    /// The index cache [`index_cache`](Self::index_cache) names, `None` when off.
    pub fn index_cache(&self) -> Option<super::index_cache::IndexCache> {
        let access = self.index_cache_access();
        match &self.index_cache {
            Some(dir) if dir.as_os_str() == "off" => None,
            Some(dir) => Some(super::index_cache::IndexCache::with_access(dir, access)),
            None => super::index_cache::IndexCache::user_default(access),
        }
    }

    /// How the index cache is written and bounded (`index_cache_mode`, `_owner`,
    /// `_max_mb`); an owner that names no user trusts nobody more (the configuration's
    /// validation refuses it first).
    pub fn index_cache_access(&self) -> CacheAccess {
        let default = CacheAccess::default();
        CacheAccess {
            mode: self.index_cache_mode.unwrap_or(default.mode),
            owner: self.index_cache_owner.as_deref().and_then(uid_of),
            max_bytes: self
                .index_cache_max_mb
                .map_or(default.max_bytes, |mb| mb.saturating_mul(1 << 20)),
        }
    }

    /// How this process talks to object stores (`remote_*`), defaults filled in.
    pub fn remote_settings(&self) -> crate::source::remote::RemoteSettings {
        let default = crate::source::remote::RemoteSettings::default();
        crate::source::remote::RemoteSettings {
            retries: self.remote_retries.unwrap_or(default.retries),
            request_timeout: self
                .remote_timeout_secs
                .map_or(default.request_timeout, std::time::Duration::from_secs),
            concurrency: self
                .remote_concurrency
                .unwrap_or(default.concurrency)
                .max(1),
            prefetch_bytes: self
                .remote_prefetch_mb
                .map_or(default.prefetch_bytes, |mb| mb.saturating_mul(1 << 20)),
            part_bytes: default.part_bytes,
        }
    }

    /// Sets how this process talks to object stores (`remote_*`); before its first
    /// request, which builds the store's client.
    pub fn configure_remote(&self) {
        crate::source::remote::configure(self.remote_settings());
        crate::source::remote::configure_disk_cache(self.remote_cache());
    }

    /// The local chunk cache of remote reads, when `remote_cache_dir` is set.
    pub fn remote_cache(&self) -> Option<crate::source::remote::DiskCacheSettings> {
        self.remote_cache_dir
            .as_ref()
            .map(|dir| crate::source::remote::DiskCacheSettings {
                dir: dir.clone(),
                max_bytes: self.remote_cache_bytes.unwrap_or(16 << 30),
            })
    }

    /// [`max_open_files`](Self::max_open_files), or its default.
    pub fn max_open_files(&self) -> usize {
        self.max_open_files
            .unwrap_or_else(crate::source::default_max_open_files)
    }
}

impl Default for IngestConfig {
    fn default() -> Self {
        Self {
            lidar_topic: None,
            camera_topics: Vec::new(),
            map_frame: None,
            ego_frame: None,
            tf_tolerance_ms: 60.0,
            max_open_files: None,
            index_cache: None,
            index_cache_mode: None,
            index_cache_owner: None,
            index_cache_max_mb: None,
            remote_retries: None,
            remote_timeout_secs: None,
            remote_concurrency: None,
            remote_prefetch_mb: None,
            remote_cache_dir: None,
            remote_cache_bytes: None,
        }
    }
}

/// What a channel is used for.
#[derive(Debug, Clone, PartialEq, Eq, Serialize, Deserialize)]
#[serde(rename_all = "snake_case")]
pub enum Role {
    /// The LiDAR sweeps.
    Lidar,
    /// A camera's images.
    Image,
    /// A camera's calibration.
    Calibration,
    /// A camera's per-pixel class map (superpixels).
    Superpixels,
    /// A camera's SLIC superpixels precomputed by `superflow-pipeline superpixels`
    /// (channel metadata [`SLIC_SETTINGS_KEY`]).
    SlicSuperpixels,
    /// Time-varying transforms (`/tf`).
    Transforms,
    /// Static transforms (`/tf_static`).
    StaticTransforms,
    /// Per-point labels parallel to the LiDAR's sweeps: a point cloud of a
    /// `<drive>.labels.mcap` sidecar.
    Labels,
    /// Not used; the string says why.
    Ignored(String),
}

impl Role {
    /// The role's name as the JSON report spells it (`lidar`, `static_transforms`, ...).
    pub fn name(&self) -> &'static str {
        match self {
            Role::Lidar => "lidar",
            Role::Image => "image",
            Role::Calibration => "calibration",
            Role::Superpixels => "superpixels",
            Role::SlicSuperpixels => "slic_superpixels",
            Role::Transforms => "transforms",
            Role::StaticTransforms => "static_transforms",
            Role::Labels => "labels",
            Role::Ignored(_) => "ignored",
        }
    }
}

/// Trailing topic segments that name an image stream rather than a camera.
const IMAGE_SUFFIXES: [&str; 12] = [
    "compressed",
    "image_raw",
    "image_rect",
    "image_rect_color",
    "image_color",
    "image_rect_compressed",
    "image",
    "camera_info",
    "superpixels",
    "semantic",
    "segmentation",
    "labels",
];

/// The camera namespace of an image, calibration or class-map topic:
/// `/CAM_FRONT/image_rect_compressed` and `/CAM_FRONT/camera_info` → `/CAM_FRONT`,
/// `/cam_front/image_raw/compressed` → `/cam_front`.
pub fn camera_namespace(topic: &str) -> &str {
    let mut ns = topic.trim_end_matches('/');
    while let Some((head, last)) = ns.rsplit_once('/') {
        if IMAGE_SUFFIXES.contains(&last.to_ascii_lowercase().as_str()) && !head.is_empty() {
            ns = head;
        } else {
            break;
        }
    }
    ns
}

/// Channel metadata of a label cloud of a `<drive>.labels.mcap` sidecar: the LiDAR topic
/// whose sweeps it labels (needed only when the sidecar has several label clouds).
pub const LABELS_LIDAR_TOPIC_KEY: &str = "superflow.labels.lidar_topic";

/// Channel metadata of a precomputed SLIC channel: the settings it was computed with.
pub const SLIC_SETTINGS_KEY: &str = "superflow.slic.settings";
/// Channel metadata of a precomputed SLIC channel: the image topic it segments.
pub const SLIC_IMAGE_TOPIC_KEY: &str = "superflow.slic.image_topic";

/// Whether an image topic carries class ids rather than colour.
pub fn is_class_map_topic(topic: &str) -> bool {
    let t = topic.to_ascii_lowercase();
    ["superpixel", "semantic", "segment", "label", "class"]
        .iter()
        .any(|k| t.contains(k))
}

/// Assigns a role to every channel of a dataset. `message_counts` gives each topic's
/// message count (to choose the main LiDAR among several point clouds).
pub fn assign_roles(
    channels: &[&ChannelInfo],
    message_counts: &dyn Fn(&str) -> u64,
    config: &IngestConfig,
) -> Vec<(String, Role)> {
    let lidar = match &config.lidar_topic {
        Some(topic) => Some(topic.clone()),
        None => channels
            .iter()
            .filter(|c| matches!(schema_kind(c), Some((SchemaKind::PointCloud, _))))
            .filter(|c| !c.topic.to_ascii_lowercase().contains("radar"))
            .max_by(|a, b| {
                message_counts(&a.topic)
                    .cmp(&message_counts(&b.topic))
                    .then_with(|| b.topic.cmp(&a.topic))
            })
            .map(|c| c.topic.clone()),
    };
    let mut roles: Vec<(String, Role)> = channels
        .iter()
        .map(|c| {
            let role = match schema_kind(c) {
                None => Role::Ignored(format!(
                    "schema `{}` ({}) is not a sensor superflow reads",
                    c.schema_name(),
                    c.message_encoding
                )),
                Some((SchemaKind::PointCloud, _)) => {
                    if lidar.as_deref() == Some(c.topic.as_str()) {
                        Role::Lidar
                    } else {
                        Role::Ignored("a point cloud other than the chosen LiDAR".into())
                    }
                }
                Some((SchemaKind::CompressedImage | SchemaKind::RawImage, _)) => {
                    if c.metadata.contains_key(SLIC_SETTINGS_KEY) {
                        Role::SlicSuperpixels
                    } else if is_class_map_topic(&c.topic) {
                        Role::Superpixels
                    } else if c.topic.to_ascii_lowercase().contains("depth") {
                        Role::Ignored("a depth image".into())
                    } else if !config.camera_topics.is_empty()
                        && !config.camera_topics.contains(&c.topic)
                    {
                        Role::Ignored("not among the configured camera topics".into())
                    } else {
                        Role::Image
                    }
                }
                Some((SchemaKind::Calibration, _)) => Role::Calibration,
                Some((
                    SchemaKind::FrameTransform
                    | SchemaKind::FrameTransforms
                    | SchemaKind::TfMessage,
                    _,
                )) => {
                    if c.topic == "/tf_static" || c.topic.ends_with("/tf_static") {
                        Role::StaticTransforms
                    } else {
                        Role::Transforms
                    }
                }
            };
            (c.topic.clone(), role)
        })
        .collect();
    roles.sort_by(|a, b| a.0.cmp(&b.0));
    roles.dedup_by(|a, b| a.0 == b.0);
    roles
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn camera_namespaces_pair_images_with_calibrations() {
        assert_eq!(
            camera_namespace("/CAM_FRONT/image_rect_compressed"),
            "/CAM_FRONT"
        );
        assert_eq!(camera_namespace("/CAM_FRONT/camera_info"), "/CAM_FRONT");
        assert_eq!(
            camera_namespace("/cam_front/image_raw/compressed"),
            "/cam_front"
        );
        assert_eq!(camera_namespace("/cam_front/camera_info"), "/cam_front");
        assert_eq!(
            camera_namespace("/kitti/camera_color_left/image_raw"),
            "/kitti/camera_color_left"
        );
        assert_eq!(camera_namespace("/cam_front/superpixels"), "/cam_front");
        assert_eq!(camera_namespace("/image"), "/image");
        assert!(is_class_map_topic("/CAM_FRONT/superpixels"));
        assert!(!is_class_map_topic("/cam_front/image_raw/compressed"));
    }
}
