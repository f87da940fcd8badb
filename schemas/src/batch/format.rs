//! The fixed-size parts of the wire format: header, section descriptors, dtypes.

use bytemuck::{Pod, Zeroable};
use iceoryx2::prelude::ZeroCopySend;

/// `b"SFLB"` read as a little-endian `u32`: the first four bytes of every header.
pub const BATCH_MAGIC: u32 = u32::from_le_bytes(*b"SFLB");
/// Version of the layout described in `BATCH_FORMAT.md`; bumped on any change.
pub const BATCH_FORMAT_VERSION: u32 = 2;
/// [`BatchHeader::flags`] bit 0: a lost batch. Every sample of the batch failed to build
/// in the pipeline; the batch still goes out at its place in the stream (epoch, step,
/// sequence) so that subscribers count it and see their epochs end, but it holds
/// nothing: no section, no sample, `payload_len` 0. The only flag version 2 defines.
pub const BATCH_LOST: u32 = 1;
/// Capacity of the section table.
pub const MAX_SECTIONS: usize = 128;
/// Maximum number of dimensions of a section.
pub const MAX_DIMS: usize = 4;
/// Bytes reserved for a section name (NUL-padded, at most `SECTION_NAME_LEN - 1` used).
pub const SECTION_NAME_LEN: usize = 32;
/// Bytes reserved for the run name (NUL-padded, at most `RUN_NAME_LEN - 1` used).
pub const RUN_NAME_LEN: usize = 64;
/// Every section starts at a payload offset that is a multiple of this (a cache line).
pub const SECTION_ALIGN: usize = 64;

/// Element type of a section. The discriminant is the code stored in the header.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Hash)]
#[repr(u32)]
pub enum DType {
    /// `u8` (numpy `<u1`).
    U8 = 1,
    /// `u16` (numpy `<u2`).
    U16 = 2,
    /// `i32` (numpy `<i4`).
    I32 = 3,
    /// `u32` (numpy `<u4`).
    U32 = 4,
    /// `i64` (numpy `<i8`).
    I64 = 5,
    /// `u64` (numpy `<u8`).
    U64 = 6,
    /// `f32` (numpy `<f4`).
    F32 = 7,
    /// `f64` (numpy `<f8`).
    F64 = 8,
}

impl DType {
    /// The dtype of a header code, if known.
    pub const fn from_code(code: u32) -> Option<Self> {
        Some(match code {
            1 => DType::U8,
            2 => DType::U16,
            3 => DType::I32,
            4 => DType::U32,
            5 => DType::I64,
            6 => DType::U64,
            7 => DType::F32,
            8 => DType::F64,
            _ => return None,
        })
    }

    /// The code stored in [`SectionDesc::dtype`].
    pub const fn code(self) -> u32 {
        self as u32
    }

    /// Bytes per element.
    pub const fn size(self) -> usize {
        match self {
            DType::U8 => 1,
            DType::U16 => 2,
            DType::I32 | DType::U32 | DType::F32 => 4,
            DType::I64 | DType::U64 | DType::F64 => 8,
        }
    }

    /// The Rust name of the element type (`u8`, `f32`, ...).
    pub const fn name(self) -> &'static str {
        match self {
            DType::U8 => "u8",
            DType::U16 => "u16",
            DType::I32 => "i32",
            DType::U32 => "u32",
            DType::I64 => "i64",
            DType::U64 => "u64",
            DType::F32 => "f32",
            DType::F64 => "f64",
        }
    }

    /// The numpy dtype string (little-endian).
    pub const fn numpy(self) -> &'static str {
        match self {
            DType::U8 => "<u1",
            DType::U16 => "<u2",
            DType::I32 => "<i4",
            DType::U32 => "<u4",
            DType::I64 => "<i8",
            DType::U64 => "<u8",
            DType::F32 => "<f4",
            DType::F64 => "<f8",
        }
    }
}

/// A Rust element type that a section can hold.
pub trait Element: Pod {
    /// The section dtype for this type.
    const DTYPE: DType;
}

macro_rules! element {
    ($($t:ty => $d:ident),* $(,)?) => {
        $(impl Element for $t { const DTYPE: DType = DType::$d; })*
    };
}
element!(u8 => U8, u16 => U16, i32 => I32, u32 => U32, i64 => I64, u64 => U64, f32 => F32, f64 => F64);

/// One entry of the section table: 88 bytes, 8-byte aligned.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Pod, Zeroable, ZeroCopySend)]
#[type_name("superflow::SectionDesc")]
#[repr(C)]
pub struct SectionDesc {
    /// UTF-8 name, NUL-padded.
    pub name: [u8; SECTION_NAME_LEN],
    /// [`DType`] code.
    pub dtype: u32,
    /// Number of used entries in `shape` (1..=4).
    pub ndim: u32,
    /// Dimensions, outermost first (row-major, C order); unused entries are 0.
    pub shape: [u64; MAX_DIMS],
    /// Byte offset of the first element from the start of the payload.
    pub offset: u64,
    /// Length in bytes: `product(shape) × dtype size`.
    pub len_bytes: u64,
}

/// What a batch is, beyond its sections: where it sits in the stream.
#[derive(Debug, Clone, Default, PartialEq, Eq)]
pub struct BatchMeta {
    /// Run name (the `<run>` of the service name).
    pub run: String,
    /// Epoch the batch belongs to.
    pub epoch: u64,
    /// Index of the batch within its epoch (per service: per rank in shard mode).
    pub step: u64,
    /// Seed of the run; with `(epoch, sample id)` it fixes every random draw.
    pub seed: u64,
    /// Publisher-wide sequence number, counting every batch published.
    pub sequence: u64,
    /// Wall-clock time the batch was written, in nanoseconds since the Unix epoch.
    pub created_unix_nanos: u64,
    /// Samples in the batch.
    pub sample_count: u32,
    /// 0, or [`BATCH_LOST`]: every sample failed, the batch holds nothing.
    pub flags: u32,
}

impl BatchMeta {
    /// Whether the batch is lost ([`BATCH_LOST`]): at its place in the stream, with no
    /// sample to train on.
    pub fn lost(&self) -> bool {
        self.flags & BATCH_LOST != 0
    }
}

/// The iceoryx2 user header of every batch: identification, stream position and the
/// section table. All fields are plain integers, so any bit pattern is a valid value;
/// [`crate::batch::BatchView::new`] decides whether it describes a valid batch.
#[derive(Debug, Clone, Copy, Pod, Zeroable, ZeroCopySend)]
#[type_name("superflow::BatchHeader")]
#[repr(C)]
pub struct BatchHeader {
    /// [`BATCH_MAGIC`].
    pub magic: u32,
    /// [`BATCH_FORMAT_VERSION`].
    pub version: u32,
    /// `size_of::<BatchHeader>()`, so readers in other languages can check their struct.
    pub header_size: u32,
    /// Entries of `sections` in use.
    pub section_count: u32,
    /// Bytes of the payload covered by sections (the loaned slice may be longer).
    pub payload_len: u64,
    /// See [`BatchMeta::epoch`].
    pub epoch: u64,
    /// See [`BatchMeta::step`].
    pub step: u64,
    /// See [`BatchMeta::seed`].
    pub seed: u64,
    /// See [`BatchMeta::sequence`].
    pub sequence: u64,
    /// See [`BatchMeta::created_unix_nanos`].
    pub created_unix_nanos: u64,
    /// See [`BatchMeta::sample_count`].
    pub sample_count: u32,
    /// See [`BatchMeta::flags`].
    pub flags: u32,
    /// Run name, NUL-padded.
    pub run: [u8; RUN_NAME_LEN],
    /// The section table; entries past `section_count` are zero.
    pub sections: [SectionDesc; MAX_SECTIONS],
}

impl Default for BatchHeader {
    fn default() -> Self {
        Self::zeroed()
    }
}

impl BatchHeader {
    /// The header's fixed size in bytes (11 400).
    pub const SIZE: usize = std::mem::size_of::<BatchHeader>();

    /// The stream position and identification carried by the header.
    pub fn meta(&self) -> BatchMeta {
        BatchMeta {
            run: nul_padded_str(&self.run).unwrap_or_default().to_string(),
            epoch: self.epoch,
            step: self.step,
            seed: self.seed,
            sequence: self.sequence,
            created_unix_nanos: self.created_unix_nanos,
            sample_count: self.sample_count,
            flags: self.flags,
        }
    }

    /// Views the header as its raw bytes (e.g. to save a batch to a file).
    pub fn as_bytes(&self) -> &[u8] {
        bytemuck::bytes_of(self)
    }

    /// Reads a header from raw bytes (any alignment). No validation happens here.
    pub fn from_bytes(bytes: &[u8]) -> Option<Self> {
        bytemuck::try_pod_read_unaligned(bytes.get(..Self::SIZE)?).ok()
    }
}

/// Copies `text` into a NUL-padded field, keeping at least one NUL at the end.
pub(crate) fn write_nul_padded(field: &mut [u8], text: &str) -> bool {
    if text.len() >= field.len() || text.as_bytes().contains(&0) {
        return false;
    }
    field.fill(0);
    field[..text.len()].copy_from_slice(text.as_bytes());
    true
}

/// Reads a NUL-padded UTF-8 field; `None` if it is not UTF-8 or has bytes after padding.
pub(crate) fn nul_padded_str(field: &[u8]) -> Option<&str> {
    let end = field.iter().position(|b| *b == 0).unwrap_or(field.len());
    if field[end..].iter().any(|b| *b != 0) {
        return None;
    }
    std::str::from_utf8(&field[..end]).ok()
}

#[cfg(test)]
mod tests {
    use super::*;
    use std::mem::{align_of, offset_of, size_of};

    /// The offsets BATCH_FORMAT.md documents; other languages rely on them.
    #[test]
    fn layout_matches_the_documented_offsets() {
        assert_eq!(size_of::<SectionDesc>(), 88);
        assert_eq!(offset_of!(SectionDesc, dtype), 32);
        assert_eq!(offset_of!(SectionDesc, ndim), 36);
        assert_eq!(offset_of!(SectionDesc, shape), 40);
        assert_eq!(offset_of!(SectionDesc, offset), 72);
        assert_eq!(offset_of!(SectionDesc, len_bytes), 80);
        assert_eq!(offset_of!(BatchHeader, payload_len), 16);
        assert_eq!(offset_of!(BatchHeader, epoch), 24);
        assert_eq!(offset_of!(BatchHeader, step), 32);
        assert_eq!(offset_of!(BatchHeader, seed), 40);
        assert_eq!(offset_of!(BatchHeader, sequence), 48);
        assert_eq!(offset_of!(BatchHeader, created_unix_nanos), 56);
        assert_eq!(offset_of!(BatchHeader, sample_count), 64);
        assert_eq!(offset_of!(BatchHeader, flags), 68);
        assert_eq!(offset_of!(BatchHeader, run), 72);
        assert_eq!(offset_of!(BatchHeader, sections), 136);
        assert_eq!(BatchHeader::SIZE, 136 + 88 * MAX_SECTIONS);
        assert_eq!(BatchHeader::SIZE, 11_400);
        assert_eq!(align_of::<BatchHeader>(), 8);
        assert_eq!(&BATCH_MAGIC.to_le_bytes(), b"SFLB");
    }

    #[test]
    fn dtype_codes_round_trip() {
        for code in 1..=8 {
            let dtype = DType::from_code(code).unwrap();
            assert_eq!(dtype.code(), code);
            assert_eq!(dtype.numpy()[2..].parse::<usize>().unwrap(), dtype.size());
        }
        assert_eq!(DType::from_code(0), None);
        assert_eq!(DType::from_code(9), None);
    }

    #[test]
    fn nul_padded_fields() {
        let mut field = [0xAAu8; 8];
        assert!(write_nul_padded(&mut field, "abc"));
        assert_eq!(nul_padded_str(&field), Some("abc"));
        assert!(!write_nul_padded(&mut field, "abcdefgh"));
        assert!(write_nul_padded(&mut field, "abcdefg"));
        assert_eq!(nul_padded_str(&[b'a', 0, b'b', 0]), None);
        assert_eq!(nul_padded_str(&[0xff, 0]), None);
    }
}
