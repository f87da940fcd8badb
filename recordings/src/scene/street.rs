//! The street the sample drives pass through: road and sidewalks, then rows of
//! buildings, trees and parked cars, traffic and a work zone, laid out from one seed
//! ([`Scene::street`]).

use super::classes::class;
use super::objects::{Motion, Scene, SceneBox};
use super::rng::SplitMix;
use nalgebra::{Point3, Vector3};

/// Half-width of the road (|y| below is road), in metres.
pub const ROAD_HALF_WIDTH: f64 = 7.5;
/// Outer edge of the sidewalks.
pub const SIDEWALK_EDGE: f64 = 11.0;

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
}
