//! Object URLs where a path goes: `s3://bucket/key`, `gs://…`, `az://…` (and the other
//! spellings [`object_store`] parses) and `http(s)://…`. A URL travels through the
//! pipeline as a [`Path`] holding its text unchanged, so that everything above
//! `source/` (drive grouping, sidecars, skip reports) works on it as on a local path;
//! only this module tells the two apart.

use std::path::{Path, PathBuf};

/// The URL schemes read through an object store.
const SCHEMES: &[&str] = &[
    "s3://", "s3a://", "gs://", "az://", "adl://", "azure://", "abfs://", "abfss://", "http://",
    "https://",
];

/// Whether `path` is an object URL rather than a local path.
pub fn is_remote(path: &Path) -> bool {
    path.to_str().is_some_and(|s| {
        SCHEMES
            .iter()
            .any(|scheme| s.len() > scheme.len() && s[..scheme.len()].eq_ignore_ascii_case(scheme))
    })
}

/// An object URL split into what names its store (`scheme://bucket`) and the key in it.
#[derive(Debug, Clone, PartialEq, Eq, Hash)]
pub struct ObjectUrl {
    /// `s3://bucket`, `https://host:port`: one client per store.
    pub store: String,
    /// The key inside the store, without a leading `/` (may be empty or end with `/`).
    pub key: String,
}

impl ObjectUrl {
    /// Splits `path` when it is an object URL.
    pub fn parse(path: &Path) -> Option<ObjectUrl> {
        if !is_remote(path) {
            return None;
        }
        let text = path.to_str()?;
        let (scheme, rest) = text.split_once("://")?;
        let (authority, key) = rest.split_once('/').unwrap_or((rest, ""));
        if authority.is_empty() {
            return None;
        }
        Some(ObjectUrl {
            store: format!("{}://{authority}", scheme.to_ascii_lowercase()),
            key: key.to_string(),
        })
    }

    /// The scheme, lower case (`s3`, `gs`, `https`, …).
    pub fn scheme(&self) -> &str {
        self.store.split_once("://").map_or("", |(s, _)| s)
    }

    /// The URL of `key` in the same store.
    pub fn with_key(&self, key: &str) -> PathBuf {
        PathBuf::from(format!("{}/{key}", self.store))
    }

    /// The whole URL.
    pub fn to_path(&self) -> PathBuf {
        self.with_key(&self.key)
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn urls_split_into_store_and_key() {
        let url = ObjectUrl::parse(Path::new("s3://drives/fleet/a.mcap")).unwrap();
        assert_eq!(url.store, "s3://drives");
        assert_eq!(url.key, "fleet/a.mcap");
        assert_eq!(url.scheme(), "s3");
        assert_eq!(url.to_path(), Path::new("s3://drives/fleet/a.mcap"));
        let prefix = ObjectUrl::parse(Path::new("gs://b/")).unwrap();
        assert_eq!((prefix.store.as_str(), prefix.key.as_str()), ("gs://b", ""));
        let http = ObjectUrl::parse(Path::new("https://host:9000/x/y.mcap")).unwrap();
        assert_eq!(
            (http.store.as_str(), http.key.as_str()),
            ("https://host:9000", "x/y.mcap")
        );
        for local in [
            "drives/a.mcap",
            "/data/s3/a.mcap",
            "s3:/a",
            "s3://",
            "./s3://x",
        ] {
            assert!(ObjectUrl::parse(Path::new(local)).is_none(), "{local}");
        }
    }

    #[test]
    fn a_url_keeps_its_text_through_path_operations() {
        let file = Path::new("s3://b/dir/drive.mcap");
        assert_eq!(
            file.with_file_name("drive.labels.mcap"),
            Path::new("s3://b/dir/drive.labels.mcap")
        );
        assert!(is_remote(&file.with_file_name("x.mcap")));
        assert_eq!(file.file_stem().unwrap(), "drive");
    }
}
