//! The plan against what it was before drives were planned in parallel and their scans
//! cached, cold and warm, and the camera scans the index cache keeps.

use super::*;
use crate::drive::index_cache::EntryKind;
use crate::drive::{IndexCache, IngestConfig};
use crate::sample::recipe::{CameraSync, EdgePolicy, KeyframeChoice};
use crate::sample::timing::{SCAN_ENTRY, ScanTiming, scan_key, scan_offsets};
use std::path::{Path, PathBuf};

/// The sample drives (the ROS 2 one with its labels sidecar, found next to it).
fn drives() -> Vec<PathBuf> {
    ["street_ros2", "street_foxglove"]
        .iter()
        .map(|name| superflow_recordings::sample_drive_path(name))
        .collect()
}

fn scratch(tag: &str) -> PathBuf {
    let dir = std::env::temp_dir().join(format!("superflow-plan-{tag}-{}", std::process::id()));
    let _ = std::fs::remove_dir_all(&dir);
    dir
}

fn open(cache: Option<&Path>) -> Dataset {
    let config = IngestConfig {
        index_cache: Some(cache.map_or_else(|| PathBuf::from("off"), Path::to_path_buf)),
        ..IngestConfig::default()
    };
    Dataset::open(&drives(), &config).unwrap_or_else(|e| panic!("{e}"))
}

fn on_threads<T: Send>(threads: usize, f: impl FnOnce() -> T + Send) -> T {
    rayon::ThreadPoolBuilder::new()
        .num_threads(threads)
        .build()
        .unwrap_or_else(|e| panic!("{e}"))
        .install(f)
}

fn assert_same_plan(a: &Plan, b: &Plan, what: &str) {
    assert_eq!(a.keyframes, b.keyframes, "{what}: keyframes");
    assert_eq!(a.skipped_at_edges, b.skipped_at_edges, "{what}: skipped");
    assert_eq!(a.scans, b.scans, "{what}: scans");
}

/// The plan of `dataset` one drive after the other, each camera scan measured.
fn sequential_from_scratch(dataset: &Dataset, config: &SampleConfig) -> Plan {
    let (plan, counts) = on_threads(1, || Plan::with_counts(dataset, config));
    assert_eq!(counts.from_cache, 0);
    for (drive, scan) in dataset.drives.iter().zip(&plan.scans) {
        assert_eq!(*scan, scan_offsets(drive, config));
    }
    plan
}

#[test]
fn a_plan_from_cached_scans_is_the_plan_measured_from_scratch() {
    let dir = scratch("warm");
    let cache = dir.join("cache");
    let config = SampleConfig::default();
    let off = open(None);
    assert!(off.drives.iter().all(|d| d.fingerprint.is_none()));
    let scratch = sequential_from_scratch(&off, &config);
    assert!(scratch.keyframes.len() >= 10);
    assert!(
        scratch.scans.iter().all(|s| s.timing != ScanTiming::Stamp),
        "{:?}",
        scratch.scans
    );

    let cold = open(Some(&cache));
    assert!(cold.drives.iter().all(|d| d.fingerprint.is_some()));
    let (filled, counts) = on_threads(4, || Plan::with_counts(&cold, &config));
    assert_eq!((counts.from_cache, counts.measured), (0, 2), "{counts:?}");
    assert_same_plan(&scratch, &filled, "measured into the cache");
    let entries = |ext: &str| {
        std::fs::read_dir(&cache)
            .unwrap()
            .filter(|e| {
                e.as_ref()
                    .is_ok_and(|e| e.path().extension().is_some_and(|x| x == ext))
            })
            .count()
    };
    assert_eq!(entries("sfscan"), 2);

    let warm = open(Some(&cache));
    assert_eq!(warm.indexed.from_cache, 3);
    for threads in [1, 4] {
        let (hit, counts) = on_threads(threads, || Plan::with_counts(&warm, &config));
        assert_eq!((counts.from_cache, counts.measured), (2, 0), "{counts:?}");
        assert_same_plan(
            &scratch,
            &hit,
            &format!("from the cache on {threads} threads"),
        );
    }
    // `drive_keyframes` (the inspect report) reads the same entries.
    for (d, drive) in warm.drives.iter().enumerate() {
        let (scan, keys) = drive_keyframes(drive, &config);
        assert_eq!(scan, scratch.scans[d]);
        assert!(
            keys.len()
                >= scratch
                    .keyframes
                    .iter()
                    .filter(|k| k.drive as usize == d)
                    .count()
        );
    }

    // Matching images at the sweep stamp measures nothing and stores nothing.
    let stamp = SampleConfig {
        camera_sync: CameraSync::Stamp,
        ..SampleConfig::default()
    };
    let at_stamp = sequential_from_scratch(&off, &stamp);
    let (hit, counts) = Plan::with_counts(&warm, &stamp);
    assert_eq!(counts.at_stamp, 2, "{counts:?}");
    assert_same_plan(&at_stamp, &hit, "camera_sync = stamp");
    assert_eq!(entries("sfscan"), 2);
    std::fs::remove_dir_all(dir).unwrap();
}

/// A digest of every keyframe of `plan` (drive, sweep, frame sweeps, reused frames, worst
/// camera offset).
fn keyframes_digest(plan: &Plan) -> u64 {
    let json = serde_json::to_vec(&plan.keyframes).unwrap_or_else(|e| panic!("{e}"));
    xxhash_rust::xxh3::xxh3_64(&json)
}

/// The recipes [`RECORDED`] was taken under: each keyframe choice, edge policy and camera
/// sync, with three temporal windows.
fn recipes() -> Vec<SampleConfig> {
    let mut recipes = Vec::new();
    for choice in [KeyframeChoice::LeastCameraOffset, KeyframeChoice::First] {
        for edge in [EdgePolicy::Reuse, EdgePolicy::Skip] {
            for sync in [CameraSync::Scan, CameraSync::Stamp] {
                for (temporal_frames, delta_t_secs, interval) in
                    [(3, 0.5, 0.5), (2, 0.1, 0.2), (3, 3.0, 1.0)]
                {
                    recipes.push(SampleConfig {
                        keyframe_choice: choice,
                        edge,
                        camera_sync: sync,
                        temporal_frames,
                        delta_t_secs,
                        keyframe_interval_secs: interval,
                        ..SampleConfig::default()
                    });
                }
            }
        }
    }
    recipes
}

/// The sample drives' plan under each of [`recipes`]: keyframes, keyframes skipped at the
/// edges, [`keyframes_digest`]. Recorded from the planner as it was before drives were
/// planned in parallel and their camera scans kept in the index cache (one drive after
/// the other, every scan measured, every sweep's usability worked out wherever it was
/// asked for), which this test compared against until it was retired.
const RECORDED: [(usize, u64, u64); 24] = [
    (12, 0, 0xdb780b190c792c87),
    (30, 0, 0xad253fce302a42d3),
    (6, 0, 0xb0c6a43e5e531189),
    (12, 0, 0x07cbf8b5b2dc10c7),
    (30, 0, 0xf4c4c44f5bb89010),
    (6, 0, 0xc1448269167423e0),
    (8, 4, 0x2998fbb8eec4d0fd),
    (28, 2, 0x888fd7d145dc33b7),
    (0, 6, 0x831154110e30ac6a),
    (8, 4, 0xcf1ecf228d63acc8),
    (28, 2, 0xd8ee97816fa1c3fa),
    (0, 6, 0x831154110e30ac6a),
    (12, 0, 0x4bd757a6d86d0d67),
    (30, 0, 0x3b94eb15b588a829),
    (6, 0, 0x16621dd7039fdb2f),
    (12, 0, 0xc8654cecf9c713b7),
    (30, 0, 0xf4115504fc4a53a4),
    (6, 0, 0x53bfa514481fe670),
    (8, 4, 0xe14d40a66eace7bc),
    (28, 2, 0x7726f8051eb7514d),
    (0, 6, 0x831154110e30ac6a),
    (8, 4, 0xbb4b6cab1927b978),
    (28, 2, 0xbd46b81b53e41c52),
    (0, 6, 0x831154110e30ac6a),
];

#[test]
fn the_plan_is_the_plan_of_before_under_every_recipe_cold_and_warm() {
    let dir = scratch("before");
    let cache = dir.join("cache");
    let off = open(None);
    let _filled = Plan::new(&open(Some(&cache)), &SampleConfig::default());
    let warm = open(Some(&cache));
    let recipes = recipes();
    assert_eq!(recipes.len(), RECORDED.len());
    for (recipe, recorded) in recipes.iter().zip(RECORDED) {
        for (what, dataset) in [("cold", &off), ("warm", &warm)] {
            let plan = Plan::new(dataset, recipe);
            let got = (
                plan.keyframes.len(),
                plan.skipped_at_edges,
                keyframes_digest(&plan),
            );
            assert_eq!(got, recorded, "{what} {recipe:?}");
            // The scans are what a measurement from scratch gives.
            for (drive, scan) in dataset.drives.iter().zip(&plan.scans) {
                assert_eq!(*scan, scan_offsets(drive, recipe), "{what} {recipe:?}");
            }
        }
    }
    assert!(RECORDED.iter().any(|&(_, skipped, _)| skipped > 0));
    assert!(
        RECORDED
            .iter()
            .all(|&(kept, skipped, _)| kept as u64 + skipped > 0)
    );
    std::fs::remove_dir_all(dir).unwrap();
}

#[test]
fn a_damaged_or_foreign_scan_entry_is_measured_again_not_trusted() {
    let dir = scratch("damaged");
    let cache_dir = dir.join("cache");
    let cache = IndexCache::new(&cache_dir);
    let config = SampleConfig::default();
    let scratch = sequential_from_scratch(&open(None), &config);
    let dataset = open(Some(&cache_dir));
    let (_, counts) = Plan::with_counts(&dataset, &config);
    assert_eq!(counts.measured, 2);
    let keys: Vec<u128> = dataset
        .drives
        .iter()
        .map(|d| scan_key(d).unwrap())
        .collect();
    assert_ne!(keys[0], keys[1]);
    let paths: Vec<PathBuf> = keys
        .iter()
        .map(|k| cache.path_of(&SCAN_ENTRY, *k))
        .collect();
    let whole: Vec<Vec<u8>> = paths.iter().map(|p| std::fs::read(p).unwrap()).collect();
    // A measurement no drive has: trusted, it would change the plan.
    let bogus = |cameras: usize| CameraScan {
        offsets_nanos: vec![vec![-123_456_789]; cameras],
        timing: ScanTiming::PointTime,
        lidar: None,
    };
    #[derive(Serialize)]
    struct Entry {
        key: u128,
        scan: CameraScan,
    }
    let cameras = dataset.drives[0].cameras.len();
    type Damage<'a> = (&'a str, Box<dyn Fn() + 'a>);
    let damages: Vec<Damage<'_>> = vec![
        (
            "truncated",
            Box::new(|| std::fs::write(&paths[0], &whole[0][..whole[0].len() / 2]).unwrap()),
        ),
        (
            "a flipped bit",
            Box::new(|| {
                let mut flipped = whole[0].clone();
                let at = flipped.len() - 3;
                flipped[at] ^= 0x10;
                std::fs::write(&paths[0], &flipped).unwrap()
            }),
        ),
        (
            "another version",
            Box::new(|| {
                let other = EntryKind {
                    version: SCAN_ENTRY.version + 1,
                    ..SCAN_ENTRY
                };
                let entry = Entry {
                    key: keys[0],
                    scan: bogus(cameras),
                };
                cache.store_entry(&other, keys[0], &entry);
            }),
        ),
        (
            "another kind's magic",
            Box::new(|| {
                let other = EntryKind {
                    magic: *b"SFINDEX\0",
                    ..SCAN_ENTRY
                };
                let entry = Entry {
                    key: keys[0],
                    scan: bogus(cameras),
                };
                cache.store_entry(&other, keys[0], &entry);
            }),
        ),
        (
            "another drive's entry",
            Box::new(|| std::fs::write(&paths[0], &whole[1]).unwrap()),
        ),
        (
            "too few cameras",
            Box::new(|| {
                let entry = Entry {
                    key: keys[0],
                    scan: bogus(cameras - 1),
                };
                cache.store_entry(&SCAN_ENTRY, keys[0], &entry);
            }),
        ),
    ];
    for (what, damage) in &damages {
        damage();
        let (plan, counts) = Plan::with_counts(&dataset, &config);
        assert_eq!((counts.from_cache, counts.measured), (1, 1), "{what}");
        assert_same_plan(&scratch, &plan, what);
        // Measured again, the entry is whole again.
        assert_eq!(std::fs::read(&paths[0]).unwrap(), whole[0], "{what}");
        let (plan, counts) = Plan::with_counts(&dataset, &config);
        assert_eq!(counts.from_cache, 2, "{what}");
        assert_same_plan(&scratch, &plan, what);
    }
    std::fs::remove_dir_all(dir).unwrap();
}

#[test]
fn a_scan_key_changes_with_what_shapes_the_drive() {
    let dir = scratch("keys");
    let cache = dir.join("cache");
    let reopen =
        |config: IngestConfig| Dataset::open(&drives(), &config).unwrap_or_else(|e| panic!("{e}"));
    let dataset = open(Some(&cache));
    let keys = |d: &Dataset| d.drives.iter().map(scan_key).collect::<Vec<_>>();
    let base = dataset.drives[0].config.clone();
    let tolerance = reopen(IngestConfig {
        tf_tolerance_ms: 10.0,
        ..base.clone()
    });
    for (a, b) in keys(&dataset).iter().zip(keys(&tolerance)) {
        assert!(a.is_some() && b.is_some() && *a != b);
    }
    // Where the cache is and how many files stay open change nothing.
    let moved = reopen(IngestConfig {
        index_cache: Some(dir.join("elsewhere")),
        max_open_files: Some(17),
        ..base
    });
    assert_eq!(keys(&dataset), keys(&moved));
    std::fs::remove_dir_all(dir).unwrap();
}
