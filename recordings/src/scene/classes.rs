//! The semantic classes of the scene's boxes and ground: [`CLASSES`] by number, and the
//! numbers the generator uses by name ([`class`]).

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
