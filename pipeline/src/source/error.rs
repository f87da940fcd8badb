//! [`SourceError`]: a file that cannot be read at all (damage the scan can work around is
//! a [`Damage`](super::Damage) instead).

use super::chunk::ChunkError;
use super::message::MessageLoc;
use std::path::PathBuf;

/// A file that cannot be read at all.
#[derive(Debug, thiserror::Error)]
pub enum SourceError {
    /// Opening or reading failed.
    #[error("{path}: {source}")]
    Io {
        /// The file.
        path: PathBuf,
        /// The I/O error.
        source: std::io::Error,
    },
    /// The file does not start with the MCAP magic.
    #[error("{path}: not an MCAP file (bad magic bytes)")]
    NotMcap {
        /// The file.
        path: PathBuf,
    },
    /// A message location that this file does not have.
    #[error("{path}: no message at {loc:?}")]
    NoSuchMessage {
        /// The file.
        path: PathBuf,
        /// The location asked for.
        loc: MessageLoc,
    },
    /// A chunk that read fine during the scan fails now (file changed?).
    #[error("{path}: chunk at byte {offset}: {source}")]
    Chunk {
        /// The file.
        path: PathBuf,
        /// Offset of the chunk record.
        offset: u64,
        /// What failed.
        source: ChunkError,
    },
    /// The file at this path is no longer the one scanned, nor a copy of it (its size,
    /// header, summary or chunks differ, or it has no summary to compare): its index
    /// would point at the wrong bytes.
    #[error(
        "{path}: the file was replaced (on disk, or in its object store) by one of other \
         content since it was indexed; its samples are skipped until the dataset is opened \
         again"
    )]
    Replaced {
        /// The file.
        path: PathBuf,
    },
    /// An object store refused or failed a request past its retries (credentials,
    /// a missing object, a store that stayed unreachable). The reason never holds a
    /// credential.
    #[error("{path}: {reason}")]
    Remote {
        /// The object's URL.
        path: PathBuf,
        /// What the store said, in words.
        reason: String,
    },
    /// The process ran out of file descriptors opening the file.
    #[error(
        "{path}: too many open files ({source}); lower `[ingest] max_open_files` \
         (now {limit}) in pipeline.toml or raise `ulimit -n`"
    )]
    TooManyOpenFiles {
        /// The file.
        path: PathBuf,
        /// The pool's limit when it happened.
        limit: usize,
        /// The I/O error (EMFILE or ENFILE).
        source: std::io::Error,
    },
}
