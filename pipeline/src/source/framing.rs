//! Record framing, checked before mcap reads bytes: mcap's readers subtract each record's
//! length from what remains unchecked (an overflow panic in debug builds, found by the
//! fuzz target `mcap_drive`), so a run of records is walked here first.

/// The 8 magic bytes at both ends of an MCAP file.
pub const MAGIC: &[u8; 8] = b"\x89MCAP0\r\n";
/// Largest chunk (uncompressed) or record accepted; a larger size is taken for corruption.
pub const MAX_RECORD_BYTES: u64 = 1 << 30;

/// A run of records that is not a run of whole records of the expected kinds. `at` is
/// the offset of the offending record from the start of the run.
#[derive(Debug, Clone, PartialEq, Eq, thiserror::Error)]
pub enum FramingError {
    /// Bytes after the last record, too few for a record header.
    #[error("{left} stray bytes after the last record")]
    StrayBytes {
        /// Offset of the stray bytes.
        at: usize,
        /// How many.
        left: usize,
    },
    /// A record longer than what remains.
    #[error("record of {len} bytes runs past the end ({left} bytes left)")]
    PastEnd {
        /// Offset of the record.
        at: usize,
        /// Its declared body length.
        len: u64,
        /// Bytes left after its header.
        left: usize,
    },
    /// A record of a kind that does not belong in this run.
    #[error("a record with opcode {opcode:#04x}, which does not belong there")]
    Misplaced {
        /// Offset of the record.
        at: usize,
        /// Its opcode.
        opcode: u8,
    },
}

impl FramingError {
    /// Offset of the offending record from the start of the run.
    pub fn at(&self) -> usize {
        match self {
            FramingError::StrayBytes { at, .. }
            | FramingError::PastEnd { at, .. }
            | FramingError::Misplaced { at, .. } => *at,
        }
    }
}

/// Checks that `records` is a run of whole records (opcode, length, body), none running
/// past its end and each of an opcode that `allowed` accepts.
pub(super) fn check_framing(
    records: &[u8],
    allowed: impl Fn(u8) -> bool,
) -> Result<(), FramingError> {
    let mut at = 0usize;
    while let Some(rest) = records.get(at..).filter(|r| !r.is_empty()) {
        let Some(&[opcode, l0, l1, l2, l3, l4, l5, l6, l7]) = rest.get(..9) else {
            return Err(FramingError::StrayBytes {
                at,
                left: rest.len(),
            });
        };
        let len = u64::from_le_bytes([l0, l1, l2, l3, l4, l5, l6, l7]);
        if len > (rest.len() - 9) as u64 {
            return Err(FramingError::PastEnd {
                at,
                len,
                left: rest.len() - 9,
            });
        }
        if !allowed(opcode) {
            return Err(FramingError::Misplaced { at, opcode });
        }
        at += 9 + len as usize;
    }
    Ok(())
}

/// The body length in a record's 9-byte opcode + length prefix.
pub(super) fn record_len(head: &[u8; 9]) -> u64 {
    u64::from_le_bytes([
        head[1], head[2], head[3], head[4], head[5], head[6], head[7], head[8],
    ])
}
