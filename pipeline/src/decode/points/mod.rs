//! Point clouds as recorders write them — a packed array of points whose layout a list
//! of named fields describes — decoded into the sensor model's [`PointCloud`].
//!
//! # Messages
//!
//! | message | entry point | layout | endianness |
//! |---|---|---|---|
//! | ROS 2 `sensor_msgs/msg/PointCloud2` | [`decode_ros2`] | `fields` (`name`, `offset`, `datatype`, `count`), `point_step`, `row_step`, `width × height` | `is_bigendian` |
//! | `foxglove.PointCloud` | [`decode_foxglove`] | `fields` (`name`, `offset`, `type`), `point_stride`; the number of points is `data.len() / point_stride` | always little-endian |
//! | either, straight from an MCAP message | [`decode_message`] | by the channel's schema | |
//!
//! Both go through one core: the fields are parsed once per message into a
//! [`PointLayout`] (offset, [`NumericType`] and [`Endianness`] of each field that is used),
//! then every point is read at those fixed offsets with `from_le_bytes`/`from_be_bytes`.
//! Nothing is looked up by name and nothing is allocated per point.
//!
//! The two numbering schemes of the element types differ and are mapped separately:
//!
//! | type | ROS `PointField.datatype` | Foxglove `NumericType` |
//! |---|---|---|
//! | int8 / uint8 | 1 / 2 | 2 / 1 |
//! | int16 / uint16 | 3 / 4 | 4 / 3 |
//! | int32 / uint32 | 5 / 6 | 6 / 5 |
//! | float32 / float64 | 7 / 8 | 7 / 8 |
//!
//! # Fields
//!
//! | attribute | field names (first match in this order) | types | result |
//! |---|---|---|---|
//! | position | `x`, `y`, `z` (all three required, `count` 1) | any | `xyz` as `f32` |
//! | intensity | `intensity`, `i`; `reflectivity` only when neither exists | any | `intensity` as `f32`, the value as stored (UINT8 `0..255`, KITTI `0..1`, ...); 0 with [`DecodedCloud::has_intensity`] `false` when absent |
//! | ring | `ring`, `channel`, `laser_id`, `line` | any, FLOAT32 included (nuScenes) | `ring` as `u16`; a value that is not an integer in `0..=65535` is an error ([`PointsError::BadRing`]) |
//! | per-point time | `time`, `t`, `time_offset`, `offset_time`, `timestamp` | see below | `time_offset_secs`, seconds relative to the message stamp |
//! | semantic label (only through [`CloudOptions::label`]) | the configured name, else `label`, `class`, `semantic`, `semantic_label`, `lidarseg` — **regardless of case** | any integer type; FLOAT32 / FLOAT64 holding integers | `label` as `u32` raw ids, masked if configured; a value that is not a non-negative integer is an error ([`PointsError::BadLabel`]); see [`LabelFieldSpec`] |
//!
//! Names are matched exactly (case-sensitive); the first field with a name wins. Fields
//! that are not used (`ambient`, `range`, `return_type`, padding, ...) are not checked:
//! an unknown datatype or a bad offset there does not matter. A used field must have
//! `count` 1, a known datatype, and lie inside the point (`offset + size <= point_step`).
//!
//! # Real layouts (each has a test)
//!
//! | source | fields (offset) | point_step |
//! |---|---|---|
//! | velodyne_pointcloud `PointcloudXYZIRT` (packed) | x0 y4 z8 intensity12 (FLOAT32), ring16 (UINT16), time18 (FLOAT32 s) | 22 |
//! | PCL `PointXYZIRT` via `pcl::toROSMsg` (aligned) | x0 y4 z8, intensity16, ring20 (UINT16), time24 | 32 |
//! | ouster-ros `Point` | x0 y4 z8, intensity16 (FLOAT32), t20 (UINT32 ns), reflectivity24, ring26 (UINT16), ambient28, range32 | 48 |
//! | KITTI (kitti2mcap) | x0 y4 z8 intensity12 (FLOAT32) | 16 |
//! | Hesai (PCL-aligned `PointXYZIT`-style; offsets vary by driver) | x0 y4 z8, intensity16 (FLOAT32), timestamp24 (FLOAT64 absolute s), ring32 (UINT16) | 48 |
//! | Livox (PointCloud2 output) | x y z intensity (FLOAT32), tag, line (UINT8), timestamp (FLOAT64 absolute) or offset_time (UINT32 ns) | — |
//! | Autoware `PointXYZIRC` | x0 y4 z8 (FLOAT32), intensity12 (UINT8), return_type13, channel14 (UINT16) | 16 |
//! | nuScenes `foxglove.PointCloud` | x0 y4 z8 intensity12 ring16, all FLOAT32 | 20 |
//!
//! Labels are read only when [`CloudOptions::label`] asks for them, so a caller that
//! does not want them pays nothing; a label-only cloud (the parallel cloud of a
//! `<drive>.labels.mcap` sidecar, without `x`, `y`, `z`) decodes with
//! [`decode_labels_message`] into a [`LabelCloud`] of every point, and
//! [`CloudOptions::kept_indices`] gives the message index of each point a LiDAR cloud
//! kept, to carry such labels through the dropping of invalid points.
//!
//! # Per-point time
//!
//! `PointCloud::time_offset_secs` is each point's time **relative to the message stamp**,
//! in seconds. Recorders disagree on the unit and reference of their time field, so,
//! unless the caller passes a [`TimeFieldSpec`], they are inferred:
//!
//! | field type | values | unit | reference | typical source |
//! |---|---|---|---|---|
//! | integer (any width) | — | nanoseconds | relative | ouster `t` (UINT32), livox `offset_time` (UINT32) |
//! | FLOAT32 / FLOAT64 | max \|v\| ≤ 1e8 | seconds | relative | velodyne / PCL `time` (FLOAT32), `time_offset` |
//! | FLOAT32 / FLOAT64 | 1e8 < max \|v\| ≤ 1e14 | seconds | absolute | hesai / livox `timestamp` (FLOAT64 s since the epoch) |
//! | FLOAT32 / FLOAT64 | 1e14 < max \|v\| ≤ 1e17 | microseconds | absolute | absolute µs stamps |
//! | FLOAT32 / FLOAT64 | max \|v\| > 1e17 | nanoseconds | absolute | livox_ros_driver2 `timestamp` (FLOAT64 ns since the epoch) |
//!
//! `max |v|` is taken over the kept points (those with a finite position), so the zero
//! or garbage times of no-return points do not flip the decision. It costs nothing for
//! relative clouds: the field is read as relative seconds while the maximum is tracked,
//! and only a cloud that turns out absolute has its time column read a second time. A
//! relative field cannot reach 1e8 s (three years); an absolute one is at least 1e8 s
//! past the epoch for any date after 1973. A float field that holds time since boot
//! (< 1e8 s) is indistinguishable from a relative one: pass a [`TimeFieldSpec`] for such
//! a recorder.
//!
//! * **Relative** fields are taken as offsets from the message stamp as they are:
//!   `offset = value / units_per_second`. They are documented as relative to the *scan
//!   start* (velodyne, ouster, livox), which equals the stamp when the driver stamps the
//!   first packet (the velodyne driver's `timestamp_first_packet: true`, ouster, livox).
//!   When the velodyne driver stamps the **last** packet instead, the true offsets are
//!   `value − sweep duration`; the message does not say which, so the field value is kept
//!   and a configuration must correct it (a `TimeFieldSpec` cannot express a shift).
//! * **Absolute** fields are converted to the offset from the stamp:
//!   `offset = value − stamp`, computed without losing the sub-microsecond part of the
//!   stamp (the integral part of the stamp in the field's unit is subtracted first).
//!   The precision is then that of the stored value (a FLOAT64 of seconds since the epoch
//!   resolves about 0.24 µs).
//!
//! A time that is not finite on a kept point is an error ([`PointsError::BadTime`]); the
//! resolved interpretation is reported in [`DecodedCloud::time_field`].
//!
//! # Invalid points, organized clouds
//!
//! Points with a non-finite `x`, `y` or `z` (organized clouds write NaN for "no return";
//! a FLOAT64 coordinate beyond the `f32` range becomes infinite) are dropped and counted
//! in [`DecodedCloud::dropped_non_finite`]; the remaining points keep their order (row by
//! row). ROS rows are `row_step` bytes apart and may be padded after their
//! `width × point_step` bytes of points; `data` must hold `row_step × height` bytes (the
//! padding of the last row may be left out; `row_step` 0 means unpadded rows).
//!
//! # Foxglove pose
//!
//! `foxglove.PointCloud.pose` is "the origin of the point cloud relative to the frame of
//! reference": the points are stored in a cloud frame and `frame_id_from_cloud = pose`.
//! When it is set and not the identity, every decoded point becomes `pose * point`
//! (rotation then translation, in `f64`), so the result is expressed in `frame_id` like
//! every other cloud. Absent position = zero, absent orientation = identity; a
//! non-finite pose or a zero quaternion is an error. nuScenes leaves the pose unset.
//!
//! # Errors
//!
//! Every [`PointsError`] about a message names its frame id and stamp (the caller adds the
//! file and topic). Malformed input never panics: sizes are checked against the data
//! before anything is read, and allocation is bounded by the data's size.
//!
//! [`PointCloud`]: superflow_schemas::sensor::PointCloud

mod cloud;
mod dialect;
mod error;
mod field;
mod grid;
mod label;
mod label_cloud;
mod layout;
mod read;
#[cfg(test)]
mod tests;
mod time;

pub use cloud::DecodedCloud;
pub use dialect::{
    CloudOptions, decode_foxglove, decode_foxglove_with, decode_message, decode_message_with,
    decode_ros2, decode_ros2_with,
};
pub use error::PointsError;
pub use field::{Endianness, FieldPlan, NamedField, NumericType};
pub use label::{LABEL_NAMES, LabelFieldSpec};
pub use label_cloud::{
    LabelCloud, decode_labels_foxglove, decode_labels_message, decode_labels_ros2, field_names,
    find_label_field,
};
pub use layout::PointLayout;
pub use time::{TimeFieldSpec, TimeReference, TimeUnit};
