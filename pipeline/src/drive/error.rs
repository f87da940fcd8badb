//! Why a dataset cannot be used for training ([`IngestError`]).

use super::index_cache::CacheError;
use crate::source::SourceError;
use std::path::PathBuf;

/// Why a dataset cannot be used for training (it can still be inspected).
#[derive(Debug, thiserror::Error)]
pub enum IngestError {
    /// No input files.
    #[error("no MCAP files given")]
    NoFiles,
    /// A dataset group whose inputs hold no MCAP file.
    #[error("dataset group `{group}`: no MCAP files in its inputs")]
    EmptyGroup {
        /// The group's name.
        group: String,
    },
    /// A file could not be opened or is not MCAP.
    #[error(transparent)]
    Source(#[from] SourceError),
    /// The index cache is refused (others may write it).
    #[error(transparent)]
    Cache(#[from] CacheError),
    /// Listing a directory failed.
    #[error("{path}: {source}")]
    Io {
        /// The directory.
        path: PathBuf,
        /// The error.
        source: std::io::Error,
    },
    /// Sensors that training needs are missing.
    #[error("{files}: {problems}")]
    Missing {
        /// The files of the dataset.
        files: String,
        /// What is missing, `; `-separated.
        problems: String,
    },
}
