//! `superflow-pipeline`: reads recorded drives (MCAP) and turns them into SuperFlow
//! training batches.
//!
//! * [`decode`]: the message types of each recording dialect (Foxglove protobuf, ROS 2
//!   CDR) and their conversion into the sensor model of `superflow-schemas`.
//! * [`drive`]: a drive in time — the [`drive::TransformTree`] answers `a_from_b` at any
//!   stamp by interpolating the recorded transforms.
//!
//! ```
//! use superflow_pipeline::drive::TransformTree;
//! use superflow_schemas::{Stamp, sensor::StampedTransform};
//! use nalgebra::{Isometry3, Vector3};
//!
//! let mut tree = TransformTree::new(0);
//! for (t, x) in [(0, 0.0), (1_000_000_000, 8.0)] {
//!     tree.insert(StampedTransform {
//!         stamp: Stamp::from_nanos(t),
//!         parent_frame: "map".into(),
//!         child_frame: "base_link".into(),
//!         parent_from_child: Isometry3::translation(x, 0.0, 0.0),
//!         is_static: false,
//!     })?;
//! }
//! let map_from_ego = tree.lookup("map", "base_link", Stamp::from_nanos(250_000_000))?;
//! assert_eq!(map_from_ego.translation.vector, Vector3::new(2.0, 0.0, 0.0));
//! # Ok::<(), superflow_pipeline::drive::TfError>(())
//! ```

pub mod batch;
pub mod config;
pub mod decode;
pub mod drive;
pub mod inspect;
pub mod invalid;
pub mod publish;
pub mod sample;
pub mod source;
#[cfg(test)]
mod test_rng;
