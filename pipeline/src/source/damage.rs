//! [`Damage`]: what a scan of a damaged file worked around, in words (a report, not an
//! error: the file is still read).

/// Something wrong with a file that the scan worked around.
#[derive(Debug, Clone, PartialEq, Eq, serde::Serialize, serde::Deserialize)]
pub enum Damage {
    /// The file ends early (no footer, or a record that runs past the end).
    Truncated {
        /// Byte offset where reading stopped.
        offset: u64,
        /// What was found there.
        reason: String,
    },
    /// The file has no summary section (or it is unreadable): no index to cross-check.
    NoSummary {
        /// Why.
        reason: String,
    },
    /// A chunk whose content could not be used (CRC mismatch, decompression failure).
    BadChunk {
        /// Offset of the chunk record.
        offset: u64,
        /// What failed.
        reason: String,
    },
    /// A record that could not be parsed; the scan resumed at `resumed_at` if possible.
    BadRecord {
        /// Offset of the record.
        offset: u64,
        /// What failed.
        reason: String,
        /// Where the scan resumed (the next indexed chunk), if anywhere.
        resumed_at: Option<u64>,
    },
    /// Fewer messages on a channel than the summary's statistics state.
    MissingMessages {
        /// The topic.
        topic: String,
        /// Per the statistics.
        expected: u64,
        /// Actually read.
        found: u64,
    },
}

impl std::fmt::Display for Damage {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        match self {
            Damage::Truncated { offset, reason } => {
                write!(f, "truncated at byte {offset}: {reason}")
            }
            Damage::NoSummary { reason } => write!(f, "no usable summary: {reason}"),
            Damage::BadChunk { offset, reason } => {
                write!(f, "chunk at byte {offset} skipped: {reason}")
            }
            Damage::BadRecord {
                offset,
                reason,
                resumed_at,
            } => {
                write!(f, "corrupt record at byte {offset}: {reason}")?;
                match resumed_at {
                    Some(at) => write!(f, "; resumed at the next indexed chunk, byte {at}"),
                    None => write!(f, "; nothing after it could be read"),
                }
            }
            Damage::MissingMessages {
                topic,
                expected,
                found,
            } => write!(f, "{topic}: {found} of {expected} messages readable"),
        }
    }
}
