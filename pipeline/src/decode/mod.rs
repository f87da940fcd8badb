//! Wire formats of recorded drives: the message types of each dialect, and their
//! conversion into the sensor model of `superflow-schemas`.
//!
//! * [`ros2`]: ROS 2 messages (`ros2msg` schemas, CDR payloads), as rosbag2 writes them.
//! * [`foxglove`]: Foxglove protobuf messages (`foxglove.PointCloud`, ...), as the
//!   nuScenes converter writes them.
//! * [`schema`]: which sensor a channel carries in which dialect ([`schema_kind`]), from
//!   its schema name and message encoding.
//! * [`points`] and [`image`]: point clouds and camera images of either dialect, decoded
//!   into the sensor model.
//!
//! Conversions check what the sensor model needs (finite numbers, unit quaternions,
//! a usable calibration) and report a [`DecodeError`] naming the frame and stamp.

mod calibration;
mod context;
mod error;
pub mod foxglove;
pub mod image;
pub mod points;
pub mod ros2;
pub mod schema;
mod transform;

pub use error::DecodeError;
pub use schema::{Dialect, SchemaKind, schema_kind};
