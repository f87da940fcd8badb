//! Arbitrary bytes as an MCAP drive file, through the real ingest path.
//!
//! Ingest reads files by path (positioned reads, bounded memory), so each input is
//! written to a per-process file under `$SUPERFLOW_FUZZ_SCRATCH`, else /dev/shm (else
//! the temp dir), and opened as `superflow-pipeline inspect` and sample building do:
//! `Dataset::open` (scan, channel discovery, index, transforms, calibrations), the
//! inspect report, the sensor check, the keyframe plan, then every sweep, image and
//! class map the index lists is read and decoded, and the poses of every sweep looked up.
#![no_main]

#[path = "common.rs"]
mod common;

use libfuzzer_sys::fuzz_target;
use std::path::PathBuf;
use std::sync::OnceLock;
use superflow_pipeline::decode::image::Target;
use superflow_pipeline::drive::{Dataset, IngestConfig};
use superflow_pipeline::inspect::InspectReport;
use superflow_pipeline::sample::{SampleBuilder, SampleConfig};
use superflow_pipeline::source::ChunkCache;

/// Frames of each stream decoded per input (the sample drives hold a few dozen).
const MAX_FRAMES: usize = 64;

fn input_path() -> &'static PathBuf {
    static PATH: OnceLock<PathBuf> = OnceLock::new();
    PATH.get_or_init(|| {
        // run.sh points SUPERFLOW_FUZZ_SCRATCH at a directory it removes afterwards.
        let shm = PathBuf::from("/dev/shm");
        let base = match std::env::var_os("SUPERFLOW_FUZZ_SCRATCH") {
            Some(dir) => PathBuf::from(dir),
            None if shm.is_dir() => shm,
            None => std::env::temp_dir(),
        };
        let dir = base.join(format!("superflow-fuzz-{}", std::process::id()));
        std::fs::create_dir_all(&dir).expect("creating the scratch directory");
        dir.join("drive.mcap")
    })
}

fuzz_target!(|data: &[u8]| {
    common::let_guarded_decoder_panics_unwind();
    let path = input_path();
    std::fs::write(path, data).expect("writing the input file");
    let config = IngestConfig::default();
    let Ok(dataset) = Dataset::open(std::slice::from_ref(path), &config) else {
        return;
    };
    let report = InspectReport::new(&dataset);
    let _ = report.to_text();
    let _ = dataset.check_sensors();
    let _ = SampleBuilder::new(&dataset, SampleConfig::default());

    let mut cache = ChunkCache::new(2);
    for drive in &dataset.drives {
        let _ = drive.time_span();
        let _ = drive.keyframes(500_000_000);
        if let Some(lidar) = &drive.lidar {
            for sweep in lidar.sweeps.iter().take(MAX_FRAMES) {
                let _ = drive.read_sweep(sweep, &mut cache);
                if let (Some(map), Some(ego)) = (&drive.map_frame, &drive.ego_frame) {
                    let _ = drive.tf.lookup(map, ego, sweep.stamp);
                    let _ = drive.tf.lookup(ego, &lidar.frame_id, sweep.stamp);
                }
            }
        }
        for camera in &drive.cameras {
            let _ = camera.period_nanos();
            for calibration in &camera.calibrations {
                common::exercise_calibration(calibration);
            }
            for frame in camera.frames.iter().take(MAX_FRAMES) {
                let _ = camera.calibration_at(frame.stamp);
                let _ = drive.read_image(camera, frame, Target::Rgb, &mut cache);
            }
            for frame in camera.superpixels.iter().take(MAX_FRAMES) {
                let _ = drive.read_image(camera, frame, Target::Mono, &mut cache);
            }
        }
    }
});
