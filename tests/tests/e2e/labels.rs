//! Per-point labels read from the recordings (`superflow_pipeline::drive::labels`)
//! against the simulation that wrote them: the Foxglove sample drive's `label` field and
//! the ROS 2 sample drive's `<drive>.labels.mcap` sidecar give, for every sweep and every
//! point the pipeline keeps, the class the simulated return hit; points dropped as
//! invalid take their labels with them in both forms; a sidecar cloud with a wrong point
//! count or a missing one, and a raw id without a class, are errors naming file, topic
//! and stamp; a mapping maps and sends unlisted ids to the ignore index.

#![allow(clippy::unwrap_used, clippy::expect_used)] // tests fail loudly on purpose

use nalgebra::Point3;
use std::collections::BTreeMap;
use std::path::{Path, PathBuf};
use superflow_pipeline::drive::{
    Dataset, DriveLabels, IngestConfig, LabelConfig, LabelError, LabelForm,
};
use superflow_pipeline::sample::{SampleBuilder, SampleConfig};
use superflow_pipeline::source::ChunkCache;
use superflow_recordings::out::McapOut;
use superflow_recordings::{
    Dialect, DriveOptions, LidarLabels, Simulation, foxglove, ros2, simulate, simulate_with,
};
use superflow_schemas::Stamp;
use superflow_schemas::ros2::{Header, PointCloud2, PointField, Ros2Message, Ros2Time};
use superflow_tests::{sample_dataset, sample_drive, scratch};

/// Writes `sim` in `dialect` into `dir` as `drive.mcap` (with `drive.labels.mcap` when
/// its labels go to a sidecar); returns the drive's path.
fn write(sim: &Simulation, dialect: Dialect, dir: &Path) -> PathBuf {
    let drive = match dialect {
        Dialect::Foxglove => foxglove::write(sim),
        Dialect::Ros2 => ros2::write(sim),
    }
    .unwrap();
    let path = dir.join("drive.mcap");
    std::fs::write(&path, &drive.mcap).unwrap();
    if let Some(bytes) = &drive.labels_sidecar {
        std::fs::write(dir.join("drive.labels.mcap"), bytes).unwrap();
    }
    path
}

fn open(path: &Path) -> Dataset {
    Dataset::open(&[path.to_path_buf()], &IngestConfig::default()).unwrap()
}

/// Every sweep's training labels, in sweep order.
fn all_labels(labels: &DriveLabels<'_>) -> Vec<Vec<u8>> {
    let mut cache = ChunkCache::new(2);
    (0..labels.sweeps())
        .map(|k| labels.training_labels(k, &mut cache).unwrap())
        .collect()
}

#[test]
fn both_forms_decode_to_the_class_of_every_simulated_return() {
    for dialect in Dialect::ALL {
        let drive = sample_drive(dialect).unwrap();
        let truth = drive.truth.labels.as_ref().expect("labelled sample drive");
        let dataset = sample_dataset(&drive).unwrap();
        let d = &dataset.drives[0];
        let labels = DriveLabels::open(d, &LabelConfig::default())
            .unwrap()
            .expect("labels found");
        match (labels.form(), truth.form.as_str()) {
            (LabelForm::Field { field }, "field") => assert_eq!(*field, truth.field),
            (LabelForm::Sidecar { file, topic }, "sidecar") => {
                assert_eq!(*topic, truth.topic);
                let name = &truth.sidecar.as_ref().unwrap().file;
                assert!(file.ends_with(&format!("/{name}")), "{file}");
            }
            (form, want) => panic!("{dialect:?}: labels found as {form:?}, written as {want}"),
        }
        assert_eq!(
            d.label_form(&LabelConfig::default()).unwrap().as_ref(),
            Some(labels.form())
        );
        let sim = simulate(dialect);
        let lidar = d.lidar.as_ref().unwrap();
        assert_eq!(labels.sweeps(), sim.sweeps.len());
        let mut cache = ChunkCache::new(2);
        let mut per_class = vec![0u64; truth.points_per_class.len()];
        for (k, sweep) in lidar.sweeps.iter().enumerate() {
            assert_eq!(sweep.stamp.nanos(), drive.truth.lidar.sweeps[k].stamp_nanos);
            let read = labels.read(k, &mut cache).unwrap();
            // Aligned with the sweep as the pipeline reads it (nothing dropped here).
            let plain = d.read_sweep(sweep, &mut cache).unwrap();
            assert_eq!(
                read.decoded.cloud.xyz, plain.cloud.xyz,
                "{dialect:?} sweep {k}"
            );
            assert_eq!(read.decoded.dropped_non_finite, 0);
            read.decoded.cloud.validate().unwrap();
            assert_eq!(read.labels, sim.sweep_classes(k), "{dialect:?} sweep {k}");
            let raw = read.decoded.cloud.label.as_deref().unwrap();
            assert!(
                raw.iter()
                    .zip(&read.labels)
                    .all(|(r, l)| *r == u32::from(*l))
            );
            for class in &read.labels {
                per_class[usize::from(*class)] += 1;
            }
        }
        assert_eq!(per_class, truth.points_per_class);
    }
}

#[test]
fn labels_align_with_the_sweeps_the_sample_builder_reads() {
    for dialect in Dialect::ALL {
        let dataset = sample_dataset(&sample_drive(dialect).unwrap()).unwrap();
        let mut config = SampleConfig::default();
        config.augment.enabled = false;
        let builder = SampleBuilder::new(&dataset, config).unwrap();
        let labels = DriveLabels::open(&dataset.drives[0], &LabelConfig::default())
            .unwrap()
            .unwrap();
        let mut cache = ChunkCache::new(2);
        for (index, key) in builder.plan().keyframes.iter().enumerate() {
            let sample = builder.build_keyframe(index, 0, index as u64).unwrap();
            for (frame, sweep) in sample.frames.iter().zip(&key.frame_sweeps) {
                let read = labels.read(*sweep as usize, &mut cache).unwrap();
                assert_eq!(
                    frame.cloud.xyz.len(),
                    read.labels.len(),
                    "{dialect:?} {index}"
                );
                if dialect == Dialect::Foxglove {
                    // Motion compensated: no de-skew, the very points.
                    assert_eq!(frame.cloud.xyz, read.decoded.cloud.xyz);
                }
            }
        }
    }
}

/// A short labelled drive whose returns `poisoned(sweep, index)` selects are written as
/// NaN points, with the labels of `labels` in `dialect`.
fn poisoned_drive(
    dialect: Dialect,
    labels: LidarLabels,
    poisoned: impl Fn(usize, usize) -> bool,
) -> (Simulation, PathBuf) {
    let options = DriveOptions {
        labels,
        ..DriveOptions::short()
    };
    let mut sim = simulate_with(dialect, &options);
    let nan = Point3::new(f64::NAN, f64::NAN, f64::NAN);
    for (k, sweep) in sim.sweeps.iter_mut().enumerate() {
        for (i, r) in sweep.iter_mut().enumerate() {
            if poisoned(k, i) {
                r.point_in_map = nan;
            }
        }
    }
    let dir = scratch::dir("labels", &format!("{}-{}", dialect.name(), labels.name()));
    let path = write(&sim, dialect, &dir);
    (sim, path)
}

#[test]
fn points_dropped_as_invalid_drop_their_labels_in_both_forms_and_dialects() {
    let poisoned = |k: usize, i: usize| (k == 3 && i % 7 == 2) || (k == 8 && i < 40);
    for dialect in Dialect::ALL {
        for form in [LidarLabels::InCloud, LidarLabels::Sidecar] {
            let (sim, path) = poisoned_drive(dialect, form, poisoned);
            let dataset = open(&path);
            let d = &dataset.drives[0];
            let labels = DriveLabels::open(d, &LabelConfig::default())
                .unwrap()
                .unwrap();
            let sidecar = matches!(labels.form(), LabelForm::Sidecar { .. });
            assert_eq!(sidecar, form == LidarLabels::Sidecar, "{dialect:?}");
            let mut cache = ChunkCache::new(2);
            for k in 0..labels.sweeps() {
                let read = labels.read(k, &mut cache).unwrap();
                let expected: Vec<u8> = sim.sweeps[k]
                    .iter()
                    .enumerate()
                    .filter(|(i, _)| !poisoned(k, *i))
                    .map(|(_, r)| r.class)
                    .collect();
                let dropped = sim.sweeps[k].len() - expected.len();
                assert_eq!(read.decoded.dropped_non_finite, dropped);
                assert_eq!(read.labels, expected, "{dialect:?} {form:?} sweep {k}");
                assert_eq!(read.labels.len(), read.decoded.cloud.len());
            }
            std::fs::remove_dir_all(path.parent().unwrap()).unwrap();
        }
    }
}

/// A labels sidecar for the ROS 2 drive of `sim`: the label cloud of each sweep, except
/// that `edit(sweep, labels)` may change its labels or (`None`) leave it out.
fn ros2_sidecar(sim: &Simulation, edit: impl Fn(usize, Vec<u8>) -> Option<Vec<u8>>) -> Vec<u8> {
    let mut out = McapOut::default();
    let schema = (
        PointCloud2::SCHEMA_NAME,
        superflow_schemas::ros2::SCHEMA_ENCODING,
        PointCloud2::SCHEMA_DEFINITION.as_bytes(),
    );
    let channel = out.channel(
        ros2::LABELS_TOPIC,
        "labels",
        schema,
        superflow_schemas::ros2::MESSAGE_ENCODING,
        BTreeMap::new(),
    );
    for k in 0..sim.sweeps.len() {
        let Some(labels) = edit(k, sim.sweep_classes(k)) else {
            continue;
        };
        let (begin, _) = sim.timing.sweep_span(k);
        let cloud = PointCloud2 {
            header: Header {
                stamp: Ros2Time::from_nanos(begin.nanos()).unwrap(),
                frame_id: ros2::LIDAR_FRAME.into(),
            },
            height: 1,
            width: labels.len() as u32,
            fields: vec![PointField {
                name: "label".into(),
                offset: 0,
                datatype: PointField::UINT8,
                count: 1,
            }],
            is_bigendian: false,
            point_step: 1,
            row_step: labels.len() as u32,
            data: labels,
            is_dense: true,
        };
        let bytes = superflow_schemas::ros2::encode(&cloud).unwrap();
        out.message(channel, begin.nanos(), begin.nanos(), bytes);
    }
    out.finish("ros2", None).unwrap().0
}

#[test]
fn a_wrong_or_missing_label_cloud_is_an_error_naming_file_topic_and_stamp() {
    let options = DriveOptions {
        labels: LidarLabels::Sidecar,
        ..DriveOptions::short()
    };
    let sim = simulate_with(Dialect::Ros2, &options);
    let dir = scratch::dir("labels", "wrong-count");
    let path = write(&sim, Dialect::Ros2, &dir);
    let sidecar = dir.join("drive.labels.mcap");
    std::fs::write(
        &sidecar,
        ros2_sidecar(&sim, |k, mut labels| match k {
            4 => {
                labels.pop();
                Some(labels)
            }
            6 => None,
            _ => Some(labels),
        }),
    )
    .unwrap();
    let dataset = open(&path);
    let labels = DriveLabels::open(&dataset.drives[0], &LabelConfig::default())
        .unwrap()
        .unwrap();
    let mut cache = ChunkCache::new(2);
    let stamp = |k: usize| sim.timing.sweep_span(k).0;
    let points = sim.sweeps[4].len();

    let e = labels.read(4, &mut cache).unwrap_err();
    let text = e.to_string();
    assert!(matches!(e, LabelError::PointCount { .. }), "{text}");
    for words in [
        sidecar.display().to_string(),
        ros2::LABELS_TOPIC.to_string(),
        stamp(4).to_string(),
        format!("{} labels for the {points} points", points - 1),
    ] {
        assert!(text.contains(&words), "{text} lacks {words}");
    }

    let e = labels.read(6, &mut cache).unwrap_err();
    let text = e.to_string();
    assert!(matches!(e, LabelError::MissingLabelCloud { .. }), "{text}");
    for words in [
        sidecar.display().to_string(),
        ros2::LABELS_TOPIC.to_string(),
        stamp(6).to_string(),
        ros2::LIDAR_TOPIC.to_string(),
    ] {
        assert!(text.contains(&words), "{text} lacks {words}");
    }
    // The other sweeps still read.
    assert_eq!(
        labels.training_labels(5, &mut cache).unwrap(),
        sim.sweep_classes(5)
    );
    std::fs::remove_dir_all(dir).unwrap();
}

#[test]
fn an_unknown_raw_id_without_a_mapping_is_an_error_naming_file_topic_stamp_and_id() {
    let drive = sample_drive(Dialect::Foxglove).unwrap();
    let dataset = sample_dataset(&drive).unwrap();
    let d = &dataset.drives[0];
    // Five classes named: the road (11) has none.
    let config = LabelConfig {
        classes: ["noise", "barrier", "bicycle", "bus", "car"]
            .map(String::from)
            .to_vec(),
        ..LabelConfig::default()
    };
    let labels = DriveLabels::open(d, &config).unwrap().unwrap();
    let mut cache = ChunkCache::new(2);
    let e = labels.read(0, &mut cache).unwrap_err();
    let text = e.to_string();
    let first_unknown = simulate(Dialect::Foxglove)
        .sweep_classes(0)
        .into_iter()
        .find(|c| *c >= 5)
        .unwrap();
    assert!(
        matches!(e, LabelError::UnknownId { id, .. } if id == u32::from(first_unknown)),
        "{text}"
    );
    let stamp = Stamp::from_nanos(drive.truth.lidar.sweeps[0].stamp_nanos);
    for words in [
        drive.path.display().to_string(),
        "/LIDAR_TOP".to_string(),
        stamp.to_string(),
        format!("unknown raw id {first_unknown} without a mapping"),
        "5 classes".to_string(),
    ] {
        assert!(text.contains(&words), "{text} lacks {words}");
    }
}

#[test]
fn a_mapping_maps_and_sends_unlisted_ids_to_the_ignore_index() {
    // Cars and the road are the two training classes; noise is ignored explicitly,
    // everything else because it is not listed.
    let config = LabelConfig {
        mapping: BTreeMap::from([
            ("4".to_string(), 0),
            ("11".to_string(), 1),
            ("0".to_string(), 255),
        ]),
        classes: vec!["car".into(), "road".into()],
        ..LabelConfig::default()
    };
    let sim = simulate(Dialect::Ros2);
    let dataset = sample_dataset(&sample_drive(Dialect::Ros2).unwrap()).unwrap();
    let labels = DriveLabels::open(&dataset.drives[0], &config)
        .unwrap()
        .unwrap();
    let got = all_labels(&labels);
    let mut seen = [0usize; 3];
    for (k, sweep) in got.iter().enumerate() {
        let expected: Vec<u8> = sim
            .sweep_classes(k)
            .iter()
            .map(|c| match c {
                4 => 0,
                11 => 1,
                _ => 255,
            })
            .collect();
        assert_eq!(*sweep, expected, "sweep {k}");
        for l in sweep {
            seen[usize::from(*l).min(2)] += 1;
        }
    }
    assert!(seen.iter().all(|n| *n > 0), "{seen:?}");
}
