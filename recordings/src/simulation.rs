//! [`Simulation`]: everything simulated for one drive, before a dialect writes it, and
//! the ground truth it gives.

use crate::dialect::Dialect;
use crate::drive::WrittenDrive;
use crate::options::{DriveOptions, LidarLabels};
use crate::render::{CameraFrame, pixel_rays, render_camera};
use crate::sample_drive::{GENERATOR_VERSION, SCENE_SEED};
use crate::scene::{self, Scene};
use crate::sim::{self, DriveTiming, Return, Rig};
use crate::trigger;
use crate::truth::{self, GroundTruth, Landmark, Observation, PoseSample, PoseTruth};
use nalgebra::{Isometry3, Point3};
use rayon::prelude::*;
use superflow_schemas::Stamp;

/// Everything simulated for one drive, before it is written in a dialect.
#[derive(Debug)]
pub struct Simulation {
    /// The scene.
    pub scene: Scene,
    /// Sensor mounts and intrinsics.
    pub rig: Rig,
    /// Stamps.
    pub timing: DriveTiming,
    /// Returns of every sweep.
    pub sweeps: Vec<Vec<Return>>,
    /// Per camera, its stamps.
    pub camera_stamps: Vec<Vec<Stamp>>,
    /// Per camera, per stamp, the rendered frame.
    pub frames: Vec<Vec<CameraFrame>>,
    /// Landmarks with expected pixels.
    pub landmarks: Vec<Landmark>,
    /// What was asked for.
    pub options: DriveOptions,
}

impl Simulation {
    /// The ego pose at `stamp`.
    pub fn map_from_ego(&self, stamp: Stamp) -> Isometry3<f64> {
        sim::map_from_ego(self.timing.start, stamp)
    }

    /// The class of every return of sweep `k`, in the order the sweep's points are
    /// written: the per-point labels of the drive (empty past the last sweep).
    pub fn sweep_classes(&self, k: usize) -> Vec<u8> {
        self.sweeps
            .get(k)
            .map(|returns| returns.iter().map(|r| r.class).collect())
            .unwrap_or_default()
    }

    /// Returns per class id over every sweep (index = id of [`scene::CLASSES`]).
    pub fn points_per_class(&self) -> Vec<u64> {
        let mut counts = vec![0u64; scene::CLASSES.len()];
        for r in self.sweeps.iter().flatten() {
            if let Some(n) = counts.get_mut(usize::from(r.class)) {
                *n += 1;
            }
        }
        counts
    }

    /// Ego poses at every LiDAR and camera stamp, for the ground truth.
    fn pose_samples(&self, lidar_stamps: &[Stamp]) -> Vec<PoseSample> {
        let mut stamps: Vec<Stamp> = lidar_stamps.to_vec();
        stamps.extend(self.camera_stamps.iter().flatten().copied());
        stamps.sort();
        stamps.dedup();
        stamps
            .into_iter()
            .map(|s| PoseSample {
                stamp_nanos: s.nanos(),
                map_from_ego: PoseTruth::from(&self.map_from_ego(s)),
            })
            .collect()
    }
}

impl Simulation {
    /// Where a dialect writer put the labels, for the ground truth: a `label` UINT8 field
    /// of the clouds on `lidar_topic`, or label clouds on `labels_topic` in the labels
    /// sidecar whose channels are `sidecar_channels`; `None` without labels.
    pub(crate) fn labels_truth(
        &self,
        dialect: Dialect,
        lidar_topic: &str,
        labels_topic: &str,
        sidecar_channels: Option<Vec<truth::ChannelTruth>>,
    ) -> Option<truth::LabelsTruth> {
        let (form, topic) = match self.options.labels.resolve(dialect) {
            LidarLabels::None => return None,
            LidarLabels::Sidecar => ("sidecar", labels_topic),
            LidarLabels::InCloud | LidarLabels::Native => ("field", lidar_topic),
        };
        Some(truth::LabelsTruth {
            form: form.into(),
            topic: topic.into(),
            field: "label".into(),
            datatype: "uint8".into(),
            points_per_class: self.points_per_class(),
            sidecar: sidecar_channels.map(|channels| truth::SidecarTruth {
                file: self
                    .options
                    .labels_sidecar_name(dialect)
                    .unwrap_or_default(),
                channels,
            }),
        })
    }

    /// The ground truth of a drive written from this simulation.
    pub(crate) fn ground_truth(&self, written: WrittenDrive) -> GroundTruth {
        GroundTruth {
            drive: self.options.drive_name(written.dialect),
            dialect: written.dialect.name().into(),
            profile: written.profile.into(),
            compression: written.compression.into(),
            generator_version: GENERATOR_VERSION,
            seed: SCENE_SEED,
            start_stamp_nanos: self.timing.start.nanos(),
            end_stamp_nanos: self
                .timing
                .start
                .add_nanos(self.timing.duration_nanos)
                .nanos(),
            classes: scene::CLASSES.iter().map(|c| c.to_string()).collect(),
            lidar: truth::LidarTruth {
                topic: written.lidar_topic,
                frame_id: written.frames.lidar.clone(),
                rate_hz: 1e9 / self.timing.sweep_nanos as f64,
                beams: self.rig.beam_elevations.len() as u32,
                columns: self.rig.columns as u32,
                motion_compensated: written.motion_compensated,
                stamp_at: written.stamp_at.into(),
                ego_from_lidar: PoseTruth::from(&self.rig.ego_from_lidar),
                sweeps: written.sweeps,
            },
            frames: written.frames,
            channels: written.channels,
            cameras: written.cameras,
            ego_poses: self.pose_samples(&written.lidar_stamps),
            landmarks: self.landmarks.clone(),
            sidecar: written
                .sidecar_channels
                .map(|channels| truth::SidecarTruth {
                    file: self
                        .options
                        .sidecar_name(written.dialect)
                        .unwrap_or_default(),
                    channels,
                }),
            labels: written.labels,
        }
    }
}

/// Simulates the sample drive as `dialect` records it (timing resolution, lens distortion).
pub fn simulate(dialect: Dialect) -> Simulation {
    simulate_with(dialect, &DriveOptions::default())
}

/// Simulates a drive of `options` as `dialect` records it. Sweeps and camera frames
/// are simulated in parallel (each frame also row band by row band).
pub fn simulate_with(dialect: Dialect, options: &DriveOptions) -> Simulation {
    let travel_m = sim::EGO_SPEED * options.duration_secs();
    let scene = Scene::street_for(SCENE_SEED, travel_m);
    let (width, height) = options.image_size;
    let mut rig = Rig::new(width, height, dialect.distortion());
    rig.cameras.truncate(options.cameras);
    rig.columns = options.lidar_columns;
    rig.beam_elevations = sim::beam_elevations(options.beams);
    rig.beam_interval_nanos = options.beam_interval_nanos;
    let mut timing = dialect.timing();
    timing.duration_nanos = options.duration_nanos;
    let sweeps: Vec<Vec<Return>> = (0..timing.sweep_count())
        .into_par_iter()
        .map(|k| sim::simulate_sweep(&scene, &rig, &timing, k))
        .collect();
    let camera_stamps: Vec<Vec<Stamp>> = (0..rig.cameras.len())
        .map(|i| trigger::camera_stamps(options.camera_trigger, &timing, &rig, i))
        .collect();
    let rays: Vec<Vec<nalgebra::Vector3<f64>>> = rig
        .cameras
        .par_iter()
        .map(|cam| pixel_rays(&cam.calibration))
        .collect();
    let jobs: Vec<(usize, Stamp)> = camera_stamps
        .iter()
        .enumerate()
        .flat_map(|(i, stamps)| stamps.iter().map(move |s| (i, *s)))
        .collect();
    let mut rendered: Vec<CameraFrame> = jobs
        .par_iter()
        .map(|(i, stamp)| render_camera(&scene, &rig, timing.start, *i, *stamp, &rays[*i]))
        .collect();
    let mut frames: Vec<Vec<CameraFrame>> = Vec::with_capacity(camera_stamps.len());
    for stamps in camera_stamps.iter().rev() {
        frames.push(rendered.split_off(rendered.len() - stamps.len()));
    }
    frames.reverse();
    let mut simulation = Simulation {
        scene,
        rig,
        timing,
        sweeps,
        camera_stamps,
        frames,
        landmarks: Vec::new(),
        options: options.clone(),
    };
    simulation.landmarks = landmarks(&simulation);
    simulation
}

/// Camera frames observed for landmarks: the first image at or after 1 s into the drive.
fn observation_stamp(sim: &Simulation, camera: usize) -> Stamp {
    let target = sim.timing.start.add_nanos(1_000_000_000);
    sim.camera_stamps[camera]
        .iter()
        .copied()
        .find(|s| *s >= target)
        .unwrap_or(sim.timing.start)
}

/// Projects a map point into a camera at its observation stamp.
fn observe(sim: &Simulation, camera: usize, point: &Point3<f64>) -> Option<Observation> {
    let cam = &sim.rig.cameras[camera];
    let stamp = observation_stamp(sim, camera);
    let map_from_camera = sim.map_from_ego(stamp) * cam.ego_from_optical();
    let in_camera = map_from_camera.inverse_transform_point(point);
    let pixel = cam.calibration.project(&in_camera)?;
    if in_camera.z < 1.0 || !cam.calibration.contains_strict(&pixel) {
        return None;
    }
    let origin: Point3<f64> = map_from_camera.translation.vector.into();
    let to_point = point - origin;
    let distance = to_point.norm();
    let visible = sim
        .scene
        .cast(
            &origin,
            &(to_point / distance),
            stamp.secs_since(sim.timing.start),
            400.0,
        )
        .is_none_or(|hit| hit.distance > distance - 0.05);
    Some(Observation {
        camera: cam.name.to_string(),
        stamp_nanos: stamp.nanos(),
        pixel: [pixel.x, pixel.y],
        depth: in_camera.z,
        visible,
    })
}

/// Up to two visible top corners of static boxes per camera, 3 to 40 m away and at
/// least 10 px inside the image; each is then observed in every camera that sees it.
fn landmarks(sim: &Simulation) -> Vec<Landmark> {
    let mut chosen: Vec<(String, Point3<f64>)> = Vec::new();
    for camera in 0..sim.rig.cameras.len() {
        let (w, h) = sim.options.image_size;
        let mut found = 0;
        for b in sim.scene.boxes.iter().filter(|b| b.motion.is_none()) {
            if found == 2 {
                break;
            }
            for (corner_index, corner) in b.corners_at(0.0).iter().enumerate().skip(4) {
                let Some(obs) = observe(sim, camera, corner) else {
                    continue;
                };
                let inside = obs.pixel[0] > 10.0
                    && obs.pixel[0] < f64::from(w) - 11.0
                    && obs.pixel[1] > 10.0
                    && obs.pixel[1] < f64::from(h) - 11.0;
                let name = format!("{}/corner_{corner_index}", b.name);
                if obs.visible
                    && inside
                    && (3.0..40.0).contains(&obs.depth)
                    && !chosen.iter().any(|(n, _)| *n == name)
                {
                    chosen.push((name, *corner));
                    found += 1;
                    break;
                }
            }
        }
    }
    chosen
        .into_iter()
        .map(|(name, point)| Landmark {
            name,
            point_in_map: [point.x, point.y, point.z],
            observations: (0..sim.rig.cameras.len())
                .filter_map(|camera| observe(sim, camera, &point))
                .collect(),
        })
        .collect()
}
