//! Cross-language checks: independent Python readers (the `mcap` package's ROS 2 and
//! protobuf decoders, numpy) agree with the drives' ground truth and with the Rust batch
//! reader. Needs `pip install -r tests/python/requirements.txt`.

#![allow(clippy::unwrap_used, clippy::expect_used)] // tests fail loudly on purpose

use serde_json::json;
use std::process::Command;
use superflow_schemas::batch::{BatchHeader, BatchLayout, BatchMeta, BatchView, BatchWriter};
use superflow_tests::workspace_root;

fn python(args: &[&str]) -> String {
    let output = Command::new("python3")
        .args(args)
        .current_dir(workspace_root())
        .output()
        .expect("python3 runs (install the packages of tests/python/requirements.txt)");
    let text = format!(
        "{}{}",
        String::from_utf8_lossy(&output.stdout),
        String::from_utf8_lossy(&output.stderr)
    );
    assert!(output.status.success(), "python3 {args:?} failed:\n{text}");
    text
}

/// A check script's last line is `N passed, 0 failed` with N > 0.
fn assert_checks_passed(text: &str) {
    let last = text
        .lines()
        .rev()
        .find(|l| !l.trim().is_empty())
        .unwrap_or("");
    assert!(
        last.ends_with(" 0 failed") && !last.starts_with("0 passed"),
        "{text}"
    );
}

#[test]
fn independent_python_decoders_agree_with_the_ground_truth() {
    assert_checks_passed(&python(&[
        "tests/python/check_drives.py",
        "recordings/drives",
    ]));
}

#[test]
fn the_numpy_loader_unpacks_a_drive_and_times_its_samples() {
    // The baseline of pipeline/docs/BENCHMARKS.md (a numpy + Pillow loader on files): one
    // file per sweep holding every point of the sweep (x, y, z, intensity as float32),
    // every camera, and a table row of positive times.
    let out = workspace_root().join(format!("target/baseline-loader-{}", std::process::id()));
    let out_arg = out.to_string_lossy().into_owned();
    let text = python(&[
        "tests/python/baseline_loader.py",
        "recordings/drives/street_foxglove.mcap",
        "--samples",
        "2",
        "--out",
        &out_arg,
    ]);
    let read = |path: std::path::PathBuf| -> serde_json::Value {
        serde_json::from_slice(&std::fs::read(&path).unwrap()).unwrap()
    };
    let truth = read(workspace_root().join("recordings/drives/street_foxglove.truth.json"));
    let index = read(out.join("index.json"));
    let (sweeps, truth_sweeps) = (
        index["sweeps"].as_array().unwrap(),
        truth["lidar"]["sweeps"].as_array().unwrap(),
    );
    assert_eq!(sweeps.len(), truth_sweeps.len());
    for (sweep, expected) in sweeps.iter().zip(truth_sweeps) {
        assert_eq!(sweep["stamp"], expected["stamp_nanos"]);
        let bytes = std::fs::metadata(out.join(sweep["file"].as_str().unwrap()))
            .unwrap()
            .len();
        assert_eq!(bytes, 16 * expected["points"].as_u64().unwrap());
    }
    let cameras = index["cameras"].as_object().unwrap();
    assert_eq!(cameras.len(), truth["cameras"].as_array().unwrap().len());
    assert!(cameras.values().all(|c| {
        let images = c["images"].as_array().unwrap();
        !images.is_empty() && images.iter().all(|i| i["png"].is_string())
    }));
    let row = text.lines().last().unwrap();
    let times: Vec<f64> = row
        .split('|')
        .filter(|c| !c.trim().is_empty())
        .map(|c| c.trim().parse().unwrap())
        .collect();
    assert_eq!(times.len(), 7, "{text}");
    assert!(times[0] > 0.0 && times.iter().all(|t| *t >= 0.0), "{text}");
    std::fs::remove_dir_all(&out).unwrap();
}

#[test]
fn numpy_reads_a_batch_exactly_as_the_rust_reader() {
    let mut layout = BatchLayout::new();
    let points = layout.add::<f32>("points", &[3, 4]).unwrap();
    let voxels = layout.add::<i32>("voxel_coords", &[2, 3]).unwrap();
    let ids = layout.add::<u64>("sample_ids", &[2]).unwrap();
    let image = layout.add::<u8>("images", &[1, 2, 2, 3]).unwrap();
    let ring = layout.add::<u16>("ring", &[3]).unwrap();
    let stamps = layout.add::<i64>("stamps_nanos", &[2]).unwrap();
    let counts = layout.add::<u32>("counts", &[1]).unwrap();
    let weights = layout.add::<f64>("weights", &[2]).unwrap();
    let empty = layout.add::<f32>("empty", &[0, 64]).unwrap();
    let meta = BatchMeta {
        run: "python-check".into(),
        epoch: 2,
        step: 5,
        seed: 77,
        sequence: 9,
        created_unix_nanos: 1_700_000_000_000_000_000,
        sample_count: 2,
        flags: 0,
    };
    let header = layout.header(&meta).unwrap();
    let mut storage = vec![0u64; layout.payload_len().div_ceil(8)];
    let payload: &mut [u8] = bytemuck::cast_slice_mut(&mut storage);
    {
        let mut w = BatchWriter::new(&layout, payload).unwrap();
        w.write(
            points,
            &[
                0.5f32, -1.25, 3.0, 7.0, 1e-3, 2.5e6, -0.0, 1.0, 9.0, 8.0, 7.5, -6.0,
            ],
        )
        .unwrap();
        w.write(voxels, &[1i32, -2, 3, i32::MAX, i32::MIN, 0])
            .unwrap();
        w.write(ids, &[u64::MAX, 12]).unwrap();
        w.write(image, &[0u8, 10, 20, 30, 40, 50, 60, 70, 80, 90, 100, 255])
            .unwrap();
        w.write(ring, &[0u16, 31, 65_535]).unwrap();
        w.write(stamps, &[1_700_000_000_123_456_789i64, -1])
            .unwrap();
        w.write(counts, &[42u32]).unwrap();
        w.write(weights, &[0.1f64, -1e300]).unwrap();
        w.write::<f32>(empty, &[]).unwrap();
    }
    let payload: &[u8] = payload;

    // The expected arrays are what the Rust reader hands out.
    let view = BatchView::new(&header, payload).unwrap();
    let mut sections = serde_json::Map::new();
    for name in view.section_names() {
        let (dtype, shape) = view.describe(name).unwrap();
        let values = match dtype.numpy() {
            "<f4" => json!(view.get::<f32>(name).unwrap().data),
            "<f8" => json!(view.get::<f64>(name).unwrap().data),
            "<i4" => json!(view.get::<i32>(name).unwrap().data),
            "<i8" => json!(view.get::<i64>(name).unwrap().data),
            "<u1" => json!(view.get::<u8>(name).unwrap().data),
            "<u2" => json!(view.get::<u16>(name).unwrap().data),
            "<u4" => json!(view.get::<u32>(name).unwrap().data),
            "<u8" => json!(view.get::<u64>(name).unwrap().data),
            other => panic!("unexpected dtype {other}"),
        };
        sections.insert(
            name.to_string(),
            json!({ "dtype": dtype.numpy(), "shape": shape, "values": values }),
        );
    }
    let expected = json!({
        "meta": {
            "run": meta.run, "epoch": meta.epoch, "step": meta.step, "seed": meta.seed,
            "sequence": meta.sequence, "sample_count": meta.sample_count,
        },
        "sections": sections,
    });

    let dir = std::env::temp_dir().join(format!("superflow-batch-{}", std::process::id()));
    std::fs::create_dir_all(&dir).unwrap();
    let batch_path = dir.join("batch.bin");
    let expected_path = dir.join("expected.json");
    let mut file = header.as_bytes().to_vec();
    assert_eq!(file.len(), BatchHeader::SIZE);
    file.extend_from_slice(payload);
    std::fs::write(&batch_path, file).unwrap();
    std::fs::write(&expected_path, serde_json::to_vec(&expected).unwrap()).unwrap();
    let text = python(&[
        "tests/python/read_batch.py",
        batch_path.to_str().unwrap(),
        expected_path.to_str().unwrap(),
    ]);
    std::fs::remove_dir_all(&dir).ok();
    let last = text
        .lines()
        .rev()
        .find(|l| !l.trim().is_empty())
        .unwrap_or("");
    assert!(last.ends_with(" 0 failed"), "{text}");
}

/// A sample written as `.npy` + `sample.json` + PNGs (what `superflow-pipeline sample`
/// writes) passes the independent numpy checks of `tests/python/check_sample.py`:
/// shapes, counts, pairings recomputed from (u, v) and flips, superpixel lookups,
/// voxel cells recomputed from the points.
#[test]
fn numpy_checks_an_exported_sample() {
    use superflow_pipeline::sample::export::write_sample;
    use superflow_pipeline::sample::{SampleBuilder, SampleConfig};
    use superflow_recordings::Dialect;
    for (dialect, augment, keyframe) in [(Dialect::Ros2, false, 1), (Dialect::Foxglove, true, 3)] {
        let drive = superflow_tests::sample_drive(dialect).unwrap();
        let ds = superflow_tests::sample_dataset(&drive).unwrap();
        let mut config = SampleConfig::default();
        config.augment.enabled = augment;
        let builder = SampleBuilder::new(&ds, config).unwrap();
        let sample = builder
            .build_keyframe(keyframe, 0, keyframe as u64)
            .unwrap();
        let dir = std::env::temp_dir().join(format!(
            "superflow-sample-{}-{}-{augment}",
            std::process::id(),
            dialect.name()
        ));
        let _ = std::fs::remove_dir_all(&dir);
        write_sample(
            &sample,
            builder.config(),
            &drive.path.display().to_string(),
            &dir,
        )
        .unwrap();
        assert_checks_passed(&python(&[
            "tests/python/check_sample.py",
            dir.to_str().unwrap(),
        ]));
        std::fs::remove_dir_all(&dir).unwrap();
    }
}

/// The facts `tests/python/check_sample_mcap.py` checks a view file against, taken from
/// the samples themselves: per frame (once per stamp, as the view writes them) the cloud's
/// size, the chosen cameras and each pairing's point, camera and pixel; per sample the
/// dense cloud's size, paired points and source sweeps.
fn view_facts(
    samples: &[superflow_pipeline::sample::Sample],
    ds: &superflow_pipeline::drive::Dataset,
    config: &superflow_pipeline::sample::SampleConfig,
) -> serde_json::Value {
    let mut seen = std::collections::HashSet::new();
    let mut frames = Vec::new();
    let mut dense = Vec::new();
    for sample in samples {
        let drive = &ds.drives[sample.id.drive as usize];
        let lidar_frame = drive.lidar.as_ref().unwrap().frame_id.clone();
        for frame in &sample.frames {
            if !seen.insert(frame.lidar_stamp) {
                continue;
            }
            frames.push(json!({
                "stamp": frame.lidar_stamp.nanos(),
                "points": frame.cloud.xyz.len(),
                "lidar_frame": lidar_frame,
                "image_size": [config.image_width, config.image_height],
                "cameras": frame.images.iter().map(|i| json!({
                    "topic": i.camera.trim_matches('/').replace('/', "_"),
                    "frame_id": i.calibration.frame_id,
                })).collect::<Vec<_>>(),
                "pairs": frame.cloud.pairings.iter()
                    .map(|p| [p.point, u32::from(p.camera), u32::from(p.row), u32::from(p.col)])
                    .collect::<Vec<_>>(),
            }));
        }
        let key = &sample.frames[sample.key_frame];
        let paired: std::collections::HashSet<u32> =
            sample.dense.pairings.iter().map(|p| p.point).collect();
        let mut sources: Vec<u8> = sample.dense.source_sweep.clone();
        sources.sort_unstable();
        sources.dedup();
        dense.push(json!({
            "stamp": key.lidar_stamp.nanos(),
            "points": sample.dense.xyz.len(),
            "paired": paired.len(),
            "sources": sources,
        }));
    }
    json!({ "frames": frames, "dense": dense })
}

/// Samples written as MCAP for Foxglove (`superflow-pipeline sample --out-mcap`, and a
/// whole drive as with `--drive-mcap`) read back by the reference `mcap` reader with
/// Foxglove's published protobuf classes (`tests/python/check_sample_mcap.py`): the
/// counts are the samples', and every paired point projects through the written
/// transforms and calibration (lens model included, images flipped or not) to within
/// 0.5 px of its pairing's pixel.
#[test]
fn foxglove_reads_samples_written_as_mcap() {
    use superflow_pipeline::sample::{SampleBuilder, SampleConfig};
    use superflow_pipeline::view::SampleMcap;
    use superflow_recordings::Dialect;
    let mut flipped = 0;
    for (dialect, augment, keyframes) in [
        (Dialect::Ros2, false, vec![1]),
        (Dialect::Foxglove, true, vec![3]),
        (Dialect::Foxglove, true, vec![0, 1, 2, 3, 4, 5]),
    ] {
        let drive = superflow_tests::sample_drive(dialect).unwrap();
        let ds = superflow_tests::sample_dataset(&drive).unwrap();
        let mut config = SampleConfig::default();
        config.augment.enabled = augment;
        let builder = SampleBuilder::new(&ds, config).unwrap();
        let samples: Vec<_> = keyframes
            .iter()
            .map(|&k| builder.build_keyframe(k, 0, k as u64).unwrap())
            .collect();
        let dir = std::env::temp_dir().join(format!(
            "superflow-view-{}-{}-{}",
            std::process::id(),
            dialect.name(),
            keyframes.len()
        ));
        std::fs::create_dir_all(&dir).unwrap();
        let file = dir.join("view.mcap");
        let mut view = SampleMcap::create(&file, builder.config()).unwrap();
        for sample in &samples {
            view.add(sample, &ds.drives[sample.id.drive as usize])
                .unwrap();
        }
        let summary = view.finish().unwrap();
        assert_eq!(summary.samples, samples.len());
        // Mirrored images are among them: their calibrations are checked too.
        flipped += samples
            .iter()
            .flat_map(|s| &s.frames)
            .flat_map(|f| &f.images)
            .filter(|i| i.flipped)
            .count();
        let facts = view_facts(&samples, &ds, builder.config());
        assert_eq!(summary.frames, facts["frames"].as_array().unwrap().len());
        let expected = dir.join("expected.json");
        std::fs::write(&expected, facts.to_string()).unwrap();
        let text = python(&[
            "tests/python/check_sample_mcap.py",
            file.to_str().unwrap(),
            expected.to_str().unwrap(),
        ]);
        assert_checks_passed(&text);
        eprintln!("{} {keyframes:?}: {text}", dialect.name());
        std::fs::remove_dir_all(&dir).unwrap();
    }
    assert!(flipped > 0);
}
