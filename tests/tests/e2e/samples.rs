//! SuperFlow samples built from the sample drives, checked against the simulation that
//! wrote them: the plan of keyframes and temporal frames, the dense cloud's alignment,
//! projections of landmarks through the builder's transforms (and what skipping the ego
//! motion between the LiDAR and camera stamps would cost), class-map superpixels against
//! the class each LiDAR return hit, flips, augmentation, determinism.

#![allow(clippy::unwrap_used, clippy::expect_used)] // tests fail loudly on purpose

use nalgebra::Point3;
use superflow_pipeline::drive::Dataset;
use superflow_pipeline::sample::project::{CameraView, camera_from_lidar};
use superflow_pipeline::sample::recipe::{
    CameraSync, EdgePolicy, KeyframeChoice, SuperpixelSource,
};
use superflow_pipeline::sample::{Sample, SampleBuilder, SampleConfig, SampleError};
use superflow_recordings::sim::{DriveTiming, Rig, simulate_sweep};
use superflow_recordings::{Dialect, IMAGE_SIZE, SCENE_SEED, scene::Scene};
use superflow_schemas::Stamp;
use superflow_tests::{sample_dataset, sample_drive};

fn open(dialect: Dialect) -> Dataset {
    sample_dataset(&sample_drive(dialect).unwrap()).unwrap()
}

fn no_augment() -> SampleConfig {
    let mut config = SampleConfig::default();
    config.augment.enabled = false;
    config
}

/// The scene, sensor rig and timing the sample drive of `dialect` was simulated with.
fn simulation(dialect: Dialect) -> (Scene, Rig, DriveTiming) {
    (
        Scene::street(SCENE_SEED),
        Rig::new(IMAGE_SIZE.0, IMAGE_SIZE.1, dialect.distortion()),
        dialect.timing(),
    )
}

/// A sample without its timings (the only part that differs between runs).
fn content(mut s: Sample) -> Sample {
    s.times = Default::default();
    s
}

#[test]
fn plan_has_keyframes_every_half_second_with_their_context() {
    for dialect in Dialect::ALL {
        let ds = open(dialect);
        let builder = SampleBuilder::new(&ds, SampleConfig::default()).unwrap();
        let plan = builder.plan();
        let sweeps = &ds.drives[0].lidar.as_ref().unwrap().sweeps;
        // 3 s of drive at 20 Hz: keyframes 10 sweeps apart, the first where every camera
        // has fired.
        assert!(
            (5..=6).contains(&plan.keyframes.len()),
            "{dialect:?}: {:?}",
            plan.keyframes
        );
        for pair in plan.keyframes.windows(2) {
            assert_eq!(pair[1].sweep - pair[0].sweep, 10);
        }
        for key in &plan.keyframes {
            let k = key.sweep;
            assert_eq!(key.frame_sweeps[1], k);
            for (slot, offset) in [(0usize, -1i64), (2, 1)] {
                let s = key.frame_sweeps[slot];
                if s == k {
                    // Reused at a drive edge: the context frame would lie outside.
                    let target = sweeps[k as usize].stamp.add_nanos(offset * 500_000_000);
                    assert!(
                        target < sweeps[0].stamp
                            || target > sweeps.last().unwrap().stamp
                            || (offset < 0 && k < 12),
                        "{dialect:?}: keyframe {k} reused without cause"
                    );
                } else {
                    let dt = sweeps[s as usize]
                        .stamp
                        .nanos_since(sweeps[k as usize].stamp);
                    assert_eq!(dt, offset * 500_000_000, "{dialect:?}: keyframe {k}");
                }
            }
        }
        let reused: u32 = plan.keyframes.iter().map(|k| k.reused).sum();
        // Skip instead of reuse drops exactly the keyframes that reused a frame.
        let skip = SampleConfig {
            edge: EdgePolicy::Skip,
            ..SampleConfig::default()
        };
        let skipping = SampleBuilder::new(&ds, skip).unwrap();
        let with_reuse = plan.keyframes.iter().filter(|k| k.reused > 0).count();
        assert!(with_reuse > 0, "the 3 s drive has edge keyframes");
        assert_eq!(skipping.plan().skipped_at_edges as usize, with_reuse);
        assert_eq!(
            skipping.plan().keyframes.len() + with_reuse,
            plan.keyframes.len()
        );
        assert!(reused as usize >= with_reuse);
        // Two frames: (t - dt, t).
        let two = SampleConfig {
            temporal_frames: 2,
            ..SampleConfig::default()
        };
        let two = SampleBuilder::new(&ds, two).unwrap();
        let s = two.build(0, 0).unwrap();
        assert_eq!(s.frames.len(), 2);
        assert_eq!(s.key_frame, 1);
        assert_eq!(
            s.frames.iter().map(|f| f.offset).collect::<Vec<_>>(),
            [-1, 0]
        );
        // Every epoch visits every keyframe once, in its own order.
        let o0 = plan.epoch_order(0, 0);
        let o1 = plan.epoch_order(0, 1);
        let mut sorted = o0.clone();
        sorted.sort_unstable();
        assert_eq!(sorted, (0..plan.keyframes.len() as u32).collect::<Vec<_>>());
        assert_ne!(o0, o1);
    }
}

/// The dense cloud: every point of the keyframe and the 2 earlier sweeps, moved into the
/// keyframe's LiDAR frame, lies within 2 cm of where the simulation put it (its map
/// position seen from the keyframe's LiDAR pose). Without the alignment the earlier
/// sweeps would be tens of centimetres off.
#[test]
fn dense_cloud_sweeps_coincide_in_the_keyframe_frame() {
    for dialect in Dialect::ALL {
        let ds = open(dialect);
        let builder = SampleBuilder::new(&ds, no_augment()).unwrap();
        let (scene, rig, timing) = simulation(dialect);
        let map_from_lidar = |stamp: Stamp| {
            superflow_recordings::sim::map_from_ego(timing.start, stamp) * rig.ego_from_lidar
        };
        for keyframe in [1usize, 3] {
            let sample = builder
                .build_keyframe(keyframe, 0, keyframe as u64)
                .unwrap();
            let key_sweep = sample.id.sweep as usize;
            let key_stamp = sample.dense_stamps[0];
            let lidar_from_map = map_from_lidar(key_stamp).inverse();
            assert_eq!(sample.dense_stamps.len(), 3);
            assert_eq!(sample.dense_missing, 0);
            let dense = &sample.dense;
            let mut worst = [0.0f64; 3];
            let mut naive = [0.0f64; 3];
            for j in 0..3usize {
                let returns = simulate_sweep(&scene, &rig, &timing, key_sweep - j);
                let own_from_map = map_from_lidar(sample.dense_stamps[j]).inverse();
                let points: Vec<&[f32; 3]> = dense
                    .xyz
                    .iter()
                    .zip(&dense.source_sweep)
                    .filter(|(_, s)| **s as usize == j)
                    .map(|(p, _)| p)
                    .collect();
                assert_eq!(points.len(), returns.len(), "{dialect:?} sweep -{j}");
                for (p, r) in points.iter().zip(&returns) {
                    let expected = lidar_from_map * r.point_in_map;
                    let got = Point3::new(f64::from(p[0]), f64::from(p[1]), f64::from(p[2]));
                    worst[j] = worst[j].max((got - expected).norm());
                    naive[j] = naive[j].max((own_from_map * r.point_in_map - expected).norm());
                }
            }
            eprintln!(
                "{dialect:?} keyframe {keyframe}: dense sweeps within {worst:.4?} m of truth; unaligned they would be {naive:.3?} m off"
            );
            assert!(worst.iter().all(|w| *w < 0.02), "{dialect:?}: {worst:?}");
            assert!(naive[1] > 0.3 && naive[2] > 0.6, "{naive:?}");
            // The keyframe's points come first, unchanged.
            let key = &sample.frames[sample.key_frame].cloud;
            assert_eq!(&dense.xyz[..key.xyz.len()], &key.xyz[..]);
            assert!(dense.source_sweep[..key.xyz.len()].iter().all(|s| *s == 0));
            // Dense pairings are the keyframe's pairings plus those of the earlier sweeps.
            assert!(dense.pairings.len() > key.pairings.len() * 2);
        }
    }
}

/// Landmarks projected through the builder's `camera_from_lidar` of each image land on
/// the truth pixel (≤ 0.5 px, distorted cameras included). Projecting as if the camera
/// fired at the LiDAR stamp (no ego motion in between) moves them by pixels.
#[test]
fn landmarks_project_through_the_sample_transforms() {
    for dialect in Dialect::ALL {
        let drive = sample_drive(dialect).unwrap();
        let truth = &drive.truth;
        let ds = open(dialect);
        let d = &ds.drives[0];
        let lidar_frame = &d.lidar.as_ref().unwrap().frame_id;
        let (mut checked, mut worst, mut naive_worst, mut naive_sum) = (0, 0.0f64, 0.0f64, 0.0);
        // The truth observes landmarks in the images at 1 s: the images matched at the
        // sweep stamp (first-sweep keyframes) and at the LiDAR's scan both meet some.
        let recipes = [
            (KeyframeChoice::First, CameraSync::Stamp),
            (KeyframeChoice::LeastCameraOffset, CameraSync::Scan),
        ];
        for (keyframe_choice, camera_sync) in recipes {
            let mut config = no_augment();
            config.cameras = 6;
            config.keyframe_choice = keyframe_choice;
            config.camera_sync = camera_sync;
            let builder = SampleBuilder::new(&ds, config).unwrap();
            for k in 0..builder.plan().keyframes.len() {
                let sample = builder.build_keyframe(k, 0, k as u64).unwrap();
                for frame in &sample.frames {
                    let map_from_lidar =
                        d.tf.lookup("map", lidar_frame, frame.lidar_stamp).unwrap();
                    for image in &frame.images {
                        let camera = truth
                            .cameras
                            .iter()
                            .find(|c| c.image_topic == image.topic)
                            .unwrap();
                        let view = CameraView::new(&image.calibration, image.camera_from_lidar);
                        let stale = camera_from_lidar(
                            &d.tf,
                            "map",
                            lidar_frame,
                            frame.lidar_stamp,
                            &camera.frame_id,
                            frame.lidar_stamp,
                        )
                        .unwrap();
                        let stale_view = CameraView::new(&image.calibration, stale);
                        for landmark in &truth.landmarks {
                            let Some(obs) = landmark.observations.iter().find(|o| {
                                o.camera == camera.name && o.stamp_nanos == image.stamp.nanos()
                            }) else {
                                continue;
                            };
                            let [x, y, z] = landmark.point_in_map;
                            let p = map_from_lidar.inverse() * Point3::new(x, y, z);
                            let p = [p.x as f32, p.y as f32, p.z as f32];
                            let Some((pixel, _)) = view.project(p) else {
                                panic!("{dialect:?} {}: not projected", landmark.name)
                            };
                            let e = (pixel.x - obs.pixel[0]).hypot(pixel.y - obs.pixel[1]);
                            worst = worst.max(e);
                            if let Some((stale_pixel, _)) = stale_view.project(p) {
                                let n = (stale_pixel.x - obs.pixel[0])
                                    .hypot(stale_pixel.y - obs.pixel[1]);
                                naive_worst = naive_worst.max(n);
                                naive_sum += n;
                            }
                            checked += 1;
                        }
                    }
                }
            }
        }
        eprintln!(
            "{dialect:?}: {checked} landmark pixels within {worst:.3} px; ignoring ego motion between LiDAR and camera stamps: up to {naive_worst:.1} px, mean {:.2} px",
            naive_sum / f64::from(checked)
        );
        assert!(
            checked >= 20,
            "{dialect:?}: only {checked} landmark observations"
        );
        assert!(worst <= 0.5, "{dialect:?}: {worst} px");
        assert!(naive_worst > 3.0, "{dialect:?}: {naive_worst} px");
    }
}

/// Class-map superpixels: the superpixel of each pairing is the class the LiDAR return
/// hit (the class map and the LiDAR agree except at object edges); ids are
/// view-consistent (the same class is the same id in every camera); an id beyond the
/// configured class count is an error naming the channel and time.
#[test]
fn class_map_superpixels_match_the_lidar_classes() {
    for dialect in Dialect::ALL {
        let ds = open(dialect);
        let builder = SampleBuilder::new(&ds, no_augment()).unwrap();
        let (scene, rig, timing) = simulation(dialect);
        let sample = builder.build_keyframe(2, 0, 2).unwrap();
        assert!(sample.class_superpixels);
        let frame = &sample.frames[sample.key_frame];
        assert_eq!(frame.num_superpixels, 17);
        let returns = simulate_sweep(&scene, &rig, &timing, frame.sweep as usize);
        let agree = frame
            .cloud
            .pairings
            .iter()
            .filter(|p| u32::from(returns[p.point as usize].class) == p.superpixel)
            .count();
        let share = agree as f64 / frame.cloud.pairings.len() as f64;
        eprintln!(
            "{dialect:?}: {agree}/{} pairings on a pixel of the class their return hit",
            frame.cloud.pairings.len()
        );
        assert!(share > 0.95, "{dialect:?}: {share}");
        // The road (class 11) appears in every camera under the same id.
        for image in &frame.images {
            assert!(image.superpixels.contains(&11), "{}", image.camera);
            assert!(image.superpixels.iter().all(|id| *id < 17));
        }
        let mut few = no_augment();
        few.num_classes = 12;
        let err = SampleBuilder::new(&ds, few)
            .unwrap()
            .build_keyframe(2, 0, 2)
            .unwrap_err();
        let text = err.to_string();
        assert!(matches!(err, SampleError::Superpixels { .. }), "{text}");
        assert!(
            text.contains("outside the configured 12 classes") && text.contains(" at "),
            "{text}"
        );
    }
}

/// A flipped image mirrors its pixels, its superpixels and its pairings' columns.
#[test]
fn flips_mirror_images_and_pairings() {
    let ds = open(Dialect::Ros2);
    let build = |p: f64| {
        let mut config = no_augment();
        config.image_flip_probability = p;
        SampleBuilder::new(&ds, config)
            .unwrap()
            .build_keyframe(2, 0, 2)
            .unwrap()
    };
    let (plain, flipped) = (build(0.0), build(1.0));
    let (w, h) = (448usize, 224usize);
    let (a, b) = (&plain.frames[1], &flipped.frames[1]);
    assert_eq!(a.cloud.pairings.len(), b.cloud.pairings.len());
    for (p, q) in a.cloud.pairings.iter().zip(&b.cloud.pairings) {
        assert_eq!(
            (p.point, p.camera, p.u, p.v, p.row),
            (q.point, q.camera, q.u, q.v, q.row)
        );
        assert_eq!(q.col as usize, w - 1 - p.col as usize);
        assert_eq!(p.superpixel, q.superpixel);
    }
    for (x, y) in a.images.iter().zip(&b.images) {
        assert!(!x.flipped && y.flipped);
        for row in [0, 100, h - 1] {
            for col in [0, 17, 300, w - 1] {
                let m = w - 1 - col;
                assert_eq!(
                    x.rgb[(row * w + col) * 3..][..3],
                    y.rgb[(row * w + m) * 3..][..3]
                );
                assert_eq!(x.superpixels[row * w + col], y.superpixels[row * w + m]);
            }
        }
    }
}

/// Augmentation is a flip, a rotation about z and a scale: distances scale by the
/// drawn factor, z only scales, and voxels are cells of the augmented points.
#[test]
fn augmentation_is_a_similarity_applied_after_pairing() {
    let ds = open(Dialect::Foxglove);
    let plain = SampleBuilder::new(&ds, no_augment())
        .unwrap()
        .build_keyframe(3, 0, 3)
        .unwrap();
    let config = SampleConfig::default();
    let grid = config.voxel;
    let augmented = SampleBuilder::new(&ds, config)
        .unwrap()
        .build_keyframe(3, 0, 3)
        .unwrap();
    let mut clouds: Vec<_> = plain.frames.iter().map(|f| &f.cloud).collect();
    clouds.push(&plain.dense);
    let mut augmented_clouds: Vec<_> = augmented.frames.iter().map(|f| &f.cloud).collect();
    augmented_clouds.push(&augmented.dense);
    let mut draws = Vec::new();
    for (a, b) in clouds.iter().zip(&augmented_clouds) {
        let aug = b.augmentation;
        draws.push(aug);
        assert!((0.95..=1.05).contains(&aug.scale));
        assert!((0.0..=std::f64::consts::PI).contains(&aug.yaw_rad));
        // Pairings are made before augmentation: identical.
        assert_eq!(a.pairings, b.pairings);
        let n = a.xyz.len();
        for i in (0..n).step_by(97) {
            let j = (i * 7 + 13) % n;
            let d = |c: &[[f32; 3]]| {
                let (p, q) = (c[i], c[j]);
                ((p[0] - q[0]).powi(2) + (p[1] - q[1]).powi(2) + (p[2] - q[2]).powi(2)).sqrt()
            };
            let (da, db) = (f64::from(d(&a.xyz)), f64::from(d(&b.xyz)));
            assert!(
                (db - da * aug.scale).abs() < 1e-4 * (1.0 + da),
                "{da} {db} {aug:?}"
            );
            assert!((f64::from(b.xyz[i][2]) - f64::from(a.xyz[i][2]) * aug.scale).abs() < 1e-4);
        }
        for (i, p) in b.xyz.iter().enumerate().step_by(31) {
            let v = b.voxels.point_to_voxel[i] as usize;
            assert_eq!(b.voxels.coords[v], grid.cell(*p));
        }
        assert_eq!(b.levels[0].coords, b.voxels.coords);
    }
    // Drawn per cloud by default.
    assert!(draws.windows(2).any(|w| w[0] != w[1]));
    let mut shared = SampleConfig::default();
    shared.augment.shared = true;
    let s = SampleBuilder::new(&ds, shared)
        .unwrap()
        .build_keyframe(3, 0, 3)
        .unwrap();
    let first = s.dense.augmentation;
    assert!(s.frames.iter().all(|f| f.cloud.augmentation == first));
}

/// `(seed, epoch, index)` fixes a sample: the same twice, with 1 or 2 threads; another
/// epoch draws differently.
#[test]
fn samples_are_deterministic_across_runs_and_threads() {
    let ds = open(Dialect::Ros2);
    let builder = SampleBuilder::new(&ds, SampleConfig::default()).unwrap();
    let pool = |n| {
        rayon::ThreadPoolBuilder::new()
            .num_threads(n)
            .build()
            .unwrap()
    };
    let one = pool(1).install(|| content(builder.build(0, 1).unwrap()));
    let two = pool(2).install(|| content(builder.build(0, 1).unwrap()));
    let again = content(builder.build(0, 1).unwrap());
    assert!(one == two, "1 vs 2 threads differ");
    assert!(one == again, "two runs differ");
    let other = content(builder.build(1, 1).unwrap());
    assert!(other != one);
    // A fresh builder (as after a restart) gives the same sample.
    let ds2 = open(Dialect::Ros2);
    let restarted = SampleBuilder::new(&ds2, SampleConfig::default()).unwrap();
    assert!(content(restarted.build(0, 1).unwrap()) == one);
}

/// SLIC superpixels on the rendered camera images: about 150 segments per image, ids
/// offset per image within a frame, and segments that follow the scene's edges — most
/// of each segment's pixels are of one class in the recorded class map.
#[test]
fn slic_superpixels_follow_the_scene() {
    use std::collections::HashMap;
    let ds = open(Dialect::Foxglove);
    let build = |source| {
        let config = SampleConfig {
            superpixels: source,
            ..no_augment()
        };
        SampleBuilder::new(&ds, config)
            .unwrap()
            .build_keyframe(2, 0, 2)
            .unwrap()
    };
    let slic = build(SuperpixelSource::Slic);
    let classes = build(SuperpixelSource::Channel);
    assert!(!slic.class_superpixels);
    let (mut pure, mut total) = (0usize, 0usize);
    for (frame, class_frame) in slic.frames.iter().zip(&classes.frames) {
        let mut next_id = 0;
        for (image, class_image) in frame.images.iter().zip(&class_frame.images) {
            let min = *image.superpixels.iter().min().unwrap();
            let max = *image.superpixels.iter().max().unwrap();
            assert_eq!(
                min, next_id,
                "ids of image {} start after the previous image",
                image.camera
            );
            let count = max - min + 1;
            assert!(
                (100..=200).contains(&count),
                "{}: {count} segments",
                image.camera
            );
            next_id = max + 1;
            let mut votes: HashMap<(u32, u32), usize> = HashMap::new();
            for (s, c) in image.superpixels.iter().zip(&class_image.superpixels) {
                *votes.entry((*s, *c)).or_default() += 1;
            }
            let mut best: HashMap<u32, usize> = HashMap::new();
            for ((s, _), n) in votes {
                let b = best.entry(s).or_default();
                *b = (*b).max(n);
            }
            pure += best.values().sum::<usize>();
            total += image.superpixels.len();
        }
        assert_eq!(frame.num_superpixels, next_id);
        for p in &frame.cloud.pairings {
            let image = &frame.images[usize::from(p.camera)];
            assert_eq!(
                image.superpixels[usize::from(p.row) * 448 + usize::from(p.col)],
                p.superpixel
            );
        }
    }
    let purity = pure as f64 / total as f64;
    eprintln!(
        "SLIC segments: {:.1} % of pixels in their segment's majority class",
        purity * 100.0
    );
    assert!(purity > 0.85, "{purity}");
}

/// Class maps in a sidecar file (`<drive>.superpixels.mcap` next to `<drive>.mcap`, as
/// when superpixels are computed offline) join the drive: naming only the drive finds
/// them, and the samples are the same as from the single file.
#[test]
fn class_maps_from_a_sidecar_mcap() {
    use std::collections::BTreeMap;
    use superflow_recordings::out::McapOut;
    let drive = sample_drive(Dialect::Ros2).unwrap();
    let dir = std::env::temp_dir().join(format!("superflow-sidecar-{}", std::process::id()));
    std::fs::create_dir_all(&dir).unwrap();
    let (mut main, mut side) = (McapOut::default(), McapOut::default());
    let mut channels: BTreeMap<u16, (bool, usize)> = BTreeMap::new();
    for message in mcap::MessageStream::new(&drive.bytes).unwrap() {
        let m = message.unwrap();
        let is_class_map = m.channel.topic.ends_with("/superpixels");
        let out = if is_class_map { &mut side } else { &mut main };
        let (_, id) = *channels.entry(m.channel.id).or_insert_with(|| {
            let schema = m.channel.schema.as_ref().unwrap();
            let id = out.channel(
                &m.channel.topic,
                "copy",
                (&schema.name, &schema.encoding, &schema.data),
                &m.channel.message_encoding,
                BTreeMap::new(),
            );
            (is_class_map, id)
        });
        out.message(
            id,
            m.log_time as i64,
            m.publish_time as i64,
            m.data.to_vec(),
        );
    }
    let (main_bytes, _) = main.finish("ros2", Some(mcap::Compression::Zstd)).unwrap();
    let (side_bytes, _) = side.finish("ros2", Some(mcap::Compression::Zstd)).unwrap();
    let main_path = dir.join("street.mcap");
    std::fs::write(&main_path, main_bytes).unwrap();
    std::fs::write(dir.join("street.superpixels.mcap"), side_bytes).unwrap();

    for input in [main_path.clone(), dir.clone()] {
        let ds = Dataset::open(std::slice::from_ref(&input), &Default::default()).unwrap();
        assert_eq!(
            ds.drives.len(),
            1,
            "{input:?}: the sidecar is not a drive of its own"
        );
        assert_eq!(ds.drives[0].files.len(), 2);
        assert!(
            ds.drives[0]
                .cameras
                .iter()
                .all(|c| !c.superpixels.is_empty())
        );
        let split = SampleBuilder::new(&ds, no_augment())
            .unwrap()
            .build_keyframe(2, 0, 2)
            .unwrap();
        let original = open(Dialect::Ros2);
        let whole = SampleBuilder::new(&original, no_augment())
            .unwrap()
            .build_keyframe(2, 0, 2)
            .unwrap();
        assert!(split.class_superpixels);
        assert!(content(split) == content(whole), "{input:?}");
    }
    std::fs::remove_dir_all(&dir).unwrap();
}

/// `superflow-pipeline sample --out-mcap` and `--drive-mcap` from the command line: one
/// sample's file, and the drive's file with a dense cloud per keyframe of the drive and
/// the frames in time order; `sample` with no output at all is refused by name.
#[test]
fn sample_writes_foxglove_files_from_the_command_line() {
    use std::process::Command;
    use superflow_tests::{pipeline_binary, workspace_root};
    let dir = std::env::temp_dir().join(format!("superflow-view-cli-{}", std::process::id()));
    std::fs::create_dir_all(&dir).unwrap();
    let (one, all) = (dir.join("one.mcap"), dir.join("drive.mcap"));
    let drive = "recordings/drives/street_ros2.mcap";
    let run = |args: &[&str]| {
        Command::new(pipeline_binary(env!("CARGO_BIN_EXE_superflow-subscriber")))
            .args(args)
            .current_dir(workspace_root())
            .env("RUST_LOG", "warn")
            .output()
            .unwrap()
    };
    let out = run(&[
        "sample",
        "--mcap",
        drive,
        "--index",
        "2",
        "--out-mcap",
        one.to_str().unwrap(),
        "--drive-mcap",
        all.to_str().unwrap(),
    ]);
    let stdout = String::from_utf8_lossy(&out.stdout);
    assert!(
        out.status.success(),
        "{stdout}{}",
        String::from_utf8_lossy(&out.stderr)
    );
    let keyframes = open(Dialect::Ros2).drives[0]
        .keyframes(superflow_schemas::time::KEYFRAME_INTERVAL_NANOS)
        .len();
    assert!(
        stdout.contains(&format!("({keyframes} samples,")),
        "{stdout}"
    );
    let topics = |path: &std::path::Path| {
        let bytes = std::fs::read(path).unwrap();
        let mut stamps: std::collections::BTreeMap<String, Vec<u64>> = Default::default();
        for message in mcap::MessageStream::new(&bytes).unwrap() {
            let message = message.unwrap();
            stamps
                .entry(message.channel.topic.clone())
                .or_default()
                .push(message.log_time);
        }
        stamps
    };
    let one = topics(&one);
    assert_eq!(one["/superflow/dense"].len(), 1);
    assert_eq!(one["/superflow/cloud"].len(), 3, "t − Δt, t, t + Δt");
    let all = topics(&all);
    assert_eq!(all["/superflow/dense"].len(), keyframes);
    let clouds = &all["/superflow/cloud"];
    assert!(clouds.windows(2).all(|w| w[0] < w[1]), "{clouds:?}");
    assert!(clouds.len() >= keyframes, "{clouds:?}");
    let out = run(&["sample", "--mcap", drive]);
    assert_eq!(out.status.code(), Some(2));
    let stderr = String::from_utf8_lossy(&out.stderr);
    assert!(
        stderr.contains("--out") && stderr.contains("--drive-mcap"),
        "{stderr}"
    );
    std::fs::remove_dir_all(&dir).unwrap();
}

/// Under the `blocks` order a frame shared by neighbouring keyframes is built once and
/// reused; every sample's bytes are still those of the same `(keyframe, epoch, index)`
/// built cold, on every sample drive, with class maps and with SLIC.
#[test]
fn blocks_reuse_frames_and_build_the_bytes_of_cold_samples() {
    use superflow_pipeline::batch::{BatchShape, batch_bytes};
    use superflow_pipeline::sample::EpochOrder;
    use superflow_schemas::batch::BatchMeta;

    let drives: Vec<_> = Dialect::ALL
        .into_iter()
        .map(|d| sample_drive(d).unwrap().path)
        .collect();
    let ds = Dataset::open(&drives, &Default::default()).unwrap();
    for superpixels in [SuperpixelSource::Auto, SuperpixelSource::Slic] {
        let config = SampleConfig {
            superpixels,
            ..SampleConfig::default()
        };
        let order = EpochOrder::Blocks { length: 3, open: 2 };
        let blocks = SampleBuilder::new(&ds, config.clone())
            .unwrap()
            .with_order(order);
        let cold = SampleBuilder::new(&ds, config.clone()).unwrap();
        let shape = BatchShape::of(&config);
        let meta = BatchMeta {
            run: "blocks".into(),
            epoch: 0,
            step: 0,
            seed: config.seed,
            sequence: 0,
            created_unix_nanos: 0,
            sample_count: 1,
            flags: 0,
        };
        let mut flips = [0usize; 2];
        for epoch in 0..2 {
            let order = blocks.epoch_order(epoch);
            assert!(order.len() >= 10, "{} keyframes", order.len());
            for (index, &keyframe) in order.iter().enumerate() {
                let warm = blocks.build(epoch, index as u64).unwrap();
                let fresh = cold
                    .build_keyframe(keyframe as usize, epoch, index as u64)
                    .unwrap();
                for image in warm.frames.iter().flat_map(|f| &f.images) {
                    flips[usize::from(image.flipped)] += 1;
                }
                let bytes =
                    |s: &Sample| batch_bytes(std::slice::from_ref(s), shape, &meta).unwrap();
                assert!(
                    bytes(&warm) == bytes(&fresh),
                    "{superpixels:?}: epoch {epoch}, position {index} (keyframe {keyframe})"
                );
                assert_eq!(content(warm), content(fresh));
            }
        }
        let stats = blocks.frame_cache().unwrap().stats();
        let hits = stats.hits.load(std::sync::atomic::Ordering::Relaxed);
        let misses = stats.misses.load(std::sync::atomic::Ordering::Relaxed);
        // Neighbouring keyframes share two of their three frames.
        assert!(
            hits > misses / 2,
            "{superpixels:?}: {hits} hits, {misses} misses"
        );
        assert!(flips[0] > 0 && flips[1] > 0, "{flips:?}");
    }
}
