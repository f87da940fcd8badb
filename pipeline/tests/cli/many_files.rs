//! Many input files under a low descriptor limit: 300 drives with two sidecars each (900
//! files) open and build samples under `ulimit -n 64`, because inputs are read through a
//! bounded pool of open files; asking the pool for more than the process may open is an
//! error that names the file and the setting.

use std::path::{Path, PathBuf};
use std::process::Command;
use superflow_pipeline::inspect::InspectReport;
use superflow_recordings::{ClassMapStorage, Dialect, DriveOptions, LidarLabels};

const DRIVES: usize = 300;

/// A directory of `DRIVES` hard links of one short ROS 2 drive, each with its labels
/// and class-map sidecars: distinct paths, so each is a drive and a file of its own.
fn linked_drives() -> PathBuf {
    let dir = std::env::temp_dir().join(format!("superflow-many-files-{}", std::process::id()));
    let _ = std::fs::remove_dir_all(&dir);
    let source = dir.join("source");
    let drives = dir.join("drives");
    std::fs::create_dir_all(&source).unwrap();
    std::fs::create_dir_all(&drives).unwrap();
    let options = DriveOptions {
        labels: LidarLabels::Sidecar,
        class_maps: ClassMapStorage::PngSidecar,
        ..DriveOptions::short()
    };
    let drive = superflow_recordings::generate_with(Dialect::Ros2, &options).unwrap();
    let files = [
        ("mcap", drive.mcap),
        ("labels.mcap", drive.labels_sidecar.unwrap()),
        ("superpixels.mcap", drive.sidecar.unwrap()),
    ];
    for (ext, bytes) in &files {
        std::fs::write(source.join(format!("drive.{ext}")), bytes).unwrap();
    }
    for i in 0..DRIVES {
        for (ext, _) in &files {
            std::fs::hard_link(
                source.join(format!("drive.{ext}")),
                drives.join(format!("d{i:03}.{ext}")),
            )
            .unwrap();
        }
    }
    drives
}

/// `superflow-pipeline <args>` under `ulimit -n 64`: whether it succeeded, stdout, stderr.
fn run_limited(args: &[&str]) -> (bool, String, String) {
    let out = Command::new("sh")
        .arg("-c")
        .arg("ulimit -n 64 && exec \"$@\"")
        .arg("sh")
        .arg(env!("CARGO_BIN_EXE_superflow-pipeline"))
        .args(args)
        .output()
        .expect("sh runs");
    (
        out.status.success(),
        String::from_utf8_lossy(&out.stdout).into_owned(),
        String::from_utf8_lossy(&out.stderr).into_owned(),
    )
}

fn path_str(path: &Path) -> &str {
    path.to_str().unwrap()
}

#[test]
fn hundreds_of_drives_open_under_ulimit_64() {
    let drives = linked_drives();
    let dir = drives.parent().unwrap().to_path_buf();
    let mcap = path_str(&drives);

    let (ok, stdout, stderr) = run_limited(&["inspect", "--json", "--mcap", mcap]);
    assert!(ok, "{stderr}");
    let report: InspectReport = serde_json::from_str(&stdout).unwrap();
    assert_eq!(report.drives.len(), DRIVES);
    assert!(report.drives.iter().all(|d| d.files.len() == 3));

    // Samples of the first drive (its files long closed by the pool, so reopened and
    // checked) and of the last.
    for index in ["0", "4", &(3 * DRIVES - 1).to_string()] {
        let out = dir.join(format!("sample-{index}"));
        let (ok, _, stderr) = run_limited(&[
            "sample",
            "--mcap",
            mcap,
            "--index",
            index,
            "--out",
            path_str(&out),
        ]);
        assert!(ok, "sample {index}: {stderr}");
        assert!(out.join("sample.json").is_file(), "sample {index}");
    }

    // A pool allowed more files than the process may open fails cleanly, naming a file
    // and what to change.
    let config = dir.join("greedy.toml");
    std::fs::write(&config, "[ingest]\nmax_open_files = 100000\n").unwrap();
    let (ok, _, stderr) = run_limited(&["inspect", "--config", path_str(&config), "--mcap", mcap]);
    assert!(!ok);
    assert!(stderr.contains("max_open_files"), "{stderr}");
    assert!(stderr.contains("ulimit -n"), "{stderr}");
    assert!(stderr.contains(".mcap"), "{stderr}");
    assert!(!stderr.contains("panicked"), "{stderr}");

    std::fs::remove_dir_all(dir).unwrap();
}
