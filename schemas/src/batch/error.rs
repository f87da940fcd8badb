//! [`BatchError`]: why a batch could not be laid out, written or read.

use super::format::{BATCH_FORMAT_VERSION, BATCH_LOST, BATCH_MAGIC, DType, MAX_SECTIONS};

/// Why a batch could not be laid out, written or read.
#[derive(Debug, Clone, PartialEq, Eq, thiserror::Error)]
pub enum BatchError {
    /// The header does not start with [`BATCH_MAGIC`].
    #[error("not a superflow batch: magic {found:#010x}, expected {BATCH_MAGIC:#010x}")]
    BadMagic {
        /// The magic found.
        found: u32,
    },
    /// The header was written by another format version.
    #[error("batch format version {found}, this build reads version {BATCH_FORMAT_VERSION}")]
    Version {
        /// The version found.
        found: u32,
    },
    /// The header's declared size differs from this build's header type.
    #[error("batch header is {found} bytes, expected {expected}")]
    HeaderSize {
        /// Declared size.
        found: u32,
        /// `size_of::<BatchHeader>()`.
        expected: u32,
    },
    /// Flags set that this version does not define.
    #[error(
        "flags {found:#x} set; version {BATCH_FORMAT_VERSION} defines only BATCH_LOST ({BATCH_LOST:#x})"
    )]
    Flags {
        /// The flags found.
        found: u32,
    },
    /// A lost batch ([`BATCH_LOST`]) that claims to hold something.
    #[error(
        "a lost batch (flag BATCH_LOST) holds nothing, but this one declares {sections} sections, {samples} samples and a payload of {payload_len} bytes"
    )]
    LostWithContent {
        /// `section_count`.
        sections: u32,
        /// `sample_count`.
        samples: u32,
        /// `payload_len`.
        payload_len: u64,
    },
    /// More sections than the table holds.
    #[error("{count} sections, at most {MAX_SECTIONS} fit in the header")]
    TooManySections {
        /// Sections requested or declared.
        count: usize,
    },
    /// The payload is shorter than the header says.
    #[error("payload has {actual} bytes, header declares {declared}")]
    PayloadTooShort {
        /// Declared `payload_len`.
        declared: u64,
        /// Bytes available.
        actual: usize,
    },
    /// A section name that is empty, too long, not UTF-8 or repeated.
    #[error("section #{index}: invalid name {name:?}: {reason}")]
    BadName {
        /// Table index.
        index: usize,
        /// The name as far as it could be read.
        name: String,
        /// What is wrong.
        reason: &'static str,
    },
    /// A section whose dtype code is unknown.
    #[error("section `{name}`: unknown dtype code {code}")]
    UnknownDType {
        /// Section name.
        name: String,
        /// The code found.
        code: u32,
    },
    /// A section whose shape, length, offset or alignment is inconsistent.
    #[error("section `{name}`: {reason}")]
    BadSection {
        /// Section name.
        name: String,
        /// What is wrong.
        reason: String,
    },
    /// Two sections share bytes.
    #[error("sections `{first}` and `{second}` overlap")]
    Overlap {
        /// The section that starts first.
        first: String,
        /// The section that starts inside it.
        second: String,
    },
    /// No section of that name.
    #[error("no section named `{name}` in the batch")]
    Missing {
        /// The name asked for.
        name: String,
    },
    /// A section read or written as the wrong element type.
    #[error("section `{name}` holds {actual:?}, not {requested:?}")]
    WrongDType {
        /// Section name.
        name: String,
        /// Its dtype.
        actual: DType,
        /// The dtype asked for.
        requested: DType,
    },
    /// The buffer handed to the writer is too small for the layout.
    #[error("buffer of {actual} bytes is too small for a payload of {needed} bytes")]
    BufferTooSmall {
        /// Bytes the layout needs.
        needed: u64,
        /// Bytes given.
        actual: usize,
    },
    /// The payload's start address does not allow typed views (alignment).
    #[error("payload or section data at an address aligned to {found} bytes; {needed} needed")]
    Misaligned {
        /// Largest power of two dividing the address (capped).
        found: usize,
        /// Alignment required.
        needed: usize,
    },
    /// A section slice was already taken from the writer.
    #[error("section `{name}` was already taken from the writer")]
    AlreadyTaken {
        /// Section name.
        name: String,
    },
    /// A section used otherwise than the section table declares (dtype, rank, size).
    #[error("section `{name}`: {reason}")]
    NotAsDeclared {
        /// Section name.
        name: String,
        /// What differs.
        reason: String,
    },
    /// The run name does not fit or is not printable ASCII.
    #[error("run name {name:?}: {reason}")]
    BadRunName {
        /// The run name.
        name: String,
        /// What is wrong.
        reason: &'static str,
    },
}
