//! Camera rendering: one ray through each pixel centre, cast into the scene at the
//! frame's stamp, giving the colour image, the per-pixel class map and the per-pixel
//! object ids (ground truth, never written).
//!
//! Pixels are cast in tiles of [`TILE`]×[`TILE`]: for each tile only the boxes whose
//! bounding sphere meets the cone of the tile's rays, and that are not all behind the
//! ground the whole tile sees, are tested. Every other box cannot be the first hit, so
//! the image is the same as casting against every box.

use crate::scene::{Scene, Snapshot, class};
use crate::sim::{Rig, map_from_ego};
use crate::srgb::to_srgb;
use nalgebra::{Point2, Point3, UnitQuaternion, Vector3};
use rayon::prelude::*;
use superflow_schemas::Stamp;
use superflow_schemas::sensor::{CameraCalibration, Image, PixelFormat};

/// Side of the square pixel tiles that share one list of candidate boxes.
pub const TILE: usize = 16;
/// Longest camera ray, metres.
pub const CAMERA_MAX_RANGE: f64 = 400.0;

/// Per-pixel object ids of a rendered frame: which scene box ([`crate::scene::Hit::object`])
/// each pixel's ray hit first. Ids are stored in 16 bits; ground, sky and ids of
/// 65535 and above read as `None`.
#[derive(Debug, Clone, PartialEq, Eq)]
pub struct ObjectMap {
    /// Width, pixels.
    pub width: u32,
    /// Height, pixels.
    pub height: u32,
    /// Row-major ids, [`ObjectMap::NONE`] where no box was hit.
    pub ids: Vec<u16>,
}

impl ObjectMap {
    /// The stored id of pixels without a box (ground, sky).
    pub const NONE: u16 = u16::MAX;

    /// The object id at pixel `(col, row)`; `None` for ground, sky or outside the image.
    pub fn get(&self, col: u32, row: u32) -> Option<u32> {
        if col >= self.width || row >= self.height {
            return None;
        }
        let index = row as usize * self.width as usize + col as usize;
        let id = *self.ids.get(index)?;
        (id != Self::NONE).then_some(u32::from(id))
    }

    /// The stored form of an object id.
    fn store(object: Option<u32>) -> u16 {
        object
            .and_then(|id| u16::try_from(id).ok())
            .filter(|id| *id != Self::NONE)
            .unwrap_or(Self::NONE)
    }
}

/// A rendered camera frame: the RGB image, the per-pixel class map and object ids.
#[derive(Debug, Clone)]
pub struct CameraFrame {
    /// Colour image (RGB8).
    pub image: Image,
    /// Class id per pixel (Mono8), what a vision foundation model would segment.
    pub classes: Image,
    /// Object id per pixel: simulation ground truth, not written to the drive.
    pub objects: ObjectMap,
}

const SUN: [f64; 3] = [0.35, -0.45, 0.82];

/// One frame's viewpoint: where the camera is, where the boxes are.
#[derive(Debug)]
struct View {
    origin: Point3<f64>,
    rotation: UnitQuaternion<f64>,
    sun: Vector3<f64>,
    /// Every box at the frame's stamp.
    snapshot: Snapshot,
}

impl View {
    /// The boxes a tile of rays `directions` may hit before the ground, ascending.
    fn candidates(&self, directions: &[Vector3<f64>], out: &mut Vec<usize>) {
        out.clear();
        let sum: Vector3<f64> = directions.iter().sum();
        let Some(axis) = sum.try_normalize(1e-9) else {
            out.extend(0..self.snapshot.poses.len());
            return;
        };
        let cos_spread = directions
            .iter()
            .map(|d| d.dot(&axis) / d.norm())
            .fold(1.0f64, f64::min);
        let spread = cos_spread.clamp(-1.0, 1.0).acos();
        // Where every ray of the tile meets the ground, no box farther away can be hit
        // first (`Scene::cast` keeps the ground when it is nearer).
        let all_down = self.origin.z > 0.02 && directions.iter().all(|d| d.z < -1e-9);
        let limit = if all_down {
            directions
                .iter()
                .map(|d| -self.origin.z / d.z)
                .fold(0.0f64, f64::max)
        } else {
            CAMERA_MAX_RANGE
        };
        let limit = limit * (1.0 + 1e-9) + 1e-6;
        for (index, pose) in self.snapshot.poses.iter().enumerate() {
            let (center, radius) = (pose.center, pose.radius);
            let v = center - self.origin;
            let distance = v.norm();
            if distance - radius > limit {
                continue;
            }
            if distance > radius {
                let half_angle = (radius / distance).asin();
                let off_axis = (v.dot(&axis) / distance).clamp(-1.0, 1.0).acos();
                if off_axis > spread + half_angle + 1e-5 {
                    continue;
                }
            }
            out.push(index);
        }
    }

    /// Colour, class and object of the ray `direction` among `candidates`.
    fn shade(
        &self,
        scene: &Scene,
        candidates: &[usize],
        direction: &Vector3<f64>,
    ) -> ([f64; 3], u8, Option<u32>) {
        let sky = {
            let up = direction.z.clamp(-0.2, 1.0);
            [0.45 - 0.25 * up, 0.6 - 0.2 * up, 0.85]
        };
        let hit = scene.cast_in(
            &self.snapshot,
            candidates,
            &self.origin,
            direction,
            CAMERA_MAX_RANGE,
        );
        match hit {
            Some(hit) => {
                let light = 0.35 + 0.65 * hit.normal.dot(&self.sun).max(0.0);
                let fog = 1.0 - (-hit.distance / 250.0).exp();
                let lit = [0, 1, 2].map(|i| hit.color[i] * light * (1.0 - fog) + sky[i] * fog);
                (lit, hit.class, hit.object)
            }
            None => (sky, class::NOISE, None),
        }
    }
}

/// One band of [`TILE`] rows (fewer at the bottom) of the three outputs.
struct Band<'a> {
    first_row: usize,
    rgb: &'a mut [u8],
    classes: &'a mut [u8],
    objects: &'a mut [u16],
}

/// Renders one band, tile by tile.
fn render_band(scene: &Scene, view: &View, rays: &[Vector3<f64>], width: usize, band: Band<'_>) {
    let rows = band.classes.len() / width;
    let mut directions = Vec::with_capacity(TILE * TILE);
    let mut candidates = Vec::with_capacity(scene.boxes.len());
    for first_col in (0..width).step_by(TILE) {
        let cols = TILE.min(width - first_col);
        directions.clear();
        for r in 0..rows {
            let start = (band.first_row + r) * width + first_col;
            directions.extend(
                rays[start..start + cols]
                    .iter()
                    .map(|ray| view.rotation * ray),
            );
        }
        view.candidates(&directions, &mut candidates);
        for r in 0..rows {
            for c in 0..cols {
                let (color, class_id, object) =
                    view.shade(scene, &candidates, &directions[r * cols + c]);
                let pixel = r * width + first_col + c;
                for (i, channel) in color.iter().enumerate() {
                    band.rgb[pixel * 3 + i] = to_srgb(*channel);
                }
                band.classes[pixel] = class_id;
                band.objects[pixel] = ObjectMap::store(object);
            }
        }
    }
}

/// Renders camera `camera` of the rig at `stamp`: one ray through each pixel centre.
pub fn render_camera(
    scene: &Scene,
    rig: &Rig,
    start: Stamp,
    camera: usize,
    stamp: Stamp,
    rays_in_camera: &[Vector3<f64>],
) -> CameraFrame {
    let cam = &rig.cameras[camera];
    let (w, h) = (
        cam.calibration.width as usize,
        cam.calibration.height as usize,
    );
    let map_from_camera = map_from_ego(start, stamp) * cam.ego_from_optical();
    let t_secs = stamp.secs_since(start);
    let view = View {
        origin: map_from_camera.translation.vector.into(),
        rotation: map_from_camera.rotation,
        sun: Vector3::from(SUN).normalize(),
        snapshot: scene.snapshot(t_secs),
    };
    let mut rgb = vec![0u8; w * h * 3];
    let mut classes = vec![class::NOISE; w * h];
    let mut objects = vec![ObjectMap::NONE; w * h];
    if w > 0 {
        rgb.par_chunks_mut(w * 3 * TILE)
            .zip(classes.par_chunks_mut(w * TILE))
            .zip(objects.par_chunks_mut(w * TILE))
            .enumerate()
            .for_each(|(index, ((rgb, classes), objects))| {
                let band = Band {
                    first_row: index * TILE,
                    rgb,
                    classes,
                    objects,
                };
                render_band(scene, &view, rays_in_camera, w, band);
            });
    }
    let frame_id = cam.calibration.frame_id.clone();
    // Sizes are consistent by construction; `Image::new` re-checks them.
    let image = Image::new(
        stamp,
        frame_id.clone(),
        w as u32,
        h as u32,
        PixelFormat::Rgb8,
        rgb,
    );
    let classes = Image::new(
        stamp,
        frame_id,
        w as u32,
        h as u32,
        PixelFormat::Mono8,
        classes,
    );
    let objects = ObjectMap {
        width: w as u32,
        height: h as u32,
        ids: objects,
    };
    match (image, classes) {
        (Ok(image), Ok(classes)) => CameraFrame {
            image,
            classes,
            objects,
        },
        (Err(e), _) | (_, Err(e)) => unreachable!("rendered image has a consistent size: {e}"),
    }
}

/// The unit ray through the centre of every pixel of a camera, row-major.
pub fn pixel_rays(calibration: &CameraCalibration) -> Vec<Vector3<f64>> {
    let (w, h) = (calibration.width, calibration.height);
    (0..h)
        .flat_map(|row| (0..w).map(move |col| (col, row)))
        .map(|(col, row)| {
            calibration
                .unproject(&Point2::new(f64::from(col), f64::from(row)))
                .coords
                .normalize()
        })
        .collect()
}

#[cfg(test)]
mod tests {
    #![allow(clippy::unwrap_used)] // tests fail loudly on purpose
    use super::*;
    use crate::dialect::Dialect;
    use crate::sample_drive::SCENE_SEED;
    use crate::scene::Scene;
    use crate::sim::{Return, simulate_sweep};
    use std::collections::BTreeMap;

    /// Returns on moving boxes by (camera, firing stamp), with their projected pixel.
    type Seen = BTreeMap<(usize, Stamp), Vec<(Return, Point2<f64>)>>;

    /// A LiDAR return on a moving box, projected into a camera whose frame is rendered at
    /// the return's firing instant (with the true rig geometry and lens distortion), lands
    /// on a pixel whose object id is that box.
    #[test]
    fn returns_on_moving_boxes_project_onto_their_object() {
        let dialect = Dialect::Ros2;
        let scene = Scene::street(SCENE_SEED);
        let mut rig = Rig::new(320, 180, dialect.distortion());
        rig.columns = 360;
        let timing = dialect.timing();
        // (camera, firing stamp) → returns on moving boxes seen strictly inside the image.
        let mut seen: Seen = BTreeMap::new();
        for k in (0..timing.sweep_count()).step_by(4) {
            for r in simulate_sweep(&scene, &rig, &timing, k) {
                let Some(id) = r.object.filter(|id| scene.is_moving(*id)) else {
                    continue;
                };
                assert_eq!(Some(r.class), scene.object(id).map(|b| b.class));
                for (i, cam) in rig.cameras.iter().enumerate() {
                    let map_from_camera =
                        map_from_ego(timing.start, r.stamp) * cam.ego_from_optical();
                    let p = map_from_camera.inverse_transform_point(&r.point_in_map);
                    let Some(pixel) = cam.calibration.project(&p) else {
                        continue;
                    };
                    if p.z > 0.5 && cam.calibration.contains_strict(&pixel) {
                        seen.entry((i, r.stamp)).or_default().push((r, pixel));
                    }
                }
            }
        }
        let rays: Vec<Vec<Vector3<f64>>> = rig
            .cameras
            .iter()
            .map(|c| pixel_rays(&c.calibration))
            .collect();
        let (mut tested, mut matched) = (0usize, 0usize);
        let mut objects = std::collections::BTreeSet::new();
        let step = (seen.len() / 40).max(1);
        for ((camera, stamp), returns) in seen.iter().step_by(step) {
            let frame = render_camera(&scene, &rig, timing.start, *camera, *stamp, &rays[*camera]);
            for (r, pixel) in returns {
                let (col, row) = (pixel.x.round() as u32, pixel.y.round() as u32);
                tested += 1;
                if frame.objects.get(col, row) == r.object {
                    matched += 1;
                    objects.insert(r.object);
                }
            }
        }
        eprintln!("{matched} of {tested} returns on moving boxes land on their object");
        assert!(
            tested >= 100,
            "only {tested} returns on moving boxes in view"
        );
        assert!(objects.len() >= 2, "moving objects matched: {objects:?}");
        // Misses are box edges (the point's pixel centre ray grazes past) and points the
        // camera sees occluded from its own viewpoint.
        assert!(
            matched as f64 >= 0.9 * tested as f64,
            "{matched} of {tested} returns land on their object"
        );
    }

    #[test]
    fn ground_and_sky_have_no_object() {
        let scene = Scene::street(SCENE_SEED);
        let rig = Rig::new(64, 36, superflow_schemas::sensor::Distortion::None);
        let rays = pixel_rays(&rig.cameras[0].calibration);
        let start = Stamp::from_nanos(0);
        let frame = render_camera(&scene, &rig, start, 0, start, &rays);
        // Bottom centre: the road in front of the car; top row: sky or a building.
        assert_eq!(frame.objects.get(32, 35), None);
        assert_eq!(frame.classes.data[35 * 64 + 32], class::DRIVEABLE_SURFACE);
        for col in 0..64 {
            let (object, class_id) = (frame.objects.get(col, 0), frame.classes.data[col as usize]);
            assert_eq!(object.is_none(), class_id == class::NOISE, "column {col}");
        }
        assert_eq!(frame.objects.get(64, 0), None);
    }

    /// Casting each tile against its candidate boxes gives the same frame as casting
    /// every pixel against every box.
    #[test]
    fn tile_culling_changes_nothing() {
        let scene = Scene::street(SCENE_SEED);
        let rig = Rig::new(96, 54, Dialect::Ros2.distortion());
        let start = Stamp::from_nanos(0);
        for camera in 0..rig.cameras.len() {
            let cam = &rig.cameras[camera];
            let rays = pixel_rays(&cam.calibration);
            let stamp = start.add_nanos(700_000_000);
            let frame = render_camera(&scene, &rig, start, camera, stamp, &rays);
            let map_from_camera = map_from_ego(start, stamp) * cam.ego_from_optical();
            let origin: Point3<f64> = map_from_camera.translation.vector.into();
            for (i, ray) in rays.iter().enumerate() {
                let direction = map_from_camera.rotation * ray;
                let hit = scene.cast(&origin, &direction, 0.7, CAMERA_MAX_RANGE);
                assert_eq!(
                    ObjectMap::store(hit.and_then(|h| h.object)),
                    frame.objects.ids[i]
                );
                assert_eq!(hit.map_or(class::NOISE, |h| h.class), frame.classes.data[i]);
            }
        }
    }
}
