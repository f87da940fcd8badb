//! Listing prefixes, and what a listing learned of each object (size and ETag): opening
//! a listed object then costs no request, and a warm start of a thousand drives costs
//! the LIST pages alone. An object that was named but never listed costs one HEAD.

use super::store::{block_on, open_url, permit};
use crate::source::SourceError;
use futures::TryStreamExt;
use object_store::ObjectStoreExt as _;
use std::collections::HashMap;
use std::path::{Path, PathBuf};
use std::sync::{LazyLock, Mutex, PoisonError};

/// What a listing or HEAD said of one object.
#[derive(Debug, Clone, PartialEq, Eq)]
pub(super) struct Listed {
    pub(super) size: u64,
    /// `None` from a store that gives none (plain HTTP without ETag): reads are then
    /// not pinned to a version.
    pub(super) etag: Option<String>,
}

/// Every object listed or HEADed by this process, by URL.
static LISTED: LazyLock<Mutex<HashMap<PathBuf, Listed>>> = LazyLock::new(Default::default);

/// The prefixes listed whole (`s3://bucket/prefix/`): an object under one of them that
/// the listing did not return does not exist, without a HEAD to ask.
static PREFIXES: LazyLock<Mutex<Vec<String>>> = LazyLock::new(Default::default);

/// The object key of `url`, as object_store spells paths.
pub(super) fn location(key: &str) -> object_store::path::Path {
    object_store::path::Path::parse(key.trim_matches('/'))
        .unwrap_or_else(|_| object_store::path::Path::from(key.trim_matches('/')))
}

/// Every object under the prefix `dir` (all pages, sub-prefixes included), sorted by
/// URL, with its size. Object stores have no directories: a prefix names everything
/// under it.
pub fn list_dir(dir: &Path) -> Result<Vec<(PathBuf, u64)>, SourceError> {
    let (url, store) = open_url(dir)?;
    let prefix = location(&url.key);
    let listed = block_on(async move {
        let _permit = permit().await;
        let prefix = (!prefix.as_ref().is_empty()).then_some(prefix);
        store.list(prefix.as_ref()).try_collect::<Vec<_>>().await
    })
    .map_err(|e| super::source_error(dir, &url, e))?;
    let whole = format!("{}/", dir.display().to_string().trim_end_matches('/'));
    PREFIXES
        .lock()
        .unwrap_or_else(PoisonError::into_inner)
        .push(whole);
    let mut found: Vec<(PathBuf, u64)> = Vec::with_capacity(listed.len());
    let mut registry = LISTED.lock().unwrap_or_else(PoisonError::into_inner);
    for meta in listed {
        let object = url.with_key(meta.location.as_ref());
        registry.insert(
            object.clone(),
            Listed {
                size: meta.size,
                etag: meta.e_tag,
            },
        );
        found.push((object, meta.size));
    }
    found.sort();
    Ok(found)
}

/// The size of the object `path`, from a listing or one HEAD; `None` when there is
/// no such object (also when a listing of a prefix above it did not return it) or the
/// store cannot say.
pub fn object_size(path: &Path) -> Option<u64> {
    let text = path.display().to_string();
    let known = LISTED
        .lock()
        .unwrap_or_else(PoisonError::into_inner)
        .get(path)
        .map(|l| l.size);
    if known.is_some() {
        return known;
    }
    let under_listed = PREFIXES
        .lock()
        .unwrap_or_else(PoisonError::into_inner)
        .iter()
        .any(|prefix| text.starts_with(prefix.as_str()));
    if under_listed {
        return None;
    }
    listed(path).ok().map(|l| l.size)
}

/// What a listing said of `path`, or what one HEAD says.
pub(super) fn listed(path: &Path) -> Result<Listed, SourceError> {
    if let Some(known) = LISTED
        .lock()
        .unwrap_or_else(PoisonError::into_inner)
        .get(path)
    {
        return Ok(known.clone());
    }
    let (url, store) = open_url(path)?;
    let location = location(&url.key);
    let meta = block_on(async move {
        let _permit = permit().await;
        store.head(&location).await
    })
    .map_err(|e| super::source_error(path, &url, e))?;
    let known = Listed {
        size: meta.size,
        etag: meta.e_tag,
    };
    LISTED
        .lock()
        .unwrap_or_else(PoisonError::into_inner)
        .insert(path.to_path_buf(), known.clone());
    Ok(known)
}
