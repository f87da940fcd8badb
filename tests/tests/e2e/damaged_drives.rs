//! Damaged copies of a sample drive are read with a clear report and no panic; a damaged
//! region costs only the messages in it.

#![allow(clippy::unwrap_used, clippy::expect_used)] // tests fail loudly on purpose

use std::collections::BTreeSet;
use std::path::PathBuf;
use superflow_pipeline::drive::{Drive, IngestConfig};
use superflow_recordings::Dialect;
use superflow_tests::{sample_drive, scratch};

fn truth_stamps(dialect: Dialect) -> BTreeSet<i64> {
    let drive = sample_drive(dialect).unwrap();
    drive
        .truth
        .lidar
        .sweeps
        .iter()
        .map(|s| s.stamp_nanos)
        .collect()
}

#[test]
fn truncated_drive_reports_where_and_keeps_what_came_before() {
    for dialect in Dialect::ALL {
        let drive = sample_drive(dialect).unwrap();
        let cut = drive.bytes.len() * 6 / 10;
        let path = scratch::file(
            "damaged",
            &format!("{}_truncated.mcap", dialect.name()),
            &drive.bytes[..cut],
        );
        let dataset = Drive::open(std::slice::from_ref(&path), &IngestConfig::default()).unwrap();
        let truncated = &dataset.skipped.entries["file truncated"];
        assert!(
            truncated.first.contains(&path.display().to_string()),
            "{}",
            truncated.first
        );
        assert!(
            truncated.first.contains("truncated at byte"),
            "{}",
            truncated.first
        );
        assert!(dataset.skipped.entries.contains_key("file without summary"));
        let sweeps: BTreeSet<i64> = dataset
            .lidar
            .as_ref()
            .unwrap()
            .sweeps
            .iter()
            .map(|s| s.stamp.nanos())
            .collect();
        let truth = truth_stamps(dialect);
        assert!(sweeps.is_subset(&truth));
        // Chunks before the cut are intact: roughly 60 % of the sweeps survive.
        assert!((25..60).contains(&sweeps.len()), "{} sweeps", sweeps.len());
        let first_truth: Vec<i64> = truth.iter().take(sweeps.len()).copied().collect();
        assert_eq!(
            sweeps.into_iter().collect::<Vec<_>>(),
            first_truth,
            "the surviving sweeps are the first ones"
        );
    }
}

#[test]
fn byte_flipped_chunk_costs_only_its_messages() {
    for dialect in Dialect::ALL {
        let drive = sample_drive(dialect).unwrap();
        let mut bytes = drive.bytes.clone();
        let middle = bytes.len() / 2;
        for b in &mut bytes[middle..middle + 64] {
            *b ^= 0x5A;
        }
        let path = scratch::file(
            "damaged",
            &format!("{}_flipped.mcap", dialect.name()),
            &bytes,
        );
        let dataset = Drive::open(std::slice::from_ref(&path), &IngestConfig::default()).unwrap();
        let report: Vec<String> = dataset
            .skipped
            .entries
            .iter()
            .map(|(k, e)| format!("{k}: {}", e.first))
            .collect();
        assert!(
            report
                .iter()
                .any(|r| r.contains(&path.display().to_string())
                    && (r.contains("chunk at byte") || r.contains("corrupt record"))),
            "{report:#?}"
        );
        let lost = dataset
            .skipped
            .entries
            .get("messages lost to damage")
            .map_or(0, |e| e.count);
        assert!(lost >= 1, "{report:#?}");
        let sweeps: BTreeSet<i64> = dataset
            .lidar
            .as_ref()
            .unwrap()
            .sweeps
            .iter()
            .map(|s| s.stamp.nanos())
            .collect();
        assert!(sweeps.is_subset(&truth_stamps(dialect)));
        // One chunk of 512 KiB holds at most a few sweeps.
        assert!(sweeps.len() >= 52, "{} of 60 sweeps survive", sweeps.len());
    }
}

#[test]
fn any_single_corruption_is_reported_not_a_panic() {
    let drive = sample_drive(Dialect::Ros2).unwrap();
    let mut state = 0x2545_F491_4F6C_DD1Du64;
    for i in 0..40 {
        state ^= state << 13;
        state ^= state >> 7;
        state ^= state << 17;
        let mut bytes = drive.bytes.clone();
        let at = (state % bytes.len() as u64) as usize;
        let end = (at + 1 + (state >> 40) as usize % 16).min(bytes.len());
        for b in &mut bytes[at..end] {
            *b = b.wrapping_add(0x3D);
        }
        let path = scratch::file("damaged", &format!("corrupt_{i}.mcap"), &bytes);
        match Drive::open(std::slice::from_ref(&path), &IngestConfig::default()) {
            Ok(dataset) => {
                let sweeps = dataset.lidar.as_ref().map_or(0, |l| l.sweeps.len());
                assert!(sweeps <= 60);
            }
            Err(err) => assert!(
                err.to_string().contains(&path.display().to_string()),
                "{err}"
            ),
        }
    }
}

#[test]
fn files_that_are_not_mcap_are_clear_errors() {
    let empty = scratch::file("damaged", "empty.mcap", b"");
    let err = Drive::open(std::slice::from_ref(&empty), &IngestConfig::default())
        .unwrap_err()
        .to_string();
    assert!(
        err.contains("not an MCAP file") && err.contains(&empty.display().to_string()),
        "{err}"
    );
    let text = scratch::file(
        "damaged",
        "text.mcap",
        b"hello, this is not a recording at all",
    );
    assert!(Drive::open(&[text], &IngestConfig::default()).is_err());
    let missing = PathBuf::from("/nonexistent/drive.mcap");
    let err = Drive::open(&[missing], &IngestConfig::default())
        .unwrap_err()
        .to_string();
    assert!(err.contains("/nonexistent/drive.mcap"), "{err}");
}

/// A drive without the calibration of one camera is indexed, but training is refused
/// with a message naming the camera and its topic.
#[test]
fn missing_calibration_and_transforms_are_named() {
    let drive = sample_drive(Dialect::Ros2).unwrap();
    let config = IngestConfig {
        lidar_topic: Some("/lidar_top/points_raw".into()),
        ..IngestConfig::default()
    };
    let dataset = Drive::open(std::slice::from_ref(&drive.path), &config).unwrap();
    dataset.check_sensors().unwrap();
    let mut broken = dataset;
    broken.cameras[0].calibrations.clear();
    let err = broken.check_sensors().unwrap_err().to_string();
    assert!(
        err.contains("cam_back")
            && err.contains("/cam_back/image_raw/compressed")
            && err.contains("no calibration"),
        "{err}"
    );
    assert!(err.contains(&drive.path.display().to_string()), "{err}");
}
