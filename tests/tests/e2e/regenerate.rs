//! The generator reproduces the committed sample drives byte for byte.

#![allow(clippy::unwrap_used, clippy::expect_used)] // tests fail loudly on purpose

use superflow_recordings::{Dialect, DriveOptions, damaged, generate};
use superflow_tests::{sample_drive, workspace_root};

#[test]
fn generator_reproduces_the_committed_drives_byte_for_byte() {
    for dialect in Dialect::ALL {
        let committed = sample_drive(dialect).unwrap();
        let drive = generate(dialect).unwrap();
        assert!(
            drive.mcap == committed.bytes,
            "{} differs from a fresh generation ({} vs {} bytes); regenerate with \
             `cargo run -p superflow-recordings` if the change is intended",
            committed.path.display(),
            drive.mcap.len(),
            committed.bytes.len()
        );
        assert!(
            drive.truth_json().unwrap() == committed.truth_json,
            "the ground truth of {} differs from a fresh generation",
            committed.path.display()
        );
        // The labels sidecar (`<drive>.labels.mcap`), where the dialect's labels go to one.
        let sidecar = committed.path.with_file_name(format!(
            "{}.labels.mcap",
            DriveOptions::default().drive_name(dialect)
        ));
        match &drive.labels_sidecar {
            Some(fresh) => {
                let bytes = std::fs::read(&sidecar).unwrap();
                assert!(
                    *fresh == bytes,
                    "{} differs from a fresh generation ({} vs {} bytes)",
                    sidecar.display(),
                    fresh.len(),
                    bytes.len()
                );
            }
            None => assert!(
                !sidecar.exists(),
                "{} is committed but not generated",
                sidecar.display()
            ),
        }
    }
}

#[test]
fn generator_reproduces_the_committed_damaged_recordings_byte_for_byte() {
    let dir = workspace_root().join("recordings/damaged");
    let fresh = damaged::damaged_recordings().unwrap();
    let mut committed: Vec<String> = std::fs::read_dir(&dir)
        .unwrap()
        .map(|e| e.unwrap().file_name().to_string_lossy().into_owned())
        .filter(|n| n.ends_with(".mcap"))
        .collect();
    committed.sort();
    let names: Vec<String> = fresh.iter().map(|f| f.name.clone()).collect();
    assert_eq!(
        names, committed,
        "recordings/damaged differs from a fresh generation; regenerate with \
         `cargo run -p superflow-recordings -- --damaged recordings/damaged`"
    );
    for file in fresh {
        let bytes = std::fs::read(dir.join(&file.name)).unwrap();
        assert!(
            bytes == file.bytes,
            "recordings/damaged/{} differs from a fresh generation ({} vs {} bytes); \
             regenerate with `cargo run -p superflow-recordings -- --damaged recordings/damaged`",
            file.name,
            file.bytes.len(),
            bytes.len()
        );
    }
}
