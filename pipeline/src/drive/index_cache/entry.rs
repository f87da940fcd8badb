//! The bytes of one entry: a magic, the version of what it holds, the identity of the
//! build that wrote it, the key it is stored under, the length and xxh3 hash of the
//! payload, and the payload (bincode). [`decode`] checks every field before it uses the
//! next, and every length against the bytes actually there.

use serde::Serialize;
use serde::de::DeserializeOwned;

/// The identity of this build's indexing: its version and a hash of the code that decides
/// what an entry holds (`build.rs`). An entry written under another identity is not read.
pub const BUILD: &str = concat!(
    env!("CARGO_PKG_VERSION"),
    "+",
    env!("SUPERFLOW_INDEX_BUILD")
);

/// The most bytes bincode may allocate decoding a payload: a length prefix beyond what
/// an entry can hold is refused before any allocation.
const MAX_DECODED_BYTES: usize = 1 << 30;

/// One kind of entry: its magic, the version of what it holds and its file extension.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub struct EntryKind {
    /// The first bytes of every entry of the kind.
    pub magic: [u8; 8],
    /// The version of the payload: raised whenever what it holds or how it is computed
    /// changes, so that no older entry is read as a newer one.
    pub version: u32,
    /// The entry files' extension, without the dot.
    pub extension: &'static str,
    /// What the entries hold, for log lines (`index`, `camera scan`).
    pub what: &'static str,
}

/// Why an entry was not used.
#[derive(Debug, thiserror::Error)]
pub enum EntryError {
    /// It could not be opened or read.
    #[error("unreadable ({0})")]
    Unreadable(#[source] std::io::Error),
    /// A symbolic link stands where the entry should be: never followed.
    #[error("it is a symbolic link (not followed)")]
    Symlink,
    /// Something other than a regular file stands where the entry should be.
    #[error("it is not a regular file but a {0}")]
    NotAFile(&'static str),
    /// The entry belongs to a user the cache does not trust.
    #[error(
        "it is owned by uid {uid}, not by this user or the cache's owner (`[ingest] index_cache_owner`)"
    )]
    Owner {
        /// The entry's owner.
        uid: u32,
    },
    /// It is larger than any entry can be.
    #[error("it is {0} bytes, more than an entry can hold")]
    TooLarge(u64),
    /// It does not begin with its kind's magic.
    #[error("bad magic: not a superflow {0} entry")]
    Magic(&'static str),
    /// It was written in another version of its kind.
    #[error("written in {what} format {found}, this pipeline reads {expected}")]
    Version {
        /// What the entries hold.
        what: &'static str,
        /// The entry's version.
        found: u32,
        /// The version this pipeline reads.
        expected: u32,
    },
    /// It was written by a build whose indexing may differ.
    #[error("written by superflow-pipeline {0}, this is {BUILD}")]
    Writer(String),
    /// It is stored under a name that is not its own (renamed or linked there).
    #[error("it is the entry of another key ({0:032x})")]
    Key(u128),
    /// It ends early.
    #[error("truncated: {0}")]
    Truncated(&'static str),
    /// Its payload does not hash to the stored hash.
    #[error("its checksum does not match its content (damaged)")]
    Checksum,
    /// Its payload does not decode.
    #[error("its content does not decode: {0}")]
    Decode(#[source] bincode::error::DecodeError),
    /// Bytes follow the payload.
    #[error("bytes left over after the {0}")]
    Trailing(&'static str),
    /// The payload decodes but does not fit the file it is the entry of.
    #[error("it does not fit the file: {0}")]
    Inconsistent(String),
}

/// The bytes of an entry of `kind` stored under `key`, holding `value`.
pub fn encode<T: Serialize>(
    kind: &EntryKind,
    key: u128,
    value: &T,
) -> Result<Vec<u8>, bincode::error::EncodeError> {
    let payload = bincode::serde::encode_to_vec(value, bincode::config::standard())?;
    let mut bytes = Vec::with_capacity(payload.len() + 96);
    bytes.extend_from_slice(&kind.magic);
    bytes.extend_from_slice(&kind.version.to_le_bytes());
    bytes.extend_from_slice(&(BUILD.len() as u16).to_le_bytes());
    bytes.extend_from_slice(BUILD.as_bytes());
    bytes.extend_from_slice(&key.to_le_bytes());
    bytes.extend_from_slice(&(payload.len() as u64).to_le_bytes());
    bytes.extend_from_slice(&xxhash_rust::xxh3::xxh3_64(&payload).to_le_bytes());
    bytes.extend_from_slice(&payload);
    Ok(bytes)
}

/// The payload of an entry of `kind` stored under `key`, checked (magic, version, build,
/// key, length, hash), not decoded.
pub fn payload<'a>(kind: &EntryKind, key: u128, bytes: &'a [u8]) -> Result<&'a [u8], EntryError> {
    let mut r = Reader(bytes);
    if r.take(kind.magic.len(), "magic")? != kind.magic {
        return Err(EntryError::Magic(kind.what));
    }
    let version = u32::from_le_bytes(r.array("version")?);
    if version != kind.version {
        return Err(EntryError::Version {
            what: kind.what,
            found: version,
            expected: kind.version,
        });
    }
    let writer_len = u16::from_le_bytes(r.array("writer")?);
    let writer = r.take(usize::from(writer_len), "writer")?;
    if writer != BUILD.as_bytes() {
        return Err(EntryError::Writer(
            String::from_utf8_lossy(writer).into_owned(),
        ));
    }
    let stored_key = u128::from_le_bytes(r.array("key")?);
    if stored_key != key {
        return Err(EntryError::Key(stored_key));
    }
    let len = u64::from_le_bytes(r.array("length")?);
    let hash = u64::from_le_bytes(r.array("checksum")?);
    let len = usize::try_from(len).map_err(|_| EntryError::Truncated("payload"))?;
    let payload = r.take(len, "payload")?;
    if !r.0.is_empty() {
        return Err(EntryError::Trailing(kind.what));
    }
    if xxhash_rust::xxh3::xxh3_64(payload) != hash {
        return Err(EntryError::Checksum);
    }
    Ok(payload)
}

/// The value an entry of `kind` stored under `key` holds.
pub fn decode<T: DeserializeOwned>(
    kind: &EntryKind,
    key: u128,
    bytes: &[u8],
) -> Result<T, EntryError> {
    let payload = payload(kind, key, bytes)?;
    let config = bincode::config::standard().with_limit::<MAX_DECODED_BYTES>();
    let (value, used) =
        bincode::serde::decode_from_slice::<T, _>(payload, config).map_err(EntryError::Decode)?;
    if used != payload.len() {
        return Err(EntryError::Trailing(kind.what));
    }
    Ok(value)
}

/// The unread rest of an entry.
struct Reader<'a>(&'a [u8]);

impl<'a> Reader<'a> {
    fn take(&mut self, n: usize, what: &'static str) -> Result<&'a [u8], EntryError> {
        if self.0.len() < n {
            return Err(EntryError::Truncated(what));
        }
        let (head, tail) = self.0.split_at(n);
        self.0 = tail;
        Ok(head)
    }

    fn array<const N: usize>(&mut self, what: &'static str) -> Result<[u8; N], EntryError> {
        let mut out = [0u8; N];
        out.copy_from_slice(self.take(N, what)?);
        Ok(out)
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    const KIND: EntryKind = EntryKind {
        magic: *b"SFTEST\0\0",
        version: 3,
        extension: "sftest",
        what: "test",
    };

    #[test]
    fn an_entry_reads_back_only_under_its_own_key_kind_and_build() {
        let value: Vec<u32> = (0..100).collect();
        let bytes = encode(&KIND, 7, &value).unwrap();
        assert_eq!(decode::<Vec<u32>>(&KIND, 7, &bytes).unwrap(), value);
        assert!(matches!(
            decode::<Vec<u32>>(&KIND, 8, &bytes),
            Err(EntryError::Key(7))
        ));
        let other = EntryKind { version: 4, ..KIND };
        assert!(matches!(
            decode::<Vec<u32>>(&other, 7, &bytes),
            Err(EntryError::Version { found: 3, .. })
        ));
        // The same bytes written by another build.
        let mut foreign = Vec::new();
        foreign.extend_from_slice(&bytes[..12]);
        foreign.extend_from_slice(&5u16.to_le_bytes());
        foreign.extend_from_slice(b"0.0.9");
        foreign.extend_from_slice(&bytes[14 + BUILD.len()..]);
        let err = decode::<Vec<u32>>(&KIND, 7, &foreign).unwrap_err();
        assert!(
            matches!(&err, EntryError::Writer(w) if w == "0.0.9"),
            "{err}"
        );
        for cut in [0, 5, 13, 20, bytes.len() - 1] {
            assert!(
                decode::<Vec<u32>>(&KIND, 7, &bytes[..cut]).is_err(),
                "cut at {cut}"
            );
        }
        let mut longer = bytes.clone();
        longer.push(0);
        assert!(matches!(
            decode::<Vec<u32>>(&KIND, 7, &longer),
            Err(EntryError::Trailing(_))
        ));
    }

    #[test]
    fn a_huge_length_prefix_with_a_valid_checksum_is_refused_without_allocating() {
        // A payload claiming 2^61 elements, hashed as a writer with the format would.
        let mut payload = vec![0xFF];
        payload.extend_from_slice(&(1u64 << 61).to_le_bytes());
        let mut bytes = encode(&KIND, 1, &()).unwrap();
        let header = bytes.len() - 16; // length and hash of an empty payload
        bytes.truncate(header);
        bytes.extend_from_slice(&(payload.len() as u64).to_le_bytes());
        bytes.extend_from_slice(&xxhash_rust::xxh3::xxh3_64(&payload).to_le_bytes());
        bytes.extend_from_slice(&payload);
        let err = decode::<Vec<u64>>(&KIND, 1, &bytes).unwrap_err();
        assert!(matches!(err, EntryError::Decode(_)), "{err}");
        // A payload length beyond the bytes there.
        let mut bytes = encode(&KIND, 1, &42u32).unwrap();
        let at = bytes.len() - 1 - 16; // the length, before the hash and the payload
        bytes[at..at + 8].copy_from_slice(&u64::MAX.to_le_bytes());
        assert!(decode::<u32>(&KIND, 1, &bytes).is_err());
    }
}
