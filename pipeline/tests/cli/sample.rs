//! `superflow-pipeline sample` on the sample drives: the files a user looks at, and
//! clear errors for bad requests.

use serde_json::Value;

/// `superflow-pipeline sample <args>`: whether it succeeded, stdout then stderr.
fn sample(args: &[&str]) -> (bool, String) {
    let (ok, stdout, stderr) = super::pipeline("sample", args);
    (ok, format!("{stdout}{stderr}"))
}

#[test]
fn writes_arrays_json_and_overlays() {
    let dir = std::env::temp_dir().join(format!("superflow-sample-cli-{}", std::process::id()));
    let _ = std::fs::remove_dir_all(&dir);
    let (ok, text) = sample(&[
        "--mcap",
        "recordings/drives/street_ros2.mcap",
        "--index",
        "2",
        "--no-augment",
        "--out",
        dir.to_str().unwrap(),
    ]);
    assert!(ok, "{text}");
    let json: Value =
        serde_json::from_slice(&std::fs::read(dir.join("sample.json")).unwrap()).unwrap();
    assert_eq!(json["format"], "superflow.sample/1");
    assert_eq!(json["id"]["keyframe"], 2);
    assert_eq!(json["cameras"].as_array().unwrap().len(), 3);
    assert_eq!(json["frames"].as_array().unwrap().len(), 3);
    assert_eq!(json["superpixels"], "class_map");
    assert_eq!(json["config"]["augment"]["enabled"], false);
    assert_eq!(
        json["dense"]["points_per_sweep"].as_array().unwrap().len(),
        3
    );
    let pngs = json["png"].as_array().unwrap();
    assert_eq!(pngs.len(), 3 * 3 * 2);
    for png in pngs {
        let bytes = std::fs::read(dir.join(png.as_str().unwrap())).unwrap();
        assert_eq!(&bytes[1..4], b"PNG");
    }
    for f in 0..3 {
        for name in [
            "points",
            "pairing_uv",
            "pairing_rowcol",
            "voxel_coords",
            "point_to_voxel",
            "images",
            "superpixels",
        ] {
            let bytes = std::fs::read(dir.join(format!("frame{f}_{name}.npy"))).unwrap();
            assert_eq!(&bytes[..6], b"\x93NUMPY", "frame{f}_{name}");
        }
    }
    assert!(dir.join("dense_source_sweep.npy").exists());
    std::fs::remove_dir_all(&dir).unwrap();
}

#[test]
fn bad_requests_are_clear_errors() {
    let (ok, text) = sample(&[
        "--mcap",
        "recordings/drives/street_ros2.mcap",
        "--index",
        "99",
        "--out",
        "/tmp/never-written",
    ]);
    assert!(!ok);
    assert!(
        text.contains("keyframe 99 requested; the drives have"),
        "{text}"
    );
    let (ok, text) = sample(&[
        "--mcap",
        "recordings/drives/nope.mcap",
        "--out",
        "/tmp/never-written",
    ]);
    assert!(!ok);
    assert!(text.contains("nope.mcap"), "{text}");
}
