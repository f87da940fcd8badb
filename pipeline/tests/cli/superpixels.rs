//! `superflow-pipeline superpixels`: writes `<drive>.slic.mcap`, leaves a current one
//! alone, refuses to overwrite one written with other settings unless `--force`.

use std::path::Path;

fn superpixels(args: &[&str]) -> (bool, String, String) {
    super::pipeline("superpixels", args)
}

#[test]
fn writes_keeps_and_rewrites_the_sidecar() {
    let root = super::root();
    let dir = std::env::temp_dir().join(format!("superflow-sp-cli-{}", std::process::id()));
    std::fs::create_dir_all(&dir).unwrap();
    let drive = dir.join("street_ros2.mcap");
    std::fs::copy(root.join("recordings/drives/street_ros2.mcap"), &drive).unwrap();
    let sidecar = dir.join("street_ros2.slic.mcap");
    let mcap = drive.to_str().unwrap();

    let (ok, stdout, stderr) = superpixels(&["--mcap", mcap]);
    assert!(ok, "{stderr}");
    // The drive has class maps: the command says which superpixels samples will use.
    assert!(
        stdout.contains("note: every camera has class maps"),
        "{stdout}"
    );
    assert!(stdout.contains("216 label maps"), "{stdout}");
    let written = std::fs::metadata(&sidecar).unwrap().modified().unwrap();

    let (ok, stdout, stderr) = superpixels(&["--mcap", mcap]);
    assert!(ok, "{stderr}");
    assert!(stdout.contains("up to date"), "{stdout}");
    assert_eq!(
        std::fs::metadata(&sidecar).unwrap().modified().unwrap(),
        written
    );

    // Other SLIC settings: an error naming the file, then --force rewrites it.
    let config = dir.join("other.toml");
    std::fs::write(&config, "[sample.slic]\nn_segments = 60\n").unwrap();
    let other = ["--mcap", mcap, "--config", config.to_str().unwrap()];
    let (ok, _, stderr) = superpixels(&other);
    assert!(!ok);
    assert!(
        stderr.contains("street_ros2.slic.mcap") && stderr.contains("--force"),
        "{stderr}"
    );
    let (ok, stdout, stderr) = superpixels(&[&other[..], &["--force"]].concat());
    assert!(ok, "{stderr}");
    assert!(stdout.contains("216 label maps"), "{stdout}");
    assert!(!Path::new(&format!("{}.partial", sidecar.display())).exists());
    std::fs::remove_dir_all(&dir).unwrap();
}
