//! `superflow-pipeline`: reads recorded drives (MCAP) and turns them into SuperFlow
//! training batches in shared memory. The modules, in the order data flows through them
//! (each uses only the ones above it):
//!
//! 1. [`source`]: one MCAP file — [`source::McapFile`] scans it once (summary and chunk
//!    index when present, a linear scan of a damaged file otherwise, every loss a
//!    [`source::Damage`]) and reads any message back through a small
//!    [`source::ChunkCache`].
//! 2. [`decode`]: the wire formats — [`decode::schema_kind`] tells each channel's
//!    [`decode::Dialect`] and [`decode::SchemaKind`] from its schema; [`decode::points`],
//!    [`decode::image`], [`decode::ros2`] and [`decode::foxglove`] turn messages into
//!    the sensor model of `superflow-schemas` (point clouds, images, calibrations,
//!    transforms).
//! 3. [`drive`]: a drive in time — [`drive::Dataset`] opens the inputs (files, rosbag2
//!    directories, sidecars), finds the channels ([`drive::IngestConfig`] overrides),
//!    indexes every [`drive::Drive`] and keeps its [`drive::TransformTree`], which
//!    answers `a_from_b` at any stamp; [`drive::DriveLabels`] reads the per-point
//!    semantic labels of any sweep (a cloud field or a `<drive>.labels.mcap` sidecar),
//!    for a probe — samples never read them.
//! 4. [`sample`]: the recipe ([`sample::SampleConfig`]) — a [`sample::Plan`] of
//!    keyframes and temporal triplets, and the [`sample::SampleBuilder`] that makes one
//!    [`sample::Sample`]: dense clouds, projection and pairings, images, superpixels,
//!    augmentation, voxels and sparse-convolution maps.
//! 5. [`batch`]: samples → the sections of one batch ([`batch::BatchPlan`]), written in
//!    place through `superflow_schemas::batch`, whose section table is the contract.
//! 6. [`publish`]: the service — [`publish::serve`] builds batches ahead on a producer
//!    thread and publishes them over iceoryx2 by the [`publish::Schedule`] (epochs,
//!    shards, hosts), with backpressure, resume ([`publish`]'s control server) and
//!    [`publish::Metrics`].
//!
//! Beside them: [`config::PipelineConfig`] (`pipeline.toml`: `[ingest]`, `[sample]`,
//! `[service]`, `[labels]`, `[[dataset]]`; a setting out of range is a
//! `superflow_common::InvalidSetting`, the trainer's too), [`inspect`] (what
//! `superflow-pipeline inspect` reports about a drive), [`fleet`] (a dataset's groups
//! and rigs, as `index`, `inspect` and the service report them) and [`view`] (samples as
//! MCAP files that Foxglove opens).
//!
//! For example, the transform tree interpolates between recorded poses:
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
pub mod fleet;
pub mod inspect;
pub mod publish;
pub mod sample;
pub mod source;
#[cfg(test)]
mod test_rng;
pub mod view;
