//! The contract between `superflow-pipeline` and its trainers, in the order data flows:
//!
//! * [`ros2`]: the ROS 2 message definitions as rosbag2 stores them (serde mirrors,
//!   `ros2msg` schema texts, the CDR codec), shared by the pipeline's decoder and the
//!   recording generator. (Foxglove's messages come from the `foxglove` crate.)
//! * [`sensor`]: the sensor data model the pipeline decodes recordings into —
//!   [`sensor::PointCloud`], [`sensor::Image`], [`sensor::CameraCalibration`] with its
//!   [`sensor::Distortion`], and [`sensor::StampedTransform`] — stamped with
//!   nanosecond [`time::Stamp`]s. Transforms are named `a_from_b`.
//! * [`batch`]: the batch on the wire. [`batch::Section`] is the one table of a SuperFlow
//!   batch's sections (name, dtype, symbolic shape, meaning; `BATCH_FORMAT.md` renders
//!   it). A fixed `#[repr(C)]` [`batch::BatchHeader`] travels as the iceoryx2 user
//!   header; the payload is a byte slice of aligned, typed sections listed in the
//!   header's section table. The producer plans a [`batch::BatchLayout`], loans that many
//!   bytes and fills each section in place with a [`batch::BatchWriter`]; a consumer
//!   reads through a validated [`batch::BatchView`]. `BATCH_FORMAT.md` documents the
//!   bytes for readers in other languages.
//! * [`service`]: the iceoryx2 service names (`superflow/<run>/batches`, ...), their QoS
//!   and [`service::ServiceSetupError`].
//!
//! ```
//! use superflow_schemas::batch::{BatchLayout, BatchMeta, BatchView, BatchWriter};
//!
//! let mut layout = BatchLayout::new();
//! let xyz = layout.add::<f32>("points_xyz", &[2, 3])?;
//! let header = layout.header(&BatchMeta { run: "demo".into(), epoch: 1, step: 7, ..Default::default() })?;
//! let mut storage = vec![0u64; layout.payload_len().div_ceil(8)];
//! let payload: &mut [u8] = bytemuck::cast_slice_mut(&mut storage);
//! BatchWriter::new(&layout, payload)?.write(xyz, &[0.0f32, 1.0, 2.0, 3.0, 4.0, 5.0])?;
//!
//! let view = BatchView::new(&header, payload)?;
//! assert_eq!(view.meta().step, 7);
//! assert_eq!(view.get::<f32>("points_xyz")?.data[4], 4.0);
//! # Ok::<(), superflow_schemas::batch::BatchError>(())
//! ```

pub mod batch;
pub mod ros2;
pub mod sensor;
pub mod service;
pub mod time;

pub use time::Stamp;
