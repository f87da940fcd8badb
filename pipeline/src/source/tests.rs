//! Tests of the MCAP reader: round trips, truncations, and the damaged files the fuzz
//! target `mcap_drive` found.

use super::*;
use mcap::records::{self, op};
use std::collections::BTreeMap;
use std::io::Cursor;

/// An in-memory writer with `options` and one raw channel per topic (their ids).
fn raw_writer(
    options: mcap::WriteOptions,
    topics: &[&str],
) -> (mcap::Writer<Cursor<Vec<u8>>>, Vec<u16>) {
    let mut writer = options.create(Cursor::new(Vec::new())).unwrap();
    let schema = writer.add_schema("test.Msg", "raw", b"bytes").unwrap();
    let channels = topics
        .iter()
        .map(|topic| {
            writer
                .add_channel(schema, topic, "raw", &BTreeMap::new())
                .unwrap()
        })
        .collect();
    (writer, channels)
}

/// Writes `n` messages on two channels; chunked or not.
fn sample_file(chunked: bool, n: u32) -> Vec<u8> {
    sample_file_saying(chunked, n, "message")
}

/// [`sample_file`] with payloads `"<word> <i>"`.
fn sample_file_saying(chunked: bool, n: u32, word: &str) -> Vec<u8> {
    let options = mcap::WriteOptions::new()
        .use_chunks(chunked)
        .chunk_size(Some(64))
        .compression(Some(mcap::Compression::Zstd));
    let (mut writer, channels) = raw_writer(options, &["/a", "/b"]);
    let (a, b) = (channels[0], channels[1]);
    for i in 0..n {
        let channel_id = if i % 3 == 0 { b } else { a };
        let header = records::MessageHeader {
            channel_id,
            sequence: i,
            log_time: 1_000 + u64::from(i),
            publish_time: 1_000 + u64::from(i),
        };
        writer
            .write_to_known_channel(&header, format!("{word} {i}").as_bytes())
            .unwrap();
    }
    writer.finish().unwrap();
    writer.into_inner().into_inner()
}

/// Topic, log time, payload and location of a scanned message.
type Seen = (String, u64, Vec<u8>, MessageLoc);

/// Scans a file whose only chunk (right after the magic) is damaged: no message
/// comes out and the chunk is reported bad at byte 8.
fn scan_rejects_the_chunk(name: &str, bytes: &[u8]) {
    let (file, seen) = scan_bytes(name, bytes);
    assert!(seen.is_empty());
    assert!(
        file.damage
            .iter()
            .any(|d| matches!(d, Damage::BadChunk { offset: 8, .. })),
        "{:?}",
        file.damage
    );
}

fn scan_bytes(name: &str, bytes: &[u8]) -> (McapFile, Vec<Seen>) {
    let dir = std::env::temp_dir().join(format!("superflow-source-{}", std::process::id()));
    std::fs::create_dir_all(&dir).unwrap();
    let path = dir.join(name);
    std::fs::write(&path, bytes).unwrap();
    let mut seen = Vec::new();
    let file = McapFile::scan(&path, |m| {
        seen.push((m.channel.topic.clone(), m.log_time, m.data.to_vec(), m.loc))
    })
    .unwrap();
    (file, seen)
}

#[test]
fn scans_and_reads_back_chunked_and_unchunked_files() {
    for chunked in [true, false] {
        let (file, seen) = scan_bytes(&format!("plain_{chunked}.mcap"), &sample_file(chunked, 30));
        assert!(file.damage.is_empty(), "{:?}", file.damage);
        assert_eq!(seen.len(), 30);
        assert_eq!(seen[4].0, "/a");
        assert_eq!(seen[6].0, "/b");
        assert_eq!(seen[7].2, b"message 7");
        let counts: Vec<u64> = file.message_counts.values().copied().collect();
        assert_eq!(counts, [20, 10]);
        // Random access in reverse order through a one-chunk cache.
        let mut cache = ChunkCache::new(1);
        for (topic, log_time, data, loc) in seen.iter().rev() {
            let m = file.read_message(*loc, &mut cache).unwrap();
            assert_eq!(
                (&m.channel.topic, m.log_time, m.data),
                (topic, *log_time, &data[..])
            );
            assert_eq!(matches!(loc, MessageLoc::Chunk { .. }), chunked);
        }
        assert!(cache.entries.len() <= 1);
        // Counted per file: in reverse order each chunk holding messages was decompressed
        // once, and the bytes are those chunk headers' uncompressed sizes.
        let decompressed = file.decompressed();
        if chunked {
            let bytes = sample_file(true, 30);
            let sizes: Vec<u64> = mcap::read::LinearReader::new(&bytes)
                .unwrap()
                .filter_map(|r| match r.unwrap() {
                    records::Record::Chunk { header, .. } => Some(header.uncompressed_size),
                    _ => None,
                })
                .collect();
            assert_eq!(sizes.len(), file.chunks.len());
            let read: std::collections::BTreeSet<usize> = seen
                .iter()
                .filter_map(|s| match s.3 {
                    MessageLoc::Chunk { chunk, .. } => Some(chunk as usize),
                    MessageLoc::Direct { .. } => None,
                })
                .collect();
            assert!(read.len() > 2);
            let want = Decompressed {
                chunks: read.len() as u64,
                bytes: read.iter().map(|&c| sizes[c]).sum(),
            };
            assert_eq!(decompressed, want);
        } else {
            assert_eq!(decompressed, Decompressed::default());
        }
        let missing = MessageLoc::Chunk {
            chunk: 999,
            index: 0,
        };
        assert!(file.read_message(missing, &mut cache).is_err());
    }
}

#[test]
fn threads_share_chunks_and_a_rewritten_file_is_read_afresh() {
    let (file, seen) = scan_bytes("shared.mcap", &sample_file(true, 60));
    assert!(seen.len() == 60 && file.chunks.len() > 4);
    // Four threads read every message at once, each through a one-chunk cache of its
    // own, in orders that meet on the same chunks: each gets every message right.
    std::thread::scope(|scope| {
        for t in 0..4 {
            let (file, seen) = (&file, &seen);
            scope.spawn(move || {
                let mut cache = ChunkCache::new(1);
                for (topic, log_time, data, loc) in seen.iter().cycle().skip(t * 7).take(60) {
                    let m = file.read_message(*loc, &mut cache).unwrap();
                    assert_eq!(
                        (&m.channel.topic, m.log_time, m.data),
                        (topic, *log_time, &data[..])
                    );
                }
            });
        }
    });
    // The same path rewritten with other payloads and opened again: its chunks are its
    // own, not the first file's from a cache, on this thread and through the shared
    // table alike.
    let mut cache = ChunkCache::new(8);
    let first = file
        .read_message(seen[5].3, &mut cache)
        .unwrap()
        .data
        .to_vec();
    assert_eq!(first, b"message 5");
    let (again, seen_again) = scan_bytes("shared.mcap", &sample_file_saying(true, 60, "rewrite"));
    assert_eq!(seen_again[5].3, seen[5].3, "the same chunk and index");
    let m = again.read_message(seen_again[5].3, &mut cache).unwrap();
    assert_eq!(m.data, b"rewrite 5");
}

/// A zstd frame holding `content` in one stored (raw) block.
fn zstd_stored(content: &[u8]) -> Vec<u8> {
    let size = u8::try_from(content.len()).unwrap();
    // Magic, single-segment frame with a 1-byte content size, then the block header:
    // last block, type raw, its size.
    let mut frame = vec![0x28, 0xb5, 0x2f, 0xfd, 0x20, size];
    let block = (u32::from(size) << 3) | 1;
    frame.extend_from_slice(&block.to_le_bytes()[..3]);
    frame.extend_from_slice(content);
    frame
}

/// A chunk record (opcode, length, body) around `compressed` data.
fn chunk_record(compression: &str, uncompressed_size: u64, compressed: &[u8]) -> Vec<u8> {
    padded_chunk_record(compression, uncompressed_size, compressed, 0)
}

/// [`chunk_record`] with `padding` zero bytes after the compressed data.
fn padded_chunk_record(
    compression: &str,
    uncompressed_size: u64,
    compressed: &[u8],
    padding: usize,
) -> Vec<u8> {
    let mut body = Vec::new();
    body.extend_from_slice(&0u64.to_le_bytes()); // message start time
    body.extend_from_slice(&0u64.to_le_bytes()); // message end time
    body.extend_from_slice(&uncompressed_size.to_le_bytes());
    body.extend_from_slice(&0u32.to_le_bytes()); // CRC: not checked
    body.extend_from_slice(&(compression.len() as u32).to_le_bytes());
    body.extend_from_slice(compression.as_bytes());
    body.extend_from_slice(&(compressed.len() as u64).to_le_bytes());
    body.extend_from_slice(compressed);
    body.resize(body.len() + padding, 0);
    let mut record = vec![op::CHUNK];
    record.extend_from_slice(&(body.len() as u64).to_le_bytes());
    record.extend_from_slice(&body);
    record
}

/// Found by the `mcap_drive` fuzz target: a record inside a compressed chunk that
/// declares an absurd length made mcap's chunk reader allocate that many bytes
/// before decompressing (the process aborted). Now the chunk is reported as bad.
#[test]
fn a_huge_record_length_inside_a_compressed_chunk_is_a_bad_chunk() {
    let mut content = vec![op::MESSAGE];
    content.extend_from_slice(&0x6161_6161_6161_6161u64.to_le_bytes());
    content.extend_from_slice(b"the rest of the chunk");
    for uncompressed_size in [content.len() as u64, MAX_RECORD_BYTES] {
        let mut bytes = MAGIC.to_vec();
        bytes.extend(chunk_record(
            "zstd",
            uncompressed_size,
            &zstd_stored(&content),
        ));
        scan_rejects_the_chunk("huge_record_in_chunk.mcap", &bytes);
    }
    // The same chunk holding a well-formed record (a schema) still reads.
    let schema = b"\x01\x00\x01\x00\x00\x00s\x03\x00\x00\x00raw\x00\x00\x00\x00";
    let mut content = vec![op::SCHEMA];
    content.extend_from_slice(&(schema.len() as u64).to_le_bytes());
    content.extend_from_slice(schema);
    let mut bytes = MAGIC.to_vec();
    bytes.extend(chunk_record(
        "zstd",
        content.len() as u64,
        &zstd_stored(&content),
    ));
    let (file, _) = scan_bytes("sane_chunk.mcap", &bytes);
    assert_eq!(file.chunks.len(), 1);
    assert!(
        !file
            .damage
            .iter()
            .any(|d| matches!(d, Damage::BadChunk { .. })),
        "{:?}",
        file.damage
    );
    assert_eq!(file.schemas.get(&1).map(|s| s.name.as_str()), Some("s"));
}

/// Found by the `mcap_drive` fuzz target: a record of an uncompressed chunk longer
/// than what remains of the chunk made mcap's reader overflow a subtraction (a panic
/// in debug builds). Now the chunk is reported as bad.
#[test]
fn a_record_running_past_an_uncompressed_chunk_is_a_bad_chunk() {
    // A record claiming 100 bytes where 5 remain.
    let mut overlong = vec![op::MESSAGE];
    overlong.extend_from_slice(&100u64.to_le_bytes());
    overlong.extend_from_slice(b"short");
    // An empty record, then 3 stray bytes.
    let mut stray = vec![op::MESSAGE];
    stray.extend_from_slice(&0u64.to_le_bytes());
    stray.extend_from_slice(&[op::MESSAGE, 1, 0]);
    for chunk in [overlong, stray] {
        let mut bytes = MAGIC.to_vec();
        // Padding after the records, as a writer may leave: the overlong record
        // would reach into it.
        bytes.extend(padded_chunk_record("", chunk.len() as u64, &chunk, 128));
        scan_rejects_the_chunk("record_past_chunk.mcap", &bytes);
    }
}

/// Found by the `mcap_drive` fuzz target: a summary whose chunk index points past
/// the end of the file made the scan resume there after a corrupt record and
/// underflow `len - pos` (a panic in debug builds). Such offsets are ignored now.
#[test]
fn a_chunk_index_past_the_end_of_the_file_is_ignored() {
    let bytes = sample_file(true, 12);
    let (file, _) = scan_bytes("index_past_end.mcap", &bytes);
    assert!(file.damage.is_empty(), "{:?}", file.damage);
    // Point every chunk index entry (chunk_start_offset follows the two 8-byte
    // times) far past the end, and corrupt the first chunk record so that the scan
    // looks for a place to resume.
    let mut corrupt = bytes.clone();
    let first_chunk = file.chunks[0].offset as usize;
    let summary_start = file
        .chunks
        .last()
        .map_or(0, |c| (c.offset + c.record_len) as usize);
    let mut at = summary_start;
    while at + 9 <= corrupt.len() {
        let opcode = corrupt[at];
        let len = u64::from_le_bytes(corrupt[at + 1..at + 9].try_into().unwrap()) as usize;
        if opcode == op::CHUNK_INDEX {
            let offset = at + 9 + 16;
            corrupt[offset..offset + 8].copy_from_slice(&(u64::MAX - 4).to_le_bytes());
        }
        if opcode == op::FOOTER {
            // No summary CRC: the edited summary must still be read.
            corrupt[at + 9 + 16..at + 9 + 20].fill(0);
            break;
        }
        at += 9 + len;
    }
    corrupt[first_chunk] = 0xee;
    let (file, _) = scan_bytes("index_past_end.mcap", &corrupt);
    assert!(
        file.damage.iter().any(
            |d| matches!(d, Damage::BadRecord { offset, .. } if *offset == first_chunk as u64)
        ),
        "{:?}",
        file.damage
    );
}

/// Found by the `mcap_drive` fuzz target: an uncompressed chunk in the summary
/// section, holding a record longer than the chunk, made mcap's `SummaryReader`
/// overflow a subtraction (a panic in debug builds). A summary with a record of a
/// kind that does not belong there, or one running past the section, is now no
/// usable summary (named with its byte offset) and the file is scanned linearly.
#[test]
fn a_malformed_summary_section_is_no_summary() {
    let bytes = sample_file(false, 6);
    let footer_start = bytes.len() - 37;
    assert_eq!(bytes[footer_start], op::FOOTER);
    let summary_start = u64::from_le_bytes(
        bytes[footer_start + 9..footer_start + 17]
            .try_into()
            .unwrap(),
    );
    // A chunk whose one record claims 100 bytes where 5 remain (padding after it:
    // mcap would read on into it).
    let mut overlong = vec![op::MESSAGE];
    overlong.extend_from_slice(&100u64.to_le_bytes());
    overlong.extend_from_slice(b"short");
    let chunk = padded_chunk_record("", overlong.len() as u64, &overlong, 128);
    // A schema record running past the summary section into the footer.
    let mut schema = vec![op::SCHEMA];
    schema.extend_from_slice(&1000u64.to_le_bytes());
    schema.extend_from_slice(b"short");
    for (summary, what) in [(chunk, "opcode 0x06"), (schema, "runs past the end")] {
        let mut corrupt = bytes[..summary_start as usize].to_vec();
        corrupt.extend_from_slice(&summary);
        corrupt.push(op::FOOTER);
        corrupt.extend_from_slice(&20u64.to_le_bytes());
        corrupt.extend_from_slice(&summary_start.to_le_bytes());
        corrupt.extend_from_slice(&0u64.to_le_bytes()); // no summary offsets
        corrupt.extend_from_slice(&0u32.to_le_bytes()); // no summary CRC
        corrupt.extend_from_slice(MAGIC);
        let (file, seen) = scan_bytes("malformed_summary.mcap", &corrupt);
        assert_eq!(seen.len(), 6, "{:?}", file.damage);
        assert!(
            file.damage.iter().any(|d| matches!(
                d,
                Damage::NoSummary { reason }
                    if reason.contains(&format!("byte {summary_start}")) && reason.contains(what)
            )),
            "{:?}",
            file.damage
        );
    }
}

#[test]
fn every_truncation_is_a_report_not_a_panic() {
    let bytes = sample_file(true, 12);
    for cut in (0..bytes.len()).step_by(7) {
        let dir = std::env::temp_dir().join(format!("superflow-cut-{}", std::process::id()));
        std::fs::create_dir_all(&dir).unwrap();
        let path = dir.join("cut.mcap");
        std::fs::write(&path, &bytes[..cut]).unwrap();
        let mut n = 0;
        match McapFile::scan(&path, |_| n += 1) {
            Ok(file) => {
                assert!(n <= 12);
                assert!(
                    !file.damage.is_empty(),
                    "a cut file at {cut} must report damage"
                );
            }
            Err(SourceError::NotMcap { .. }) => assert!(cut < 8),
            Err(e) => panic!("unexpected error at {cut}: {e}"),
        }
    }
}

/// `bytes` as one LZ4 frame with content and block checksums (as mcap writes chunks).
fn lz4_frame(bytes: &[u8]) -> Vec<u8> {
    use std::io::Write;
    let mut encoder = lz4::EncoderBuilder::new()
        .checksum(lz4::ContentChecksum::ChecksumEnabled)
        .block_size(lz4::BlockSize::Max64KB)
        .build(Vec::new())
        .unwrap();
    encoder.write_all(bytes).unwrap();
    let (frame, result) = encoder.finish();
    result.unwrap();
    frame
}

#[test]
fn lz4_frames_decode_without_their_checksums_and_stop_at_the_size() {
    let content: Vec<u8> = (0..300_000u32).map(|i| (i * 7 % 251) as u8).collect();
    let frame = lz4_frame(&content);
    let mut out = vec![0u8; content.len()];
    chunk::lz4_frames(&frame, &mut out).unwrap();
    assert_eq!(out, content);
    // Fewer bytes wanted than the frame holds: the first ones, the rest unread.
    let mut head = vec![0u8; 1_000];
    chunk::lz4_frames(&frame, &mut head).unwrap();
    assert_eq!(head, content[..1_000]);
    // More wanted than the frames hold, and every truncation: an error, never a panic.
    let mut more = vec![0u8; content.len() + 1];
    let err = chunk::lz4_frames(&frame, &mut more).unwrap_err();
    assert!(err.to_string().contains("frames end after"), "{err}");
    // (A cut inside the end mark and content checksum loses no data: decoded.)
    for cut in [0, 3, 7, 11, 20, frame.len() / 2, frame.len() - 20] {
        let mut out = vec![0u8; content.len()];
        assert!(
            chunk::lz4_frames(&frame[..cut], &mut out).is_err(),
            "cut {cut}"
        );
    }
    // A frame whose checksum is wrong decodes: the chunk's CRC is the check.
    let mut bad_sum = frame.clone();
    let last = bad_sum.len() - 1;
    bad_sum[last] ^= 0xFF;
    let mut out = vec![0u8; content.len()];
    chunk::lz4_frames(&bad_sum, &mut out).unwrap();
    assert_eq!(out, content);
}

#[test]
fn zstd_frames_decode_in_one_call_and_must_fill_the_declared_size() {
    let content: Vec<u8> = (0..300_000u32).map(|i| (i * 7 % 251) as u8).collect();
    let frame = zstd::bulk::compress(&content, 3).unwrap();
    assert_eq!(chunk::zstd_frames(&frame, content.len()).unwrap(), content);
    // Frames one after another (as a writer may split a chunk) decode as one.
    let mut two = zstd::bulk::compress(&content[..100_000], 3).unwrap();
    two.extend(zstd::bulk::compress(&content[100_000..], 1).unwrap());
    assert_eq!(chunk::zstd_frames(&two, content.len()).unwrap(), content);
    // Stored blocks too.
    assert_eq!(chunk::zstd_frames(&zstd_stored(b"abc"), 3).unwrap(), b"abc");
    // A declared size the frames do not fill, or overflow: an error either way.
    for size in [content.len() + 1, content.len() - 1, 0] {
        let err = chunk::zstd_frames(&frame, size).unwrap_err();
        assert!(!err.to_string().is_empty(), "size {size}");
    }
    // Every truncation and a damaged header: errors, never a panic.
    for cut in [0, 3, 4, 9, frame.len() / 2, frame.len() - 1] {
        assert!(
            chunk::zstd_frames(&frame[..cut], content.len()).is_err(),
            "cut {cut}"
        );
    }
    let mut bad = frame.clone();
    bad[0] ^= 0xFF;
    assert!(chunk::zstd_frames(&bad, content.len()).is_err());
}

#[test]
fn lz4_chunks_round_trip_and_a_flipped_byte_is_a_bad_chunk() {
    let n = 40;
    let options = mcap::WriteOptions::new()
        .use_chunks(true)
        .chunk_size(Some(100_000))
        .compression(Some(mcap::Compression::Lz4));
    let (mut writer, channels) = raw_writer(options, &["/a"]);
    let a = channels[0];
    for i in 0..n {
        let header = records::MessageHeader {
            channel_id: a,
            sequence: i,
            log_time: 1_000 + u64::from(i),
            publish_time: 1_000 + u64::from(i),
        };
        let payload = format!("message {i} ").repeat(50);
        writer
            .write_to_known_channel(&header, payload.as_bytes())
            .unwrap();
    }
    writer.finish().unwrap();
    let bytes = writer.into_inner().into_inner();
    let (file, seen) = scan_bytes("lz4.mcap", &bytes);
    assert!(file.damage.is_empty(), "{:?}", file.damage);
    assert_eq!(seen.len(), n as usize);
    for (i, (topic, time, payload, _)) in seen.iter().enumerate() {
        assert_eq!((topic.as_str(), *time), ("/a", 1_000 + i as u64));
        assert_eq!(payload, format!("message {i} ").repeat(50).as_bytes());
    }
    // A byte flipped in the compressed records: the chunk is reported (by the frame's
    // decoding or by the chunk's CRC), its messages are not delivered wrong.
    for at in [150, 400, 900] {
        let mut damaged = bytes.clone();
        damaged[at] ^= 0x20;
        let (file, seen) = scan_bytes("lz4_flipped.mcap", &damaged);
        assert!(
            file.damage
                .iter()
                .any(|d| matches!(d, Damage::BadChunk { .. })),
            "byte {at}: {:?}",
            file.damage
        );
        assert!(seen.is_empty(), "byte {at}: {} messages", seen.len());
    }
}

#[test]
fn a_checked_chunk_read_again_is_decoded_as_far_as_it_is_read_unless_its_bytes_changed() {
    // 8 zstd chunks of ~600 kB (several 128 KiB blocks each), ~30 messages a chunk.
    let options = mcap::WriteOptions::new()
        .chunk_size(Some(600_000))
        .compression(Some(mcap::Compression::Zstd));
    let (mut writer, channels) = raw_writer(options, &["/a"]);
    for i in 0..240u32 {
        let header = records::MessageHeader {
            channel_id: channels[0],
            sequence: i,
            log_time: 1_000 + u64::from(i),
            publish_time: 1_000 + u64::from(i),
        };
        let payload: Vec<u8> = (0..20_000u32)
            .map(|j| (j.wrapping_mul(2_654_435_761).wrapping_add(i) >> 24) as u8)
            .collect();
        writer.write_to_known_channel(&header, &payload).unwrap();
    }
    writer.finish().unwrap();
    let bytes = writer.into_inner().into_inner();
    let (file, seen) = scan_bytes("on_demand.mcap", &bytes);
    assert!(file.damage.is_empty(), "{:?}", file.damage);
    let firsts: Vec<&Seen> = seen
        .iter()
        .filter(|s| matches!(s.3, MessageLoc::Chunk { index: 0, .. }))
        .collect();
    assert!(firsts.len() >= 7, "{} chunks", firsts.len());
    let read = |cache: &mut ChunkCache, s: &Seen| {
        let m = file.read_message(s.3, cache).unwrap();
        assert_eq!((m.log_time, m.data), (s.1, &s.2[..]), "{:?}", s.3);
    };
    // One thread: the shared table keeps 4 chunks, so the passes below read most chunks
    // from the file again.
    let pool = rayon::ThreadPoolBuilder::new()
        .num_threads(1)
        .build()
        .unwrap();
    pool.install(|| {
        let mut cache = ChunkCache::new(1);
        // First reads decode whole chunks and check their CRCs.
        for s in &firsts {
            read(&mut cache, s);
        }
        let whole = file.decompressed();
        assert_eq!(whole.chunks, firsts.len() as u64);
        // Read again, each chunk only as far as its first message.
        for s in &firsts {
            read(&mut cache, s);
        }
        let again = file.decompressed();
        let (chunks, decoded) = (again.chunks - whole.chunks, again.bytes - whole.bytes);
        assert!(chunks >= 4, "{chunks} chunks read again");
        let per_chunk = whole.bytes / whole.chunks;
        assert!(
            decoded * 2 < chunks * per_chunk,
            "{decoded} bytes decoded for {chunks} first messages, chunks of {per_chunk}"
        );
        // Every message, last first: chunks decode on from where they stopped.
        for s in seen.iter().rev() {
            read(&mut cache, s);
        }
        // The file changes under the reader: a chunk read again with other bytes is
        // decoded whole, and the damage is found.
        let target = &file.chunks[0];
        let mut damaged = bytes.clone();
        damaged[(target.offset + target.record_len / 2) as usize] ^= 0x55;
        std::fs::write(file.path(), &damaged).unwrap();
        for s in &firsts[firsts.len() - 5..] {
            read(&mut cache, s);
        }
        let err = file
            .read_message(firsts[0].3, &mut cache)
            .expect_err("the changed chunk is rejected");
        assert!(
            err.to_string()
                .contains(&format!("chunk at byte {}", target.offset)),
            "{err}"
        );
    });
}

#[test]
fn a_file_replaced_after_its_scan_is_not_read_as_the_old_one() {
    let (file, seen) = scan_bytes("replaced.mcap", &sample_file(true, 20));
    let loc = seen[5].3;
    let mut cache = ChunkCache::new(2);
    assert_eq!(file.read_message(loc, &mut cache).unwrap().data, seen[5].2);
    // The pool closed the file (as it does past its limit); another file took its path.
    HandlePool::global().forget(file.id);
    let other = file.path().with_extension("new");
    std::fs::write(&other, sample_file_saying(true, 20, "replaced")).unwrap();
    std::fs::rename(&other, file.path()).unwrap();
    let loc = seen[15].3;
    let err = file.read_message(loc, &mut ChunkCache::new(2)).unwrap_err();
    assert!(matches!(err, SourceError::Replaced { .. }), "{err}");
    assert!(err.to_string().contains("replaced.mcap"), "{err}");
}

#[test]
fn a_file_replaced_by_an_identical_copy_is_read_on_and_a_rewrite_is_not() {
    let bytes = sample_file(true, 20);
    let (file, seen) = scan_bytes("copied.mcap", &bytes);
    assert!(file.content_digest().unwrap().is_some());
    // A re-sync: the same bytes under a new inode, the old file closed by the pool.
    HandlePool::global().forget(file.id);
    let copy = file.path().with_extension("copy");
    std::fs::write(&copy, &bytes).unwrap();
    std::fs::rename(&copy, file.path()).unwrap();
    for i in [3, 15] {
        let mut cache = ChunkCache::new(2);
        let got = file.read_message(seen[i].3, &mut cache).unwrap();
        assert_eq!(got.data, seen[i].2);
    }
    // Then rewritten with other content, same size: refused, not misread.
    HandlePool::global().forget(file.id);
    let other = sample_file_saying(true, 20, "messagf");
    let rewrite = file.path().with_extension("other");
    std::fs::write(&rewrite, &other).unwrap();
    std::fs::rename(&rewrite, file.path()).unwrap();
    let err = file
        .read_message(seen[7].3, &mut ChunkCache::new(2))
        .unwrap_err();
    assert!(matches!(err, SourceError::Replaced { .. }), "{err}");
}
