//! A batch written section by section and read back; malformed batches rejected.

#![allow(clippy::unwrap_used, clippy::expect_used)] // tests fail loudly on purpose

use superflow_schemas::batch::{
    BATCH_FORMAT_VERSION, BATCH_LOST, BatchError, BatchHeader, BatchLayout, BatchMeta, BatchView,
    BatchWriter, DType, SectionId,
};

/// 8-byte aligned storage, as iceoryx2 hands out.
fn storage(len: usize) -> Vec<u64> {
    vec![0; len.div_ceil(8)]
}

struct Example {
    layout: BatchLayout,
    header: BatchHeader,
    ids: Vec<SectionId>,
}

fn example() -> Example {
    let mut layout = BatchLayout::new();
    let ids = vec![
        layout.add::<f32>("points", &[5, 4]).unwrap(),
        layout.add::<u32>("sample_ids", &[3]).unwrap(),
        layout.add::<i32>("voxel_coords", &[2, 2, 4]).unwrap(),
        layout.add::<u8>("images", &[1, 2, 3, 3]).unwrap(),
        layout.add::<i64>("stamps_nanos", &[3]).unwrap(),
        layout.add::<u8>("empty", &[0, 7]).unwrap(),
    ];
    let header = layout
        .header(&BatchMeta {
            run: "roundtrip".into(),
            epoch: 3,
            step: 11,
            seed: 42,
            sequence: 1234,
            created_unix_nanos: 1_700_000_000_000_000_000,
            sample_count: 3,
            flags: 0,
        })
        .unwrap();
    Example {
        layout,
        header,
        ids,
    }
}

fn fill(example: &Example, payload: &mut [u8]) {
    let ids = &example.ids;
    let mut writer = BatchWriter::new(&example.layout, payload).unwrap();
    // Two sections taken at once: disjoint borrows of one buffer, filled in place.
    let points = writer.take::<f32>(ids[0]).unwrap();
    let voxels = writer.take::<i32>(ids[2]).unwrap();
    for (i, v) in points.iter_mut().enumerate() {
        *v = i as f32 * 0.5 - 3.0;
    }
    for (i, v) in voxels.iter_mut().enumerate() {
        *v = -(i as i32);
    }
    writer.write(ids[1], &[7u32, 8, 9]).unwrap();
    let pixels: Vec<u8> = (0..18).map(|i| i as u8 * 10).collect();
    writer.write(ids[3], &pixels).unwrap();
    writer.write(ids[4], &[-5i64, 0, i64::MAX]).unwrap();
}

#[test]
fn written_batch_reads_back_section_by_section() {
    let example = example();
    let (layout, header) = (&example.layout, example.header);
    let mut store = storage(layout.payload_len());
    let payload: &mut [u8] = bytemuck::cast_slice_mut(&mut store);
    fill(&example, payload);
    let view = BatchView::new(&header, payload).unwrap();

    let meta = view.meta();
    assert_eq!(
        (
            meta.run.as_str(),
            meta.epoch,
            meta.step,
            meta.seed,
            meta.sequence
        ),
        ("roundtrip", 3, 11, 42, 1234)
    );
    assert_eq!(meta.sample_count, 3);
    assert_eq!(
        view.section_names().collect::<Vec<_>>(),
        [
            "points",
            "sample_ids",
            "voxel_coords",
            "images",
            "stamps_nanos",
            "empty"
        ]
    );

    let points = view.get::<f32>("points").unwrap();
    assert_eq!(points.shape(), &[5, 4]);
    assert_eq!(points.data.len(), 20);
    assert_eq!(points.data[0], -3.0);
    assert_eq!(points.data[19], 6.5);

    assert_eq!(view.get::<u32>("sample_ids").unwrap().data, &[7, 8, 9]);
    let voxels = view.get::<i32>("voxel_coords").unwrap();
    assert_eq!(voxels.shape(), &[2, 2, 4]);
    assert_eq!(voxels.data[15], -15);
    let images = view.get::<u8>("images").unwrap();
    assert_eq!(images.shape(), &[1, 2, 3, 3]);
    assert_eq!(images.data[17], 170);
    assert_eq!(
        view.get::<i64>("stamps_nanos").unwrap().data,
        &[-5, 0, i64::MAX]
    );
    let empty = view.get::<u8>("empty").unwrap();
    assert_eq!((empty.shape(), empty.data.len()), (&[0usize, 7][..], 0));
    assert_eq!(
        view.describe("voxel_coords").unwrap(),
        (DType::I32, &[2usize, 2, 4][..])
    );

    // Sections start on 64-byte boundaries; the bytes between them are zero.
    for desc in layout.sections() {
        assert_eq!(desc.offset % 64, 0);
    }
    assert!(matches!(
        view.get::<u32>("points"),
        Err(BatchError::WrongDType { .. })
    ));
    assert!(matches!(
        view.get::<f32>("nope"),
        Err(BatchError::Missing { .. })
    ));

    // The header survives a trip through raw bytes (a file, another language).
    let copy = BatchHeader::from_bytes(header.as_bytes()).unwrap();
    assert_eq!(copy.as_bytes(), header.as_bytes());
}

#[test]
fn the_same_content_gives_bit_identical_payloads() {
    let example = example();
    let mut first = storage(example.layout.payload_len());
    let mut second = vec![u64::MAX; first.len()]; // stale bytes from an earlier batch
    fill(&example, bytemuck::cast_slice_mut(&mut first));
    fill(&example, bytemuck::cast_slice_mut(&mut second));
    assert_eq!(first, second);
}

/// Every corruption of the header is reported as an error naming the problem.
#[test]
fn malformed_batches_are_rejected_with_clear_errors() {
    let example = example();
    let (layout, header) = (&example.layout, example.header);
    let mut store = storage(layout.payload_len());
    let payload: &mut [u8] = bytemuck::cast_slice_mut(&mut store);
    fill(&example, payload);
    let payload: &[u8] = payload;

    let check = |mutate: &dyn Fn(&mut BatchHeader), payload: &[u8], expect: &str| {
        let mut bad = header;
        mutate(&mut bad);
        let err = BatchView::new(&bad, payload).expect_err(expect);
        assert!(
            err.to_string().contains(expect),
            "expected `{expect}` in `{err}`"
        );
    };
    check(&|h| h.magic = 0x1234, payload, "not a superflow batch");
    // A batch of the layout before mixed rigs, and one of a later version: refused by
    // version, never misread.
    check(
        &|h| h.version = 1,
        payload,
        "batch format version 1, this build reads version 2",
    );
    check(
        &|h| h.version = BATCH_FORMAT_VERSION + 1,
        payload,
        "batch format version 3",
    );
    check(&|h| h.header_size = 100, payload, "header is 100 bytes");
    check(&|h| h.section_count = 129, payload, "129 sections");
    check(&|h| h.payload_len += 1, payload, "payload has");
    check(
        &|h| h.sections[1].dtype = 99,
        payload,
        "unknown dtype code 99",
    );
    check(&|h| h.sections[1].ndim = 0, payload, "ndim 0");
    check(&|h| h.sections[1].ndim = 5, payload, "ndim 5");
    check(
        &|h| h.sections[1].shape[0] = 4,
        payload,
        "12 bytes for shape [4]",
    );
    check(
        &|h| h.sections[1].shape[2] = 1,
        payload,
        "unused shape entries",
    );
    check(
        &|h| {
            h.sections[0].shape[0] = u64::MAX / 2;
            h.sections[0].len_bytes = u64::MAX;
        },
        payload,
        "overflows",
    );
    check(
        &|h| h.sections[4].offset = h.payload_len,
        payload,
        "outside the payload",
    );
    check(
        &|h| h.sections[4].offset = u64::MAX - 63,
        payload,
        "outside the payload",
    );
    check(&|h| h.sections[1].offset = 0, payload, "overlap");
    check(
        &|h| h.sections[0].offset = 2,
        payload,
        "not a multiple of 64",
    );
    check(
        &|h| h.sections[2].name = h.sections[1].name,
        payload,
        "used twice",
    );
    check(&|h| h.sections[2].name = [0; 32], payload, "empty");
    check(
        &|h| h.sections[2].name = [b'a'; 32],
        payload,
        "not NUL-terminated",
    );
    check(
        &|h| h.sections[2].name[1] = 0xFF,
        payload,
        "not NUL-padded UTF-8",
    );
    check(&|_| {}, &payload[..payload.len() - 1], "payload has");
    // A payload that starts 4 bytes into aligned storage: the i64 section is misaligned.
    let mut shifted = vec![0u64; payload.len().div_ceil(8) + 1];
    let shifted: &mut [u8] = bytemuck::cast_slice_mut(&mut shifted);
    shifted[4..4 + payload.len()].copy_from_slice(payload);
    check(&|_| {}, &shifted[4..], "aligned to 4 bytes; 8 needed");
    // Bits other than BATCH_LOST, and BATCH_LOST on a batch that holds something.
    check(
        &|h| h.flags = 2,
        payload,
        "flags 0x2 set; version 2 defines only BATCH_LOST",
    );
    check(&|h| h.flags = BATCH_LOST | 4, payload, "flags 0x5 set");
    check(
        &|h| h.flags = BATCH_LOST,
        payload,
        "a lost batch (flag BATCH_LOST) holds nothing, but this one declares 6 sections",
    );
    check(&|h| h.run[0] = b'/', payload, "run name");
    check(&|h| h.run = [0; 64], payload, "empty");
    check(
        &|h| h.sections[100].dtype = 7,
        payload,
        "`#100`: an unused table entry is not zero",
    );
    check(
        &|h| {
            h.sections[5].offset += 8; // the empty section, misaligned
        },
        payload,
        "not a multiple of 64",
    );
}

/// Random corruption of header bytes never panics; it is either rejected or still
/// describes sections inside the payload.
#[test]
fn random_header_corruption_never_panics() {
    let example = example();
    let (layout, header) = (&example.layout, example.header);
    let mut store = storage(layout.payload_len());
    let payload: &mut [u8] = bytemuck::cast_slice_mut(&mut store);
    fill(&example, payload);
    let mut state = 0x9E37_79B9_7F4A_7C15u64;
    let mut next = move || {
        state ^= state << 13;
        state ^= state >> 7;
        state ^= state << 17;
        state
    };
    let used = 136 + 88 * layout.sections().len();
    for _ in 0..20_000 {
        let mut bytes = header.as_bytes().to_vec();
        for _ in 0..(1 + next() % 4) {
            let at = (next() % used as u64) as usize;
            bytes[at] ^= 1 << (next() % 8);
        }
        let bad = BatchHeader::from_bytes(&bytes).unwrap();
        if let Ok(view) = BatchView::new(&bad, payload) {
            for name in view.section_names() {
                let raw = view.bytes(name).unwrap();
                let (_, shape) = view.describe(name).unwrap();
                assert!(raw.len() <= payload.len());
                assert!(shape.iter().product::<usize>() <= raw.len());
            }
        }
    }
}

/// A lost batch (every sample failed in the pipeline): its place in the stream and
/// nothing else. Written by `BatchHeader::lost`, read with any payload slice (iceoryx2
/// may hand out a few bytes), refused when it claims sections, samples or payload bytes.
#[test]
fn lost_batches_keep_their_place_and_hold_nothing() {
    let meta = BatchMeta {
        run: "lost".into(),
        epoch: 2,
        step: 5,
        seed: 9,
        sequence: 77,
        created_unix_nanos: 1,
        sample_count: 4, // ignored: a lost batch has none
        flags: 0,
    };
    let header = BatchHeader::lost(&meta).unwrap();
    assert_eq!(
        (
            header.flags,
            header.section_count,
            header.sample_count,
            header.payload_len
        ),
        (BATCH_LOST, 0, 0, 0)
    );
    assert!(
        header
            .sections
            .iter()
            .all(|s| s.len_bytes == 0 && s.ndim == 0)
    );
    for payload in [&[][..], &[0u8; 8][..]] {
        let view = BatchView::new(&header, payload).unwrap();
        assert!(view.is_lost() && view.meta().lost());
        let m = view.meta();
        assert_eq!((m.epoch, m.step, m.seed, m.sequence), (2, 5, 9, 77));
        assert_eq!(m.run, "lost");
        assert_eq!(view.section_names().count(), 0);
        assert!(matches!(
            view.get::<u64>("sample_ids"),
            Err(BatchError::Missing { .. })
        ));
    }
    // An ordinary batch is not lost.
    let example = example();
    let mut store = storage(example.layout.payload_len());
    let payload: &mut [u8] = bytemuck::cast_slice_mut(&mut store);
    fill(&example, payload);
    assert!(!BatchView::new(&example.header, payload).unwrap().is_lost());

    let refused = |mutate: &dyn Fn(&mut BatchHeader)| {
        let mut bad = header;
        mutate(&mut bad);
        BatchView::new(&bad, &[0u8; 64]).unwrap_err()
    };
    for err in [
        refused(&|h| h.sample_count = 1),
        refused(&|h| h.payload_len = 8),
        refused(&|h| h.section_count = 1),
    ] {
        assert!(matches!(err, BatchError::LostWithContent { .. }), "{err}");
    }
    // The writer refuses the flag on a layout that holds something, and unknown flags.
    let mut layout = BatchLayout::new();
    layout.add::<u8>("x", &[1]).unwrap();
    let lost_meta = BatchMeta {
        flags: BATCH_LOST,
        sample_count: 0,
        ..meta.clone()
    };
    assert!(matches!(
        layout.header(&lost_meta),
        Err(BatchError::LostWithContent { sections: 1, .. })
    ));
    assert!(matches!(
        BatchLayout::new().header(&BatchMeta {
            sample_count: 1,
            ..lost_meta.clone()
        }),
        Err(BatchError::LostWithContent { samples: 1, .. })
    ));
    assert!(matches!(
        BatchLayout::new().header(&BatchMeta { flags: 2, ..meta }),
        Err(BatchError::Flags { found: 2 })
    ));
    assert!(BatchLayout::new().header(&lost_meta).is_ok());
}
