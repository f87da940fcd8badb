//! The ROS 2 message definitions as rosbag2 stores them in MCAP files, shared by the
//! pipeline's decoder (`superflow_pipeline::decode::ros2`) and the recording generator
//! (`superflow-recordings`).
//!
//! A rosbag2 MCAP file stores each topic's type as a schema whose encoding is
//! [`SCHEMA_ENCODING`] (`ros2msg`): the type's `.msg` text followed by the texts of all
//! the types it depends on (see [`POINT_CLOUD2_DEFINITION`] and friends). Each message
//! is a CDR payload ([`MESSAGE_ENCODING`], `cdr`): a 4-byte encapsulation header that
//! names the byte order, then the fields in declaration order, each primitive aligned to
//! its own size relative to the start of the body (the byte after the header).
//!
//! This module holds:
//!
//! * serde mirrors of the message types the pipeline reads ([`PointCloud2`],
//!   [`CompressedImage`], [`Image`], [`CameraInfo`], [`TfMessage`]) and the types they
//!   contain, field for field in the order of the ROS 2 definitions, and the
//!   [`Ros2Message`] trait that names a top-level type's schema;
//! * `definitions`: the `ros2msg` schema texts of the top-level types,
//!   byte for byte in the layout rosbag2 writes (the `.msg` texts keep every field and
//!   constant, with shortened comments);
//! * `cdr`: [`encode`] and [`decode`], which add and read the encapsulation header
//!   around `cdr-encoding`, and their [`CdrError`].
//!
//! `uint8[]` fields (`data`) are read and written as one block of bytes, not byte by
//! byte, so a multi-megabyte cloud or image costs one copy.
//!
//! ```
//! use superflow_schemas::ros2::{self, Header, Ros2Time};
//!
//! let header = Header { stamp: Ros2Time { sec: 1, nanosec: 2 }, frame_id: "map".into() };
//! let bytes = ros2::encode(&header)?;
//! assert_eq!(bytes[..4], [0x00, 0x01, 0x00, 0x00]); // CDR_LE
//! assert_eq!(ros2::decode::<Header>(&bytes)?, header);
//! # Ok::<(), ros2::CdrError>(())
//! ```

mod cdr;
#[macro_use]
mod definitions;
#[cfg(test)]
mod tests;

use serde::de::DeserializeOwned;
use serde::{Deserialize, Serialize};

pub use cdr::{CdrError, ENCAPSULATION_HEADER_LEN, decode, encode};
pub use definitions::{
    CAMERA_INFO_DEFINITION, COMPRESSED_IMAGE_DEFINITION, IMAGE_DEFINITION, POINT_CLOUD2_DEFINITION,
    TF_MESSAGE_DEFINITION,
};

use crate::Stamp;

// ---------------------------------------------------------------------------------------
// Names and encodings
// ---------------------------------------------------------------------------------------

/// MCAP schema encoding of rosbag2 schemas: concatenated `.msg` texts.
pub const SCHEMA_ENCODING: &str = "ros2msg";

/// MCAP message encoding of rosbag2 messages: CDR with an encapsulation header.
pub const MESSAGE_ENCODING: &str = "cdr";

/// Schema name of [`PointCloud2`].
pub const POINT_CLOUD2: &str = "sensor_msgs/msg/PointCloud2";

/// Schema name of [`CompressedImage`].
pub const COMPRESSED_IMAGE: &str = "sensor_msgs/msg/CompressedImage";

/// Schema name of [`Image`].
pub const IMAGE: &str = "sensor_msgs/msg/Image";

/// Schema name of [`CameraInfo`].
pub const CAMERA_INFO: &str = "sensor_msgs/msg/CameraInfo";

/// Schema name of [`TfMessage`] (the type of `/tf` and `/tf_static`).
pub const TF_MESSAGE: &str = "tf2_msgs/msg/TFMessage";

// ---------------------------------------------------------------------------------------
// Message types
// ---------------------------------------------------------------------------------------

/// `builtin_interfaces/msg/Time`: a time as seconds and nanoseconds since an epoch.
#[derive(Serialize, Deserialize, Debug, Clone, Copy, PartialEq, Eq, Hash, Default)]
pub struct Ros2Time {
    /// Whole seconds (may be negative).
    pub sec: i32,
    /// Nanoseconds added to `sec`, in `[0, 1e9)` for a well-formed time.
    pub nanosec: u32,
}

impl Ros2Time {
    /// The time as nanoseconds since the epoch (never overflows: `nanosec` is not
    /// required to be below 1e9 here).
    pub fn as_nanos(self) -> i64 {
        i64::from(self.sec) * 1_000_000_000 + i64::from(self.nanosec)
    }

    /// The time `nanos` nanoseconds after the epoch, or `None` when its seconds do not
    /// fit in an `i32`.
    pub fn from_nanos(nanos: i64) -> Option<Self> {
        let sec = i32::try_from(nanos.div_euclid(1_000_000_000)).ok()?;
        let nanosec = u32::try_from(nanos.rem_euclid(1_000_000_000)).ok()?;
        Some(Self { sec, nanosec })
    }

    /// The time as a [`Stamp`].
    pub fn stamp(self) -> Stamp {
        Stamp::from_nanos(self.as_nanos())
    }
}

/// `std_msgs/msg/Header`: acquisition time and coordinate frame of stamped data.
#[derive(Serialize, Deserialize, Debug, Clone, PartialEq, Eq, Hash, Default)]
pub struct Header {
    /// Acquisition time.
    pub stamp: Ros2Time,
    /// Coordinate frame the data is expressed in.
    pub frame_id: String,
}

/// `sensor_msgs/msg/PointField`: one channel of the points of a [`PointCloud2`].
#[derive(Serialize, Deserialize, Debug, Clone, PartialEq, Eq, Hash, Default)]
pub struct PointField {
    /// Channel name (`x`, `y`, `z`, `intensity`, ...).
    pub name: String,
    /// Offset of the channel from the start of a point, in bytes.
    pub offset: u32,
    /// Element type: one of [`PointField::INT8`] ... [`PointField::FLOAT64`].
    pub datatype: u8,
    /// Number of elements of the channel.
    pub count: u32,
}

impl PointField {
    /// `datatype` of an `int8` channel.
    pub const INT8: u8 = 1;
    /// `datatype` of a `uint8` channel.
    pub const UINT8: u8 = 2;
    /// `datatype` of an `int16` channel.
    pub const INT16: u8 = 3;
    /// `datatype` of a `uint16` channel.
    pub const UINT16: u8 = 4;
    /// `datatype` of an `int32` channel.
    pub const INT32: u8 = 5;
    /// `datatype` of a `uint32` channel.
    pub const UINT32: u8 = 6;
    /// `datatype` of a `float32` channel.
    pub const FLOAT32: u8 = 7;
    /// `datatype` of a `float64` channel.
    pub const FLOAT64: u8 = 8;

    /// Size in bytes of one element of `datatype`, or `None` for an unknown datatype.
    pub fn datatype_size(datatype: u8) -> Option<u32> {
        match datatype {
            Self::INT8 | Self::UINT8 => Some(1),
            Self::INT16 | Self::UINT16 => Some(2),
            Self::INT32 | Self::UINT32 | Self::FLOAT32 => Some(4),
            Self::FLOAT64 => Some(8),
            _ => None,
        }
    }
}

/// `sensor_msgs/msg/PointCloud2`: points as a binary blob whose layout `fields` describe.
#[derive(Serialize, Deserialize, Debug, Clone, PartialEq, Default)]
pub struct PointCloud2 {
    /// Acquisition time and frame of the points.
    pub header: Header,
    /// Number of rows (1 for an unordered cloud).
    pub height: u32,
    /// Number of points per row.
    pub width: u32,
    /// Layout of a point in `data`.
    pub fields: Vec<PointField>,
    /// Whether multi-byte values in `data` are big-endian.
    pub is_bigendian: bool,
    /// Length of a point in bytes.
    pub point_step: u32,
    /// Length of a row in bytes.
    pub row_step: u32,
    /// Point data, `row_step * height` bytes.
    #[serde(with = "cdr::octets")]
    pub data: Vec<u8>,
    /// Whether there are no invalid points.
    pub is_dense: bool,
}

/// `sensor_msgs/msg/CompressedImage`: an encoded (JPEG, PNG, ...) image.
#[derive(Serialize, Deserialize, Debug, Clone, PartialEq, Eq, Hash, Default)]
pub struct CompressedImage {
    /// Acquisition time and optical frame of the camera.
    pub header: Header,
    /// Compression format (`jpeg`, `png`, `rgb8; jpeg compressed bgr8`, ...).
    pub format: String,
    /// Compressed image buffer.
    #[serde(with = "cdr::octets")]
    pub data: Vec<u8>,
}

/// `sensor_msgs/msg/Image`: an uncompressed image, (0, 0) at the top-left corner.
#[derive(Serialize, Deserialize, Debug, Clone, PartialEq, Eq, Hash, Default)]
pub struct Image {
    /// Acquisition time and optical frame of the camera.
    pub header: Header,
    /// Number of rows.
    pub height: u32,
    /// Number of columns.
    pub width: u32,
    /// Pixel encoding (`rgb8`, `mono8`, `16UC1`, ...).
    pub encoding: String,
    /// Whether multi-byte pixel values are big-endian (0 or 1).
    pub is_bigendian: u8,
    /// Length of a row in bytes.
    pub step: u32,
    /// Pixel data, `step * height` bytes.
    #[serde(with = "cdr::octets")]
    pub data: Vec<u8>,
}

/// `sensor_msgs/msg/RegionOfInterest`: a rectangular window of an image.
#[derive(Serialize, Deserialize, Debug, Clone, Copy, PartialEq, Eq, Hash, Default)]
pub struct RegionOfInterest {
    /// Leftmost pixel of the window.
    pub x_offset: u32,
    /// Topmost pixel of the window.
    pub y_offset: u32,
    /// Height of the window in pixels.
    pub height: u32,
    /// Width of the window in pixels.
    pub width: u32,
    /// Whether a rectified window should be computed.
    pub do_rectify: bool,
}

/// `sensor_msgs/msg/CameraInfo`: calibration of a camera.
#[derive(Serialize, Deserialize, Debug, Clone, PartialEq, Default)]
pub struct CameraInfo {
    /// Acquisition time and optical frame of the camera.
    pub header: Header,
    /// Image height the camera was calibrated with.
    pub height: u32,
    /// Image width the camera was calibrated with.
    pub width: u32,
    /// Distortion model of `d` (`plumb_bob`, `rational_polynomial`, `equidistant`, ...).
    pub distortion_model: String,
    /// Distortion parameters; their number depends on the model.
    pub d: Vec<f64>,
    /// Intrinsic matrix of the raw (distorted) image, 3x3 row-major.
    pub k: [f64; 9],
    /// Rectification matrix (stereo cameras), 3x3 row-major.
    pub r: [f64; 9],
    /// Projection matrix of the rectified image, 3x4 row-major.
    pub p: [f64; 12],
    /// Horizontal binning (0 means 1).
    pub binning_x: u32,
    /// Vertical binning (0 means 1).
    pub binning_y: u32,
    /// Captured window of the full-resolution sensor (all 0 means the full image).
    pub roi: RegionOfInterest,
}

/// `geometry_msgs/msg/Vector3`: a vector in free space.
#[derive(Serialize, Deserialize, Debug, Clone, Copy, PartialEq, Default)]
pub struct Vector3 {
    /// X component.
    pub x: f64,
    /// Y component.
    pub y: f64,
    /// Z component.
    pub z: f64,
}

/// `geometry_msgs/msg/Quaternion`: an orientation. The default is the identity, as in
/// ROS 2 (`w` defaults to 1).
#[derive(Serialize, Deserialize, Debug, Clone, Copy, PartialEq)]
pub struct Quaternion {
    /// X component.
    pub x: f64,
    /// Y component.
    pub y: f64,
    /// Z component.
    pub z: f64,
    /// W (scalar) component.
    pub w: f64,
}

impl Default for Quaternion {
    fn default() -> Self {
        Self {
            x: 0.0,
            y: 0.0,
            z: 0.0,
            w: 1.0,
        }
    }
}

/// `geometry_msgs/msg/Transform`: a rigid transform between two frames (the default is
/// the identity).
#[derive(Serialize, Deserialize, Debug, Clone, Copy, PartialEq, Default)]
pub struct Transform {
    /// Translation.
    pub translation: Vector3,
    /// Rotation.
    pub rotation: Quaternion,
}

/// `geometry_msgs/msg/TransformStamped`: the pose of `child_frame_id` in
/// `header.frame_id` at `header.stamp`.
#[derive(Serialize, Deserialize, Debug, Clone, PartialEq, Default)]
pub struct TransformStamped {
    /// Time of the transform and parent frame.
    pub header: Header,
    /// Child frame.
    pub child_frame_id: String,
    /// Transform from child frame coordinates to parent frame coordinates.
    pub transform: Transform,
}

/// `tf2_msgs/msg/TFMessage`: a batch of transforms (`/tf`, `/tf_static`).
#[derive(Serialize, Deserialize, Debug, Clone, PartialEq, Default)]
pub struct TfMessage {
    /// The transforms.
    pub transforms: Vec<TransformStamped>,
}

/// A top-level message type: one that is a channel's schema in a rosbag2 MCAP file.
pub trait Ros2Message: Serialize + DeserializeOwned {
    /// Schema name (`pkg/msg/Type`).
    const SCHEMA_NAME: &'static str;
    /// Schema data in the [`SCHEMA_ENCODING`] (`ros2msg`) format.
    const SCHEMA_DEFINITION: &'static str;
}

impl Ros2Message for PointCloud2 {
    const SCHEMA_NAME: &'static str = POINT_CLOUD2;
    const SCHEMA_DEFINITION: &'static str = POINT_CLOUD2_DEFINITION;
}

impl Ros2Message for CompressedImage {
    const SCHEMA_NAME: &'static str = COMPRESSED_IMAGE;
    const SCHEMA_DEFINITION: &'static str = COMPRESSED_IMAGE_DEFINITION;
}

impl Ros2Message for Image {
    const SCHEMA_NAME: &'static str = IMAGE;
    const SCHEMA_DEFINITION: &'static str = IMAGE_DEFINITION;
}

impl Ros2Message for CameraInfo {
    const SCHEMA_NAME: &'static str = CAMERA_INFO;
    const SCHEMA_DEFINITION: &'static str = CAMERA_INFO_DEFINITION;
}

impl Ros2Message for TfMessage {
    const SCHEMA_NAME: &'static str = TF_MESSAGE;
    const SCHEMA_DEFINITION: &'static str = TF_MESSAGE_DEFINITION;
}
