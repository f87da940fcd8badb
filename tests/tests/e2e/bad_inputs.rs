//! Every recording of `recordings/damaged/` against its `<name>.expected.json`: the real
//! `superflow-pipeline inspect --json` (and the text form) reports exactly the expected
//! skips, counts and problems with the required words; `superflow-pipeline sample`
//! builds keyframe 0 of a usable file or refuses an unusable one with the required
//! words; the library builds every keyframe of a usable file with the expected counts
//! of dropped points (or the expected error). No command may panic. A recording without
//! an expected report, or a report without its recording, fails the test.

#![allow(clippy::unwrap_used, clippy::expect_used)] // tests fail loudly on purpose

use crate::SUBSCRIBER;
use serde::Deserialize;
use std::collections::BTreeMap;
use std::path::{Path, PathBuf};
use std::time::{Duration, Instant};
use superflow_pipeline::drive::{Dataset, IngestConfig};
use superflow_pipeline::inspect::{INSPECT_FORMAT, InspectReport};
use superflow_pipeline::sample::recipe::{CameraSync, KeyframeChoice};
use superflow_pipeline::sample::{SampleBuilder, SampleConfig};
use superflow_tests::process::run_pipeline;
use superflow_tests::{scratch, workspace_root};

/// The directory, relative to the workspace root (commands run there, so the reports
/// name files as `recordings/damaged/<name>.mcap`).
const DIR: &str = "recordings/damaged";
/// The watchdog of each `superflow-pipeline` command: a hang fails the test.
const LIMIT: Duration = Duration::from_secs(120);

/// `<name>.expected.json`.
#[derive(Debug, Deserialize)]
#[serde(deny_unknown_fields)]
struct Expected {
    /// The recording's file name.
    file: String,
    /// The damage, in words (for people; the README table repeats it).
    #[allow(dead_code)]
    damage: String,
    inspect: ExpectedInspect,
    samples: ExpectedSamples,
}

#[derive(Debug, Deserialize)]
#[serde(deny_unknown_fields)]
struct ExpectedInspect {
    dialect: String,
    lidar_sweeps: usize,
    /// Images per camera name.
    images: BTreeMap<String, usize>,
    /// Calibrated cameras (a calibration was found).
    calibrated_cameras: Vec<String>,
    usable_keyframes: usize,
    /// First to last LiDAR stamp (±1 µs), absent when there is no sweep.
    duration_secs: Option<f64>,
    /// Every skip kind with its exact count and words its first occurrence must contain.
    skipped: BTreeMap<String, ExpectedSkip>,
    /// Words each of the file's damage lines must contain, in order (empty: healthy).
    damage: Vec<Vec<String>>,
    /// `null` when the drive is trainable, else words the problem must contain.
    problems: Option<Vec<String>>,
}

#[derive(Debug, Deserialize)]
#[serde(deny_unknown_fields)]
struct ExpectedSkip {
    count: u64,
    first_contains: Vec<String>,
}

#[derive(Debug, Deserialize)]
#[serde(deny_unknown_fields)]
struct ExpectedSamples {
    /// Words the refusal must contain when no sample can be built (the file is then not
    /// trainable); `null` otherwise.
    error_contains: Option<Vec<String>>,
    /// Per keyframe of the plan: `{"ok": {...}}` with what the sample holds, or
    /// `{"error_contains": [...]}`.
    #[serde(default)]
    keyframes: Vec<ExpectedKeyframe>,
}

#[derive(Debug, Deserialize)]
#[serde(deny_unknown_fields, rename_all = "snake_case")]
enum ExpectedKeyframe {
    Ok {
        /// Sweep index of each temporal frame.
        sweeps: Vec<u32>,
        dropped_non_finite: Vec<u64>,
        dense_dropped_non_finite: u64,
        /// Points of each temporal frame.
        points: Vec<usize>,
        /// Earlier sweeps the dense cloud lacks (drive start, unreadable or empty sweep).
        dense_missing: u32,
    },
    ErrorContains(Vec<String>),
}

/// Every `.mcap` and `.expected.json` of the directory, by stem.
fn listing() -> (Vec<String>, Vec<String>) {
    let mut mcaps = Vec::new();
    let mut expected = Vec::new();
    for entry in std::fs::read_dir(workspace_root().join(DIR)).unwrap() {
        let name = entry.unwrap().file_name().to_string_lossy().into_owned();
        if let Some(stem) = name.strip_suffix(".expected.json") {
            expected.push(stem.to_string());
        } else if let Some(stem) = name.strip_suffix(".mcap") {
            mcaps.push(stem.to_string());
        }
    }
    mcaps.sort();
    expected.sort();
    (mcaps, expected)
}

fn contains_all(text: &str, words: &[String], what: &str, errors: &mut Vec<String>) {
    for w in words {
        if !text.contains(w.as_str()) {
            errors.push(format!("{what}: `{w}` not in {text:?}"));
        }
    }
}

/// Checks one recording; returns what differs from its expected report.
fn check(stem: &str) -> Vec<String> {
    let mut errors = Vec::new();
    let root = workspace_root();
    let expected_path = root.join(DIR).join(format!("{stem}.expected.json"));
    let expected: Expected = serde_json::from_slice(&std::fs::read(&expected_path).unwrap())
        .unwrap_or_else(|e| panic!("{}: {e}", expected_path.display()));
    let relative = format!("{DIR}/{stem}.mcap");
    if expected.file != format!("{stem}.mcap") {
        errors.push(format!("{stem}: expected report names {}", expected.file));
    }

    // What a user sees: inspect, JSON and text.
    let (ok, stdout, stderr) = run_pipeline(
        SUBSCRIBER,
        &["inspect", "--json", "--mcap", &relative],
        &[],
        LIMIT,
    );
    if !ok {
        errors.push(format!("{stem}: inspect --json failed:\n{stderr}"));
        return errors;
    }
    let report: InspectReport = serde_json::from_str(&stdout).unwrap();
    assert_eq!(report.format, INSPECT_FORMAT);
    assert_eq!(report.drives.len(), 1, "{stem}: one drive");
    let drive = &report.drives[0];
    let e = &expected.inspect;
    let mut eq = |what: &str, got: String, want: String| {
        if got != want {
            errors.push(format!("{stem}: {what}: got {got}, expected {want}"));
        }
    };
    eq("dialect", drive.dialect.clone(), e.dialect.clone());
    eq(
        "lidar_sweeps",
        drive.lidar_sweeps.to_string(),
        e.lidar_sweeps.to_string(),
    );
    let images: BTreeMap<String, usize> = drive
        .cameras
        .iter()
        .map(|c| (c.name.clone(), c.images))
        .collect();
    eq("images", format!("{images:?}"), format!("{:?}", e.images));
    let calibrated: Vec<String> = drive
        .cameras
        .iter()
        .filter(|c| c.calibrations > 0)
        .map(|c| c.name.clone())
        .collect();
    eq(
        "calibrated cameras",
        format!("{calibrated:?}"),
        format!("{:?}", e.calibrated_cameras),
    );
    eq(
        "usable_keyframes",
        drive.usable_keyframes.to_string(),
        e.usable_keyframes.to_string(),
    );
    match (drive.duration_secs, e.duration_secs) {
        (Some(got), Some(want)) if (got - want).abs() <= 1e-6 => {}
        (None, None) => {}
        (got, want) => eq("duration_secs", format!("{got:?}"), format!("{want:?}")),
    }
    let got_skips: BTreeMap<&str, u64> = drive
        .skipped
        .entries
        .iter()
        .map(|(k, v)| (k.as_str(), v.count))
        .collect();
    let want_skips: BTreeMap<&str, u64> = e
        .skipped
        .iter()
        .map(|(k, v)| (k.as_str(), v.count))
        .collect();
    eq(
        "skipped",
        format!("{got_skips:?}"),
        format!("{want_skips:?}"),
    );
    for (kind, want) in &e.skipped {
        if let Some(got) = drive.skipped.entries.get(kind) {
            contains_all(
                &got.first,
                &want.first_contains,
                &format!("{stem}: skip `{kind}`"),
                &mut errors,
            );
        }
    }
    let damage = &drive.files[0].damage;
    if damage.len() != e.damage.len() {
        errors.push(format!(
            "{stem}: damage {damage:?}, expected {} lines",
            e.damage.len()
        ));
    }
    for (got, words) in damage.iter().zip(&e.damage) {
        contains_all(got, words, &format!("{stem}: damage"), &mut errors);
    }
    match (&drive.problems, &e.problems) {
        (None, None) => {}
        (Some(got), Some(words)) => {
            contains_all(got, words, &format!("{stem}: problems"), &mut errors)
        }
        (got, want) => errors.push(format!(
            "{stem}: problems {got:?}, expected {}",
            if want.is_some() { "some" } else { "none" }
        )),
    }
    // The text form shows the same words.
    let (ok, text, stderr) =
        run_pipeline(SUBSCRIBER, &["inspect", "--mcap", &relative], &[], LIMIT);
    if !ok {
        errors.push(format!("{stem}: inspect failed:\n{stderr}"));
    }
    for (kind, want) in &e.skipped {
        contains_all(
            &text,
            &[format!("{kind}: {}", want.count)],
            &format!("{stem}: inspect text"),
            &mut errors,
        );
        contains_all(
            &text,
            &want.first_contains,
            &format!("{stem}: inspect text"),
            &mut errors,
        );
    }
    if let Some(words) = &e.problems {
        contains_all(
            &text,
            &["not trainable".to_string()],
            &format!("{stem}: inspect text"),
            &mut errors,
        );
        contains_all(&text, words, &format!("{stem}: inspect text"), &mut errors);
    }

    // Samples: the binary for keyframe 0, the library for every keyframe.
    let out = scratch::path("bad-inputs", stem);
    let out_text = out.display().to_string();
    let (ok, _, stderr) = run_pipeline(
        SUBSCRIBER,
        &[
            "sample",
            "--mcap",
            &relative,
            "--index",
            "0",
            "--no-augment",
            "--out",
            &out_text,
        ],
        &[],
        LIMIT,
    );
    let _ = std::fs::remove_dir_all(&out);
    match &expected.samples.error_contains {
        Some(words) => {
            if ok {
                errors.push(format!("{stem}: sample succeeded, expected a refusal"));
            }
            contains_all(
                &stderr,
                words,
                &format!("{stem}: sample refusal"),
                &mut errors,
            );
        }
        None if !ok => errors.push(format!("{stem}: sample --index 0 failed:\n{stderr}")),
        None => {}
    }
    errors.extend(check_library(
        stem,
        &root.join(&relative),
        &expected.samples,
    ));
    errors
}

/// Builds every keyframe through the library with the default recipe, no augmentation,
/// keyframes chosen as the first sweep of each interval with images at the sweep stamp:
/// the damage of these files was placed in the sweeps (0, 10, 20) and images that rule
/// picks, so that it lands in the samples.
fn check_library(stem: &str, path: &Path, expected: &ExpectedSamples) -> Vec<String> {
    let mut errors = Vec::new();
    let dataset = Dataset::open(&[path.to_path_buf()], &IngestConfig::default()).unwrap();
    let mut config = SampleConfig {
        keyframe_choice: KeyframeChoice::First,
        camera_sync: CameraSync::Stamp,
        ..SampleConfig::default()
    };
    config.augment.enabled = false;
    let builder = match SampleBuilder::new(&dataset, config) {
        Ok(b) => b,
        Err(e) => {
            match &expected.error_contains {
                Some(words) => contains_all(
                    &e.to_string(),
                    words,
                    &format!("{stem}: SampleBuilder::new"),
                    &mut errors,
                ),
                None => errors.push(format!("{stem}: SampleBuilder::new failed: {e}")),
            }
            return errors;
        }
    };
    if expected.error_contains.is_some() {
        errors.push(format!(
            "{stem}: SampleBuilder::new succeeded, expected a refusal"
        ));
        return errors;
    }
    let keyframes = builder.plan().keyframes.len();
    if keyframes != expected.keyframes.len() {
        errors.push(format!(
            "{stem}: the plan has {keyframes} keyframes, expected {}",
            expected.keyframes.len()
        ));
    }
    for (k, want) in expected.keyframes.iter().enumerate().take(keyframes) {
        let built = builder.build_keyframe(k, 0, k as u64);
        match (built, want) {
            (
                Ok(sample),
                ExpectedKeyframe::Ok {
                    sweeps,
                    dropped_non_finite,
                    dense_dropped_non_finite,
                    points,
                    dense_missing,
                },
            ) => {
                let got_sweeps: Vec<u32> = sample.frames.iter().map(|f| f.sweep).collect();
                let got_dropped: Vec<u64> =
                    sample.frames.iter().map(|f| f.dropped_non_finite).collect();
                let got_points: Vec<usize> =
                    sample.frames.iter().map(|f| f.cloud.xyz.len()).collect();
                let got = (
                    &got_sweeps,
                    &got_dropped,
                    sample.dense_dropped_non_finite,
                    &got_points,
                    sample.dense_missing,
                );
                let want = (
                    sweeps,
                    dropped_non_finite,
                    *dense_dropped_non_finite,
                    points,
                    *dense_missing,
                );
                if got != want {
                    errors.push(format!(
                        "{stem}: keyframe {k}: (sweeps, dropped per frame, dense dropped, \
                         points per frame, dense missing) = {got:?}, expected {want:?}"
                    ));
                }
                let finite = sample
                    .frames
                    .iter()
                    .flat_map(|f| &f.cloud.xyz)
                    .chain(&sample.dense.xyz)
                    .all(|p| p.iter().all(|v| v.is_finite()));
                if !finite {
                    errors.push(format!("{stem}: keyframe {k}: a non-finite point survived"));
                }
            }
            (Err(e), ExpectedKeyframe::ErrorContains(words)) => contains_all(
                &e.to_string(),
                words,
                &format!("{stem}: keyframe {k}"),
                &mut errors,
            ),
            (Ok(_), ExpectedKeyframe::ErrorContains(_)) => {
                errors.push(format!("{stem}: keyframe {k} built, expected an error"))
            }
            (Err(e), ExpectedKeyframe::Ok { .. }) => {
                errors.push(format!("{stem}: keyframe {k} failed: {e}"))
            }
        }
    }
    errors
}

#[test]
fn every_damaged_recording_has_an_expected_report_and_matches_it() {
    let started = Instant::now();
    let (mcaps, expected) = listing();
    assert!(!mcaps.is_empty(), "no recordings in {DIR}");
    assert_eq!(
        mcaps, expected,
        "every recording in {DIR} needs <name>.expected.json and every expected report its \
         <name>.mcap"
    );
    // Two at a time: each check runs the binary a few times.
    let stems: Vec<PathBuf> = mcaps.iter().map(PathBuf::from).collect();
    let errors: Vec<String> = std::thread::scope(|scope| {
        let halves: Vec<_> = stems
            .chunks(stems.len().div_ceil(2))
            .map(|part| {
                scope.spawn(move || {
                    part.iter()
                        .flat_map(|s| check(&s.display().to_string()))
                        .collect::<Vec<_>>()
                })
            })
            .collect();
        halves
            .into_iter()
            .flat_map(|h| h.join().expect("a check panicked"))
            .collect()
    });
    assert!(
        errors.is_empty(),
        "{} mismatches:\n{}",
        errors.len(),
        errors.join("\n")
    );
    eprintln!(
        "{} damaged recordings checked in {:.1} s",
        mcaps.len(),
        started.elapsed().as_secs_f64()
    );
}

#[test]
fn the_readme_lists_every_damaged_recording() {
    let readme = std::fs::read_to_string(workspace_root().join(DIR).join("README.md")).unwrap();
    for stem in listing().0 {
        assert!(
            readme.contains(&format!("`{stem}.mcap`")),
            "{DIR}/README.md does not list {stem}.mcap"
        );
    }
}
