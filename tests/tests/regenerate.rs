//! The generator reproduces the committed sample drives byte for byte.

#![allow(clippy::unwrap_used, clippy::expect_used)] // tests fail loudly on purpose

use superflow_recordings::{Dialect, generate};
use superflow_tests::sample_drive;

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
    }
}
