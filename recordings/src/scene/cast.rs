//! Exact ray casting into the scene: boxes by a bounding-sphere test then a slab test,
//! the ground plane, and the materials of what was hit. A [`Snapshot`] holds the boxes'
//! poses at one instant for the many rays of a camera frame.

use super::classes::class;
use super::objects::{Hit, Scene, SceneBox};
use super::street::{ROAD_HALF_WIDTH, SIDEWALK_EDGE};
use nalgebra::{Point3, Vector3};

/// A box at one instant: its centre, the sine and cosine of its heading and the radius of
/// its bounding sphere (about the centre).
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct BoxPose {
    /// Centre, map frame.
    pub center: Point3<f64>,
    /// `yaw.sin_cos()`.
    pub sin_cos: (f64, f64),
    /// Bounding-sphere radius, metres.
    pub radius: f64,
}

/// The poses of every box of a scene at one instant.
#[derive(Debug, Clone, PartialEq)]
pub struct Snapshot {
    /// Seconds after the drive's start.
    pub t_secs: f64,
    /// One pose per box, in the order of [`Scene::boxes`].
    pub poses: Vec<BoxPose>,
}

/// Where the boxes are during one cast.
trait Poses {
    /// Seconds after the drive's start.
    fn t_secs(&self) -> f64;
    /// Centre and heading's sine and cosine of box `index`.
    fn pose(&self, index: usize, b: &SceneBox) -> (Point3<f64>, (f64, f64));
}

/// Poses computed box by box, as the rays need them.
struct Live(f64);

impl Poses for Live {
    fn t_secs(&self) -> f64 {
        self.0
    }

    fn pose(&self, _: usize, b: &SceneBox) -> (Point3<f64>, (f64, f64)) {
        (b.center_at(self.0), b.yaw.sin_cos())
    }
}

impl Poses for Snapshot {
    fn t_secs(&self) -> f64 {
        self.t_secs
    }

    fn pose(&self, index: usize, b: &SceneBox) -> (Point3<f64>, (f64, f64)) {
        match self.poses.get(index) {
            Some(p) => (p.center, p.sin_cos),
            None => Live(self.t_secs).pose(index, b),
        }
    }
}

/// A ray: unit direction, longest distance.
#[derive(Debug, Clone, Copy)]
struct Ray<'a> {
    origin: &'a Point3<f64>,
    direction: &'a Vector3<f64>,
    max_range: f64,
}

impl Scene {
    /// The poses of every box at `t_secs` after the drive's start.
    pub fn snapshot(&self, t_secs: f64) -> Snapshot {
        Snapshot {
            t_secs,
            poses: self
                .boxes
                .iter()
                .map(|b| BoxPose {
                    center: b.center_at(t_secs),
                    sin_cos: b.yaw.sin_cos(),
                    radius: b.half.norm(),
                })
                .collect(),
        }
    }

    /// The first surface hit by the ray `origin + s·direction` (unit direction, s > 1 cm)
    /// at `t_secs` after the drive's start, if any within `max_range`.
    pub fn cast(
        &self,
        origin: &Point3<f64>,
        direction: &Vector3<f64>,
        t_secs: f64,
        max_range: f64,
    ) -> Option<Hit> {
        let ray = Ray {
            origin,
            direction,
            max_range,
        };
        self.cast_boxes(self.boxes.iter().enumerate(), &Live(t_secs), &ray)
    }

    /// [`Scene::cast`] at the instant of `snapshot` (this scene's), testing only the boxes
    /// of `candidates` (indices into [`Scene::boxes`], ascending): the same hit as `cast`
    /// whenever every box the ray can hit before the ground is among them.
    pub fn cast_in(
        &self,
        snapshot: &Snapshot,
        candidates: &[usize],
        origin: &Point3<f64>,
        direction: &Vector3<f64>,
        max_range: f64,
    ) -> Option<Hit> {
        let ray = Ray {
            origin,
            direction,
            max_range,
        };
        let boxes = candidates
            .iter()
            .filter_map(|&i| self.boxes.get(i).map(|b| (i, b)));
        self.cast_boxes(boxes, snapshot, &ray)
    }

    /// The nearest hit among `boxes` (posed by `poses`) and the ground.
    fn cast_boxes<'a>(
        &'a self,
        boxes: impl Iterator<Item = (usize, &'a SceneBox)>,
        poses: &impl Poses,
        ray: &Ray<'_>,
    ) -> Option<Hit> {
        let Ray {
            origin,
            direction,
            max_range,
        } = *ray;
        let mut best: Option<(f64, usize, Vector3<f64>)> = None;
        let mut nearest = max_range;
        for (index, b) in boxes {
            let pose = poses.pose(index, b);
            // Bounding-sphere rejection before the exact slab test.
            let to_center = pose.0 - origin;
            let along = to_center.dot(direction);
            let radius2 = b.half.norm_squared();
            if along < -radius2.sqrt()
                || along - radius2.sqrt() > nearest
                || to_center.norm_squared() - along * along > radius2
            {
                continue;
            }
            if let Some((s, normal)) = intersect_box(b, pose, origin, direction, nearest) {
                nearest = s;
                best = Some((s, index, normal));
            }
        }
        let ground = (direction.z < -1e-9)
            .then(|| -origin.z / direction.z)
            .filter(|s| *s > 0.01 && *s < nearest);
        if let Some(s) = ground {
            let point = origin + direction * s;
            let (class, color, reflectivity) = ground_material(&point);
            return Some(Hit {
                distance: s,
                point,
                normal: Vector3::z(),
                class,
                color,
                reflectivity,
                object: None,
            });
        }
        let (s, index, normal) = best?;
        let b = &self.boxes[index];
        let point = origin + direction * s;
        let (color, reflectivity) = box_material(b, &point, &normal, poses.t_secs());
        Some(Hit {
            distance: s,
            point,
            normal,
            class: b.class,
            color,
            reflectivity,
            object: u32::try_from(index).ok(),
        })
    }
}

/// Slab test in the box's own frame; returns the entry distance and outward normal.
fn intersect_box(
    b: &SceneBox,
    (c, (s, co)): (Point3<f64>, (f64, f64)),
    origin: &Point3<f64>,
    direction: &Vector3<f64>,
    max_s: f64,
) -> Option<(f64, Vector3<f64>)> {
    let rel = origin - c;
    // Rotate into the box frame (inverse yaw).
    let o = Vector3::new(co * rel.x + s * rel.y, -s * rel.x + co * rel.y, rel.z);
    let d = Vector3::new(
        co * direction.x + s * direction.y,
        -s * direction.x + co * direction.y,
        direction.z,
    );
    let mut t_near = 0.01f64;
    let mut t_far = max_s;
    let mut axis = usize::MAX;
    let mut sign = 0.0;
    for i in 0..3 {
        if d[i].abs() < 1e-12 {
            if o[i].abs() > b.half[i] {
                return None;
            }
            continue;
        }
        let inv = 1.0 / d[i];
        let mut t0 = (-b.half[i] - o[i]) * inv;
        let mut t1 = (b.half[i] - o[i]) * inv;
        let mut entry_sign = -1.0;
        if t0 > t1 {
            std::mem::swap(&mut t0, &mut t1);
            entry_sign = 1.0;
        }
        if t0 > t_near {
            t_near = t0;
            axis = i;
            sign = entry_sign;
        }
        t_far = t_far.min(t1);
        if t_near > t_far {
            return None;
        }
    }
    if axis == usize::MAX {
        return None; // origin inside the box
    }
    let mut local = Vector3::zeros();
    local[axis] = sign;
    let normal = Vector3::new(
        co * local.x - s * local.y,
        s * local.x + co * local.y,
        local.z,
    );
    Some((t_near, normal))
}

fn ground_material(p: &Point3<f64>) -> (u8, [f64; 3], f64) {
    let ay = p.y.abs();
    if ay < ROAD_HALF_WIDTH {
        // Dashed centre line and solid edge lines.
        let dash = (p.y + 1.5).abs() < 0.08 && p.x.rem_euclid(6.0) < 3.0;
        let edge = (ay - 7.2).abs() < 0.1;
        if dash || edge {
            (class::DRIVEABLE_SURFACE, [0.92, 0.92, 0.88], 0.85)
        } else {
            let patch = ((p.x * 0.7).floor() + (p.y * 0.7).floor()).rem_euclid(2.0);
            let g = 0.26 + 0.03 * patch;
            (class::DRIVEABLE_SURFACE, [g, g, g + 0.01], 0.12)
        }
    } else if ay < SIDEWALK_EDGE {
        let tile = ((p.x * 2.0).floor() + (p.y * 2.0).floor()).rem_euclid(2.0);
        let g = 0.58 + 0.05 * tile;
        (class::SIDEWALK, [g, g * 0.97, g * 0.92], 0.3)
    } else {
        let n = ((p.x * 1.3).sin() * (p.y * 1.7).cos() * 0.5 + 0.5) * 0.08;
        (class::TERRAIN, [0.22 + n, 0.42 + n, 0.16], 0.2)
    }
}

fn box_material(
    b: &SceneBox,
    p: &Point3<f64>,
    normal: &Vector3<f64>,
    t_secs: f64,
) -> ([f64; 3], f64) {
    if b.class != class::MANMADE || b.half.z < 3.5 {
        // Darker lower half on cars (windows are above the belt line in reality; any
        // contrast will do for the images).
        if b.class == class::CAR && p.z > b.center_at(t_secs).z + 0.2 {
            return (b.color.map(|c| c * 0.45), b.reflectivity * 0.6);
        }
        return (b.color, b.reflectivity);
    }
    // Buildings: a grid of windows on the facades.
    let along = if normal.z.abs() > 0.5 {
        return (b.color.map(|c| c * 0.8), b.reflectivity);
    } else {
        p.x * normal.y.abs() + p.y * normal.x.abs()
    };
    let window = along.rem_euclid(2.5) > 0.8 && p.z.rem_euclid(3.0) > 1.0 && p.z > 2.5;
    if window {
        ([0.2, 0.27, 0.35], 0.1)
    } else {
        (b.color, b.reflectivity)
    }
}
