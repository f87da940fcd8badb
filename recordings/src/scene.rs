//! A small procedural street: ground regions, buildings, trees, cones, parked and moving
//! cars and a pedestrian, all boxes, with semantic classes and colours; exact ray casting
//! ([`cast`]).

mod cast;

pub use cast::{BoxPose, Snapshot};

use nalgebra::{Point3, Vector3};

/// Semantic classes, numbered as nuScenes-lidarseg's 16 classes plus 0 for noise and sky.
pub const CLASSES: [&str; 17] = [
    "noise",
    "barrier",
    "bicycle",
    "bus",
    "car",
    "construction_vehicle",
    "motorcycle",
    "pedestrian",
    "traffic_cone",
    "trailer",
    "truck",
    "driveable_surface",
    "other_flat",
    "sidewalk",
    "terrain",
    "manmade",
    "vegetation",
];

/// Class ids used by the scene.
pub mod class {
    /// Sky and anything not hit.
    pub const NOISE: u8 = 0;
    /// Concrete barriers.
    pub const BARRIER: u8 = 1;
    /// Cars.
    pub const CAR: u8 = 4;
    /// Pedestrians.
    pub const PEDESTRIAN: u8 = 7;
    /// Traffic cones.
    pub const TRAFFIC_CONE: u8 = 8;
    /// The road.
    pub const DRIVEABLE_SURFACE: u8 = 11;
    /// Sidewalks.
    pub const SIDEWALK: u8 = 13;
    /// Grass beside the sidewalk.
    pub const TERRAIN: u8 = 14;
    /// Buildings and poles.
    pub const MANMADE: u8 = 15;
    /// Trees.
    pub const VEGETATION: u8 = 16;
}

/// Half-width of the road (|y| below is road), in metres.
pub const ROAD_HALF_WIDTH: f64 = 7.5;
/// Outer edge of the sidewalks.
pub const SIDEWALK_EDGE: f64 = 11.0;

/// A deterministic pseudo-random stream (splitmix64), so the scene is identical on every
/// machine and with every dependency version.
#[derive(Debug, Clone)]
pub struct SplitMix(u64);

impl SplitMix {
    /// A stream from a seed.
    pub fn new(seed: u64) -> Self {
        Self(seed)
    }

    /// The next 64 random bits.
    pub fn next_u64(&mut self) -> u64 {
        self.0 = self.0.wrapping_add(0x9E37_79B9_7F4A_7C15);
        let mut z = self.0;
        z = (z ^ (z >> 30)).wrapping_mul(0xBF58_476D_1CE4_E5B9);
        z = (z ^ (z >> 27)).wrapping_mul(0x94D0_49BB_1331_11EB);
        z ^ (z >> 31)
    }

    /// Uniform in `[lo, hi)`.
    pub fn uniform(&mut self, lo: f64, hi: f64) -> f64 {
        lo + (hi - lo) * ((self.next_u64() >> 11) as f64 / (1u64 << 53) as f64)
    }
}

/// How a box moves: constant velocity along x from `x0` at the drive's start.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct Motion {
    /// Speed along +x in m/s (negative: driving towards -x).
    pub speed_x: f64,
}

/// An upright box (yaw only) with a class and a base colour.
#[derive(Debug, Clone, PartialEq)]
pub struct SceneBox {
    /// Stable name, used for landmarks.
    pub name: String,
    /// Centre of the box at the drive's start (map frame).
    pub center: Point3<f64>,
    /// Half extents along the box's own x, y, z.
    pub half: Vector3<f64>,
    /// Heading about z, radians.
    pub yaw: f64,
    /// Semantic class.
    pub class: u8,
    /// Base colour (linear RGB in 0..1).
    pub color: [f64; 3],
    /// LiDAR reflectivity in 0..1.
    pub reflectivity: f64,
    /// `None` for static boxes.
    pub motion: Option<Motion>,
}

impl SceneBox {
    /// Centre at `t_secs` after the drive's start.
    pub fn center_at(&self, t_secs: f64) -> Point3<f64> {
        match self.motion {
            None => self.center,
            Some(m) => self.center + Vector3::new(m.speed_x * t_secs, 0.0, 0.0),
        }
    }

    /// Whether the box moves during the drive.
    pub fn is_moving(&self) -> bool {
        self.motion.is_some_and(|m| m.speed_x != 0.0)
    }

    /// The eight corners at `t_secs`, bottom ones first.
    pub fn corners_at(&self, t_secs: f64) -> [Point3<f64>; 8] {
        let c = self.center_at(t_secs);
        let (s, co) = self.yaw.sin_cos();
        let mut out = [Point3::origin(); 8];
        for (i, corner) in out.iter_mut().enumerate() {
            let lx = if i & 1 == 0 {
                -self.half.x
            } else {
                self.half.x
            };
            let ly = if i & 2 == 0 {
                -self.half.y
            } else {
                self.half.y
            };
            let lz = if i & 4 == 0 {
                -self.half.z
            } else {
                self.half.z
            };
            *corner = Point3::new(c.x + co * lx - s * ly, c.y + s * lx + co * ly, c.z + lz);
        }
        out
    }
}

/// What a ray hit.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct Hit {
    /// Distance along the (unit) ray.
    pub distance: f64,
    /// Hit point in the map frame.
    pub point: Point3<f64>,
    /// Outward surface normal (unit).
    pub normal: Vector3<f64>,
    /// Semantic class.
    pub class: u8,
    /// Surface colour at the hit (texture included).
    pub color: [f64; 3],
    /// LiDAR reflectivity at the hit.
    pub reflectivity: f64,
    /// Id of the box hit (its index in [`Scene::boxes`]); `None` for the ground.
    pub object: Option<u32>,
}

/// The street scene.
#[derive(Debug, Clone)]
pub struct Scene {
    /// Every box of the scene.
    pub boxes: Vec<SceneBox>,
}

fn jitter(rng: &mut SplitMix, color: [f64; 3], amount: f64) -> [f64; 3] {
    let k = rng.uniform(1.0 - amount, 1.0 + amount);
    color.map(|c| (c * k).clamp(0.0, 1.0))
}

/// A box as the street lays it out: standing on the ground, `base` the centre of its
/// bottom face and `size` its full extents.
#[derive(Debug)]
struct Placed {
    name: String,
    base: [f64; 3],
    size: [f64; 3],
    yaw: f64,
    class: u8,
    color: [f64; 3],
    reflectivity: f64,
    motion: Option<Motion>,
}

/// The street while it is being laid out: the random stream and the boxes so far. Each
/// part draws from the stream in turn, so the order of the parts fixes the scene.
#[derive(Debug)]
struct StreetBuilder {
    rng: SplitMix,
    boxes: Vec<SceneBox>,
    /// How much further than the sample drives' street the rows of buildings, trees and
    /// parked cars go, metres.
    extra_m: f64,
}

impl StreetBuilder {
    fn add(&mut self, placed: Placed) {
        let Placed {
            name,
            base: [x, y, z],
            size: [length, width, height],
            yaw,
            class,
            color,
            reflectivity,
            motion,
        } = placed;
        self.boxes.push(SceneBox {
            name,
            center: Point3::new(x, y, z + height / 2.0),
            half: Vector3::new(length / 2.0, width / 2.0, height / 2.0),
            yaw,
            class,
            color,
            reflectivity,
            motion,
        });
    }

    /// Buildings along one side of the street (`sign` 1 left, -1 right).
    fn buildings(&mut self, side: &str, sign: f64) {
        let mut x = -45.0;
        let mut index = 0;
        while x < 95.0 + self.extra_m {
            let length = self.rng.uniform(8.0, 16.0);
            let depth = self.rng.uniform(8.0, 14.0);
            let height = self.rng.uniform(6.0, 18.0);
            let setback = self.rng.uniform(13.0, 16.0);
            let color = jitter(&mut self.rng, [0.62, 0.55, 0.48], 0.25);
            let yaw = self.rng.uniform(-0.05, 0.05);
            self.add(Placed {
                name: format!("building_{side}_{index}"),
                base: [x + length / 2.0, sign * (setback + depth / 2.0), 0.0],
                size: [length, depth, height],
                yaw,
                class: class::MANMADE,
                color,
                reflectivity: 0.35,
                motion: None,
            });
            x += length + self.rng.uniform(1.5, 5.0);
            index += 1;
        }
    }

    /// Trees, and every third a pole, along the sidewalk edge of one side.
    fn trees_and_poles(&mut self, side: &str, sign: f64) {
        let mut x = -40.0 + self.rng.uniform(0.0, 6.0);
        let mut index = 0;
        while x < 90.0 + self.extra_m {
            if index % 3 == 2 {
                self.add(Placed {
                    name: format!("pole_{side}_{index}"),
                    base: [x, sign * 10.2, 0.0],
                    size: [0.3, 0.3, 6.0],
                    yaw: 0.0,
                    class: class::MANMADE,
                    color: [0.35, 0.35, 0.38],
                    reflectivity: 0.6,
                    motion: None,
                });
            } else {
                let color = jitter(&mut self.rng, [0.18, 0.45, 0.15], 0.2);
                let height = self.rng.uniform(3.5, 6.0);
                let yaw = self.rng.uniform(0.0, 1.5);
                self.add(Placed {
                    name: format!("tree_{side}_{index}"),
                    base: [x, sign * 10.0, 0.0],
                    size: [1.6, 1.6, height],
                    yaw,
                    class: class::VEGETATION,
                    color,
                    reflectivity: 0.25,
                    motion: None,
                });
            }
            x += self.rng.uniform(7.0, 11.0);
            index += 1;
        }
    }

    /// Parked cars on the right edge of the road.
    fn parked_cars(&mut self) {
        let mut x = -20.0;
        let mut index = 0;
        while x < 80.0 + self.extra_m {
            let color = [
                self.rng.uniform(0.1, 0.9),
                self.rng.uniform(0.1, 0.9),
                self.rng.uniform(0.1, 0.9),
            ];
            let yaw = self.rng.uniform(-0.08, 0.08);
            self.add(Placed {
                name: format!("parked_car_{index}"),
                base: [x, -6.3, 0.0],
                size: [4.5, 1.9, 1.5],
                yaw,
                class: class::CAR,
                color,
                reflectivity: 0.5,
                motion: None,
            });
            x += self.rng.uniform(7.0, 14.0);
            index += 1;
        }
    }

    /// Traffic: a car ahead in the ego lane, an oncoming car, a pedestrian.
    fn traffic(&mut self) {
        self.add(Placed {
            name: "lead_car".into(),
            base: [14.0, 0.3, 0.0],
            size: [4.6, 1.9, 1.6],
            yaw: 0.0,
            class: class::CAR,
            color: [0.75, 0.1, 0.1],
            reflectivity: 0.5,
            motion: Some(Motion { speed_x: 6.0 }),
        });
        self.add(Placed {
            name: "oncoming_car".into(),
            base: [45.0, -3.4, 0.0],
            size: [4.4, 1.8, 1.5],
            yaw: std::f64::consts::PI,
            class: class::CAR,
            color: [0.15, 0.2, 0.7],
            reflectivity: 0.5,
            motion: Some(Motion { speed_x: -9.0 }),
        });
        self.add(Placed {
            name: "pedestrian".into(),
            base: [6.0, 8.8, 0.0],
            size: [0.5, 0.6, 1.75],
            yaw: 0.0,
            class: class::PEDESTRIAN,
            color: [0.85, 0.6, 0.2],
            reflectivity: 0.4,
            motion: Some(Motion { speed_x: 1.4 }),
        });
    }

    /// Cones and a barrier at a work zone on the left edge of the road.
    fn work_zone(&mut self) {
        for i in 0..5 {
            self.add(Placed {
                name: format!("cone_{i}"),
                base: [22.0 + 2.0 * i as f64, 6.6, 0.0],
                size: [0.4, 0.4, 0.7],
                yaw: 0.0,
                class: class::TRAFFIC_CONE,
                color: [1.0, 0.45, 0.05],
                reflectivity: 0.9,
                motion: None,
            });
        }
        self.add(Placed {
            name: "barrier_0".into(),
            base: [34.0, 6.8, 0.0],
            size: [4.0, 0.5, 1.0],
            yaw: 0.0,
            class: class::BARRIER,
            color: [0.8, 0.8, 0.78],
            reflectivity: 0.7,
            motion: None,
        });
    }
}

/// How far the ego travels along the street of [`Scene::street`] (3 s at
/// [`crate::sim::EGO_SPEED`]); a longer drive needs [`Scene::street_for`].
pub const STREET_TRAVEL_M: f64 = 24.0;

impl Scene {
    /// Builds the street from a seed. The ego drives along +x near y = 0.
    pub fn street(seed: u64) -> Self {
        Self::street_for(seed, STREET_TRAVEL_M)
    }

    /// The street of [`Scene::street`] with its rows of buildings, trees and parked cars
    /// as much longer as the ego travels beyond [`STREET_TRAVEL_M`] (`travel_m` metres),
    /// so that a long drive stays in a street; the same scene for any shorter travel.
    pub fn street_for(seed: u64, travel_m: f64) -> Self {
        let mut street = StreetBuilder {
            rng: SplitMix::new(seed),
            boxes: Vec::new(),
            extra_m: (travel_m - STREET_TRAVEL_M).max(0.0),
        };
        for (side, sign) in [("left", 1.0), ("right", -1.0)] {
            street.buildings(side, sign);
            street.trees_and_poles(side, sign);
        }
        street.parked_cars();
        street.traffic();
        street.work_zone();
        Scene {
            boxes: street.boxes,
        }
    }

    /// The box of object id `id` (as [`Hit::object`] gives it), if there is one.
    pub fn object(&self, id: u32) -> Option<&SceneBox> {
        self.boxes.get(usize::try_from(id).ok()?)
    }

    /// Whether object `id` is a box that moves during the drive (`false` for an id
    /// without a box).
    pub fn is_moving(&self, id: u32) -> bool {
        self.object(id).is_some_and(SceneBox::is_moving)
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn a_longer_drive_gets_a_longer_street_and_a_short_one_the_same() {
        let street = Scene::street(7);
        assert_eq!(Scene::street_for(7, 12.0).boxes, street.boxes);
        let long = Scene::street_for(7, STREET_TRAVEL_M + 200.0);
        let reach = |scene: &Scene, prefix: &str| {
            scene
                .boxes
                .iter()
                .filter(|b| b.name.starts_with(prefix))
                .map(|b| b.center.x)
                .fold(f64::MIN, f64::max)
        };
        for row in ["building_left", "tree_right", "parked_car"] {
            assert!(reach(&long, row) > reach(&street, row) + 180.0, "{row}");
        }
    }

    #[test]
    fn rays_hit_ground_boxes_and_sky() {
        let scene = Scene::street(7);
        let origin = Point3::new(0.0, 0.0, 1.8);
        let down = scene
            .cast(&origin, &Vector3::new(0.0, 0.0, -1.0), 0.0, 100.0)
            .unwrap();
        assert!((down.distance - 1.8).abs() < 1e-12);
        assert_eq!(down.class, class::DRIVEABLE_SURFACE);
        assert!(scene.cast(&origin, &Vector3::z(), 0.0, 100.0).is_none());
        // From the sidewalk, looking left at a building's middle hits its facade.
        let building = scene
            .boxes
            .iter()
            .find(|b| b.name.starts_with("building_left"))
            .unwrap();
        let from = Point3::new(building.center.x, 12.5, building.center.z);
        let hit = scene.cast(&from, &Vector3::y(), 0.0, 100.0).unwrap();
        assert_eq!(hit.class, class::MANMADE);
        assert!(hit.point.y > 12.5 && hit.point.y < building.center.y);
        assert!((hit.normal.norm() - 1.0).abs() < 1e-12);
        assert!(
            hit.normal.y < -0.99,
            "facade faces the street: {}",
            hit.normal
        );
    }

    #[test]
    fn box_hit_lies_on_the_box_surface() {
        let b = SceneBox {
            name: "b".into(),
            center: Point3::new(10.0, 0.0, 1.0),
            half: Vector3::new(1.0, 2.0, 1.0),
            yaw: 0.3,
            class: class::CAR,
            color: [1.0; 3],
            reflectivity: 1.0,
            motion: None,
        };
        let scene = Scene { boxes: vec![b] };
        let origin = Point3::new(0.0, 0.0, 1.0);
        let hit = scene
            .cast(&origin, &Vector3::new(1.0, 0.0, 0.0), 0.0, 100.0)
            .unwrap();
        // The near face is at local x = -1: point minus centre, rotated back, has x = -1.
        let rel = hit.point - Point3::new(10.0, 0.0, 1.0);
        let (s, c) = 0.3f64.sin_cos();
        assert!(((c * rel.x + s * rel.y) + 1.0).abs() < 1e-9);
        assert!((hit.normal - Vector3::new(-c, -s, 0.0)).norm() < 1e-12);
    }
}
