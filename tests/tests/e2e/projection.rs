//! Geometry of samples on the sample drives: raw sweeps de-skew onto the
//! motion-compensated ones, and LiDAR points projected into the cameras (paper Eq. 1,
//! with the lens distortion) land on pixels of the class they hit.

#![allow(clippy::unwrap_used, clippy::expect_used)] // tests fail loudly on purpose

use nalgebra::Point3;
use superflow_pipeline::decode::image::Target;
use superflow_pipeline::drive::nearest;
use superflow_pipeline::drive::{Drive, IngestConfig};
use superflow_pipeline::sample::deskew::deskew;
use superflow_pipeline::sample::project::{CameraView, camera_from_lidar, pair_points};
use superflow_pipeline::source::ChunkCache;
use superflow_recordings::{Dialect, DriveOptions, generate_with};
use superflow_tests::{dataset, sample_drive};

/// The ROS 2 drive records the same simulated returns as the Foxglove drive, raw (each
/// point in the LiDAR frame at its firing instant, stamped at the sweep start) instead
/// of compensated (all points at the sweep end). De-skewing the raw sweep and moving
/// the compensated one to the sweep start must give the same points.
#[test]
fn raw_sweeps_deskew_onto_the_compensated_sweeps() {
    let ros = dataset(&sample_drive(Dialect::Ros2).unwrap()).unwrap();
    let fox = dataset(&sample_drive(Dialect::Foxglove).unwrap()).unwrap();
    deskew_onto_compensated(&ros, &fox, &[3, 20, 41], 300);
}

/// The same with the lasers of a column firing 1.152 µs apart, as an HDL-32E's do: every
/// point of a raw sweep has its own time (32 beams × 1084 columns a sweep, as on the
/// speed bench's drives).
#[test]
fn raw_sweeps_with_a_time_per_point_deskew_onto_the_compensated_sweeps() {
    let options = DriveOptions {
        name: "per_beam_{dialect}".into(),
        duration_nanos: 600_000_000,
        cameras: 1,
        image_size: (160, 90),
        ..DriveOptions::nuscenes(160, 90)
    };
    let dir = std::env::temp_dir().join(format!("superflow-deskew-{}", std::process::id()));
    std::fs::create_dir_all(&dir).unwrap();
    let [ros, fox] = [Dialect::Ros2, Dialect::Foxglove].map(|dialect| {
        let generated = generate_with(dialect, &options).unwrap();
        let path = dir.join(format!("{}.mcap", options.drive_name(dialect)));
        std::fs::write(&path, &generated.mcap).unwrap();
        Drive::open(std::slice::from_ref(&path), &IngestConfig::default()).unwrap()
    });
    deskew_onto_compensated(&ros, &fox, &[2, 7, 11], 32 * 1084);
    let _ = std::fs::remove_dir_all(&dir);
}

/// De-skews sweeps `sweeps` of the raw drive `ros` and checks them against the same
/// sweeps of the compensated drive `fox`; each raw sweep has at least `distinct_times`
/// firing times (of its points that returned).
fn deskew_onto_compensated(ros: &Drive, fox: &Drive, sweeps: &[usize], distinct_times: usize) {
    let (ros_lidar, fox_lidar) = (ros.lidar.as_ref().unwrap(), fox.lidar.as_ref().unwrap());
    let mut cache = ChunkCache::new(2);
    for &k in sweeps {
        let raw = ros
            .read_sweep(&ros_lidar.sweeps[k], &mut cache)
            .unwrap()
            .cloud;
        let compensated = fox
            .read_sweep(&fox_lidar.sweeps[k], &mut cache)
            .unwrap()
            .cloud;
        assert_eq!(raw.len(), compensated.len());
        let mut times: Vec<u32> = raw
            .time_offset_secs
            .as_ref()
            .unwrap()
            .iter()
            .map(|t| t.to_bits())
            .collect();
        times.sort_unstable();
        times.dedup();
        // Columns with no return at all leave their times out.
        assert!(
            times.len() * 10 >= distinct_times.min(raw.len()) * 9,
            "sweep {k}: {} distinct times",
            times.len()
        );
        let fixed = deskew(&raw, &ros.tf, "map").unwrap();
        // Foxglove points: LIDAR_TOP at the sweep end -> map -> lidar_top at the sweep start.
        let map_from_end = fox
            .tf
            .lookup("map", "LIDAR_TOP", compensated.stamp)
            .unwrap();
        let start_from_map = ros.tf.lookup("lidar_top", "map", raw.stamp).unwrap();
        let start_from_end = start_from_map * map_from_end;
        let (mut worst_fixed, mut worst_raw) = (0.0f64, 0.0f64);
        for ((f, r), c) in fixed.xyz.iter().zip(&raw.xyz).zip(&compensated.xyz) {
            let expected =
                start_from_end * Point3::new(f64::from(c[0]), f64::from(c[1]), f64::from(c[2]));
            let d = |p: &[f32; 3]| {
                (Point3::new(f64::from(p[0]), f64::from(p[1]), f64::from(p[2])) - expected).norm()
            };
            worst_fixed = worst_fixed.max(d(f));
            worst_raw = worst_raw.max(d(r));
        }
        // f32 storage and 50 Hz pose interpolation leave about a millimetre at 70 m.
        assert!(
            worst_fixed < 3e-3,
            "sweep {k}: de-skewed points off by {worst_fixed} m"
        );
        // Without de-skew the 8 m/s motion over a 50 ms revolution smears by decimetres.
        assert!(
            worst_raw > 0.2,
            "sweep {k}: raw points only {worst_raw} m off"
        );
        eprintln!(
            "sweep {k}: {} times, de-skewed within {worst_fixed:.5} m, raw off by up to {worst_raw:.3} m",
            times.len()
        );
    }
}

/// Points projected into each camera land on the class they hit: on road pixels they
/// lie on the ground plane z = 0, on building/pole pixels above it.
#[test]
fn projected_points_land_on_their_class() {
    for dialect in Dialect::ALL {
        let drive = sample_drive(dialect).unwrap();
        let ds = dataset(&drive).unwrap();
        let lidar = ds.lidar.as_ref().unwrap();
        let map = ds.map_frame.as_deref().unwrap();
        let mut cache = ChunkCache::new(4);
        let (mut road, mut road_ok, mut built, mut built_ok) = (0, 0, 0, 0);
        for k in [10, 20, 30, 40] {
            let sweep = &lidar.sweeps[k];
            let cloud = deskew(
                &ds.read_sweep(sweep, &mut cache).unwrap().cloud,
                &ds.tf,
                map,
            )
            .unwrap();
            let map_from_lidar = ds.tf.lookup(map, &lidar.frame_id, cloud.stamp).unwrap();
            for camera in &ds.cameras {
                let frame = nearest(&camera.frames, cloud.stamp).unwrap();
                let classes_frame = nearest(&camera.superpixels, frame.stamp).unwrap();
                assert_eq!(classes_frame.stamp, frame.stamp);
                let classes = ds
                    .read_image(camera, classes_frame, Target::Mono, &mut cache)
                    .unwrap();
                let calibration = camera.calibration_at(frame.stamp).unwrap();
                let camera_from_lidar = camera_from_lidar(
                    &ds.tf,
                    map,
                    &lidar.frame_id,
                    cloud.stamp,
                    &camera.frame_id,
                    frame.stamp,
                )
                .unwrap();
                let view = CameraView::new(calibration, camera_from_lidar);
                for pairing in pair_points(&cloud.xyz, &view) {
                    assert!(pairing.depth > 1.0);
                    assert!(pairing.u > 0.0 && pairing.u < calibration.width as f32 - 1.0);
                    let class = classes
                        .pixel(pairing.u.round() as u32, pairing.v.round() as u32)
                        .unwrap()[0];
                    let p = cloud.xyz[pairing.point as usize];
                    let z = (map_from_lidar
                        * Point3::new(f64::from(p[0]), f64::from(p[1]), f64::from(p[2])))
                    .z;
                    match drive.truth.classes[class as usize].as_str() {
                        "driveable_surface" => {
                            road += 1;
                            road_ok += usize::from(z.abs() < 0.05);
                        }
                        "manmade" => {
                            built += 1;
                            built_ok += usize::from(z > 0.15);
                        }
                        _ => {}
                    }
                }
            }
        }
        let (road_frac, built_frac) =
            (road_ok as f64 / road as f64, built_ok as f64 / built as f64);
        eprintln!(
            "{}: road {road_ok}/{road}, manmade {built_ok}/{built}",
            drive.path.display()
        );
        // Cameras fire up to 40 ms from the sweep and cars move, so a few points land on
        // a neighbouring surface; a wrong pose, extrinsic or distortion drops these far.
        assert!(
            road > 1_000 && road_frac > 0.97,
            "{}: road {road_ok}/{road}",
            drive.path.display()
        );
        assert!(
            built > 300 && built_frac > 0.9,
            "{}: manmade {built_ok}/{built}",
            drive.path.display()
        );
    }
}
