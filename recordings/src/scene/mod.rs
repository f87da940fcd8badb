//! A small procedural street: ground regions, buildings, trees, cones, parked and moving
//! cars and a pedestrian, all boxes, with semantic classes and colours; exact ray casting.
//!
//! By concern: `objects` (boxes, their motion, a ray's hit), `classes` (the semantic
//! classes), `street` (the layout drawn from a seed), `rng` (the random stream it is drawn
//! from) and `cast` (ray casting into a scene, and the boxes' poses at one instant).

mod cast;
mod classes;
mod objects;
mod rng;
mod street;

pub use cast::{BoxPose, Snapshot};
pub use classes::{CLASSES, class};
pub use objects::{Hit, Motion, Scene, SceneBox};
pub use rng::SplitMix;
pub use street::{ROAD_HALF_WIDTH, SIDEWALK_EDGE, STREET_TRAVEL_M};

#[cfg(test)]
mod tests;
