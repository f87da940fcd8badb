//! The CDR codec of rosbag2 payloads: the 4-byte encapsulation header around
//! `cdr-encoding`'s body ([`encode`], [`decode`], [`CdrError`]), and `uint8[]` fields as
//! one block of octets.

use std::any::type_name;
use std::fmt;

use byteorder::{BigEndian, LittleEndian};
use serde::de::{SeqAccess, Visitor};
use serde::{Deserialize, Deserializer, Serialize, Serializer};

/// Length of the CDR encapsulation header that starts every payload.
pub const ENCAPSULATION_HEADER_LEN: usize = 4;

/// Representation identifier of big-endian plain CDR (`CDR_BE`).
const CDR_BE: [u8; 2] = [0x00, 0x00];

/// Representation identifier of little-endian plain CDR (`CDR_LE`).
const CDR_LE: [u8; 2] = [0x00, 0x01];

/// Why a CDR payload could not be encoded or decoded.
#[derive(Debug, thiserror::Error)]
pub enum CdrError {
    /// The payload cannot even hold the 4-byte encapsulation header.
    #[error("CDR payload of {len} bytes is shorter than the 4-byte encapsulation header")]
    TooShort {
        /// Length of the payload.
        len: usize,
    },
    /// The encapsulation header names a representation other than plain CDR (for
    /// example parameter lists or XCDR2).
    #[error(
        "unsupported CDR representation identifier {:02x} {:02x} (expected 00 01 CDR_LE or 00 00 CDR_BE)",
        id[0],
        id[1]
    )]
    UnsupportedRepresentation {
        /// The first two bytes of the payload.
        id: [u8; 2],
    },
    /// The body is not a valid encoding of the type (truncated, bad string, bad bool, ...).
    #[error("cannot decode {type_name} from a {len}-byte CDR payload: {reason}")]
    Decode {
        /// Rust type that was being decoded.
        type_name: &'static str,
        /// Length of the payload, header included.
        len: usize,
        /// What `cdr-encoding` reported.
        reason: cdr_encoding::Error,
    },
    /// The value cannot be written as CDR (a `uint8[]` longer than `u32::MAX`, ...).
    #[error("cannot encode {type_name} as CDR: {reason}")]
    Encode {
        /// Rust type that was being encoded.
        type_name: &'static str,
        /// What `cdr-encoding` reported.
        reason: cdr_encoding::Error,
    },
}

/// Encodes `msg` as a CDR payload: the encapsulation header `00 01 00 00` (`CDR_LE`)
/// followed by the little-endian body, aligned relative to the start of the body.
pub fn encode<T: Serialize>(msg: &T) -> Result<Vec<u8>, CdrError> {
    let mut out = Vec::with_capacity(ENCAPSULATION_HEADER_LEN + 64);
    out.extend_from_slice(&[CDR_LE[0], CDR_LE[1], 0x00, 0x00]);
    // The serializer counts alignment from its own first byte, which is the body's.
    cdr_encoding::to_writer::<T, LittleEndian, _>(&mut out, msg).map_err(|reason| {
        CdrError::Encode {
            type_name: type_name::<T>(),
            reason,
        }
    })?;
    Ok(out)
}

/// Decodes a CDR payload (encapsulation header, then body) as a `T`.
///
/// Accepts `CDR_LE` (`00 01`) and `CDR_BE` (`00 00`); the two option bytes of the header
/// are ignored, and so are bytes after the end of the value (DDS pads payloads to a
/// multiple of 4). Never panics, and allocates no more than the payload's size whatever
/// the lengths it declares.
pub fn decode<'de, T: Deserialize<'de>>(bytes: &'de [u8]) -> Result<T, CdrError> {
    let Some((header, body)) = bytes.split_first_chunk::<ENCAPSULATION_HEADER_LEN>() else {
        return Err(CdrError::TooShort { len: bytes.len() });
    };
    // The deserializer counts alignment from the first byte of `body`, as CDR requires.
    let decoded = match [header[0], header[1]] {
        CDR_LE => cdr_encoding::from_bytes::<T, LittleEndian>(body),
        CDR_BE => cdr_encoding::from_bytes::<T, BigEndian>(body),
        id => return Err(CdrError::UnsupportedRepresentation { id }),
    };
    decoded
        .map(|(value, _consumed)| value)
        .map_err(|reason| CdrError::Decode {
            type_name: type_name::<T>(),
            len: bytes.len(),
            reason,
        })
}

/// `uint8[]` fields as a CDR `sequence<octet>` read and written in one block.
///
/// `Vec<u8>`'s own serde impls go through `serialize_seq`/`deserialize_seq`, one call
/// (and one bounds check and push) per byte. `cdr-encoding` implements
/// `serialize_bytes` and `deserialize_byte_buf` as the same wire format (a `u32` count
/// aligned to 4, then the bytes), but as a single copy.
pub(super) mod octets {
    use super::{Deserializer, SeqAccess, Serializer, Visitor, fmt};

    /// Writes `bytes` as a length-prefixed octet sequence.
    pub(in crate::ros2) fn serialize<S: Serializer>(
        bytes: &[u8],
        serializer: S,
    ) -> Result<S::Ok, S::Error> {
        if u32::try_from(bytes.len()).is_err() {
            return Err(serde::ser::Error::custom(format_args!(
                "a uint8[] of {} bytes does not fit a CDR sequence (u32 length)",
                bytes.len()
            )));
        }
        serializer.serialize_bytes(bytes)
    }

    /// Reads a length-prefixed octet sequence.
    pub(in crate::ros2) fn deserialize<'de, D: Deserializer<'de>>(
        deserializer: D,
    ) -> Result<Vec<u8>, D::Error> {
        deserializer.deserialize_byte_buf(OctetsVisitor)
    }

    /// Accepts bytes in any of the forms serde formats hand them over.
    #[derive(Debug)]
    struct OctetsVisitor;

    impl<'de> Visitor<'de> for OctetsVisitor {
        type Value = Vec<u8>;

        fn expecting(&self, formatter: &mut fmt::Formatter<'_>) -> fmt::Result {
            formatter.write_str("a sequence of octets")
        }

        fn visit_bytes<E: serde::de::Error>(self, v: &[u8]) -> Result<Self::Value, E> {
            Ok(v.to_vec())
        }

        fn visit_byte_buf<E: serde::de::Error>(self, v: Vec<u8>) -> Result<Self::Value, E> {
            Ok(v)
        }

        // Self-describing formats (JSON, ...) may present bytes as a sequence of numbers.
        fn visit_seq<A: SeqAccess<'de>>(self, mut seq: A) -> Result<Self::Value, A::Error> {
            // The hint comes from the input: never trust it for more than a small buffer.
            let mut out = Vec::with_capacity(seq.size_hint().unwrap_or(0).min(1 << 16));
            while let Some(byte) = seq.next_element::<u8>()? {
                out.push(byte);
            }
            Ok(out)
        }
    }
}
