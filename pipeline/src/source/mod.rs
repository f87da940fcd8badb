//! Reading MCAP files with bounded memory.
//!
//! [`McapFile::scan`] makes one pass over a file, record by record, holding at most one
//! chunk in memory: it registers schemas and channels, hands every message to a visitor
//! together with its [`MessageLoc`], and notes damage (truncation, bad chunk CRCs,
//! undecodable records) instead of failing: a damaged region costs only the messages in
//! it. When the file has a summary, its chunk index is used to resynchronize after a
//! corrupt record and its statistics to count what was lost.
//!
//! [`McapFile::read_message`] later fetches one message by location through a
//! [`ChunkCache`] of a few decompressed chunks.
//!
//! The work is split by concern: `file` (the scanned file and its reads), `message` (the
//! records and messages a scan hands out), `error` (a file that cannot be read), `scan`
//! (the pass over the records), `summary` (the summary section, its framing checked
//! first), `framing` (records framed before mcap reads them, and the sizes that bound
//! them), `chunk` (decompressing and splitting one chunk), `partial` (a zstd chunk decoded
//! only as far as it is read), `cache` (random access), `tally` (what random access did),
//! `damage` (what a scan worked around), `facts` (what a scan learned, to be stored, and
//! the fingerprint that says when it still holds), `handles` (the bounded pool of open
//! files every read goes through), `remote` (files in object stores: a URL where a path
//! goes) and `place` (directories, files and sizes of local paths and URLs alike).

mod cache;
mod chunk;
mod damage;
mod error;
mod facts;
mod file;
mod framing;
mod handles;
mod message;
mod partial;
mod place;
pub mod remote;
mod scan;
mod summary;
mod tally;

pub use cache::{ChunkCache, keep_chunks_for_blocks};
pub use chunk::ChunkError;
pub use damage::Damage;
pub use error::SourceError;
pub use facts::ScannedFile;
pub use file::McapFile;
pub use framing::{FramingError, MAGIC, MAX_RECORD_BYTES};
pub use handles::{FileIdentity, HandlePool, default_max_open_files, raise_open_file_limit};
pub use message::{ChannelInfo, MessageLoc, MessageRef, SchemaInfo};
pub use place::{is_dir, is_file, mcap_files_in, on_read_pool, size_of};
pub use remote::is_remote;
pub use tally::Decompressed;

#[cfg(test)]
mod tests;
