//! ROS 2 messages as rosbag2 records them in MCAP files.
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
//!   contain, field for field in the order of the ROS 2 definitions;
//! * the schema names and `ros2msg` schema texts of the top-level types, byte for byte
//!   in the layout rosbag2 writes (the `.msg` texts keep every field and constant, with
//!   shortened comments);
//! * [`encode`] and [`decode`], which add and read the encapsulation header around
//!   `cdr-encoding`.
//!
//! `uint8[]` fields (`data`) are read and written as one block of bytes, not byte by
//! byte, so a multi-megabyte cloud or image costs one copy.

use std::any::type_name;
use std::fmt;

use byteorder::{BigEndian, LittleEndian};
use serde::de::{DeserializeOwned, SeqAccess, Visitor};
use serde::{Deserialize, Deserializer, Serialize, Serializer};

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

/// Length of the CDR encapsulation header that starts every payload.
pub const ENCAPSULATION_HEADER_LEN: usize = 4;

/// Representation identifier of big-endian plain CDR (`CDR_BE`).
const CDR_BE: [u8; 2] = [0x00, 0x00];

/// Representation identifier of little-endian plain CDR (`CDR_LE`).
const CDR_LE: [u8; 2] = [0x00, 0x01];

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
    #[serde(with = "octets")]
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
    #[serde(with = "octets")]
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
    #[serde(with = "octets")]
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

/// `uint8[]` fields as a CDR `sequence<octet>` read and written in one block.
///
/// `Vec<u8>`'s own serde impls go through `serialize_seq`/`deserialize_seq`, one call
/// (and one bounds check and push) per byte. `cdr-encoding` implements
/// `serialize_bytes` and `deserialize_byte_buf` as the same wire format (a `u32` count
/// aligned to 4, then the bytes), but as a single copy.
mod octets {
    use super::{Deserializer, SeqAccess, Serializer, Visitor, fmt};

    /// Writes `bytes` as a length-prefixed octet sequence.
    pub(super) fn serialize<S: Serializer>(bytes: &[u8], serializer: S) -> Result<S::Ok, S::Error> {
        if u32::try_from(bytes.len()).is_err() {
            return Err(serde::ser::Error::custom(format_args!(
                "a uint8[] of {} bytes does not fit a CDR sequence (u32 length)",
                bytes.len()
            )));
        }
        serializer.serialize_bytes(bytes)
    }

    /// Reads a length-prefixed octet sequence.
    pub(super) fn deserialize<'de, D: Deserializer<'de>>(
        deserializer: D,
    ) -> Result<Vec<u8>, D::Error> {
        deserializer.deserialize_byte_buf(OctetsVisitor)
    }

    /// Accepts bytes in any of the forms serde formats hand them over.
    #[derive(Debug)]
    struct OctetsVisitor;

    impl<'de> Visitor<'de> for OctetsVisitor {
        type Value = Vec<u8>;

        fn expecting(&self, formatter: &mut fmt::Formatter<'_>) -> fmt::Result {
            formatter.write_str("a sequence of octets")
        }

        fn visit_bytes<E: serde::de::Error>(self, v: &[u8]) -> Result<Self::Value, E> {
            Ok(v.to_vec())
        }

        fn visit_byte_buf<E: serde::de::Error>(self, v: Vec<u8>) -> Result<Self::Value, E> {
            Ok(v)
        }

        // Self-describing formats (JSON, ...) may present bytes as a sequence of numbers.
        fn visit_seq<A: SeqAccess<'de>>(self, mut seq: A) -> Result<Self::Value, A::Error> {
            // The hint comes from the input: never trust it for more than a small buffer.
            let mut out = Vec::with_capacity(seq.size_hint().unwrap_or(0).min(1 << 16));
            while let Some(byte) = seq.next_element::<u8>()? {
                out.push(byte);
            }
            Ok(out)
        }
    }
}

// ---------------------------------------------------------------------------------------
// Schema texts
// ---------------------------------------------------------------------------------------
//
// rosbag2 (`LocalMessageDefinitionSource::get_full_text`) writes the root type's `.msg`
// file, then for each dependency not written yet, depth first and in the sorted order of
// the type names as they appear in the field lines (a bare `Type` gets the package of
// the file it is used in): "\n", 80 '=', "\n", "MSG: pkg/Type\n" and the dependency's
// file. Every file ends with a newline, so a blank line precedes each separator.

/// The `.msg` text of `builtin_interfaces/msg/Time`.
macro_rules! time_msg {
    () => {
        concat!(
            "# Time since an epoch, in whole seconds plus nanoseconds.\n",
            "\n",
            "# The seconds component, valid over all int32 values.\n",
            "int32 sec\n",
            "\n",
            "# The nanoseconds component, in [0, 1e9), added to the seconds component.\n",
            "uint32 nanosec\n",
        )
    };
}

/// The `.msg` text of `std_msgs/msg/Header`.
macro_rules! header_msg {
    () => {
        concat!(
            "# Standard metadata for stamped data in a particular coordinate frame.\n",
            "\n",
            "# Timestamp, as seconds and nanoseconds.\n",
            "builtin_interfaces/Time stamp\n",
            "\n",
            "# Coordinate frame this data is associated with.\n",
            "string frame_id\n",
        )
    };
}

/// The `.msg` text of `sensor_msgs/msg/PointField`.
macro_rules! point_field_msg {
    () => {
        concat!(
            "# Describes one channel of the points of a PointCloud2.\n",
            "\n",
            "uint8 INT8    = 1\n",
            "uint8 UINT8   = 2\n",
            "uint8 INT16   = 3\n",
            "uint8 UINT16  = 4\n",
            "uint8 INT32   = 5\n",
            "uint8 UINT32  = 6\n",
            "uint8 FLOAT32 = 7\n",
            "uint8 FLOAT64 = 8\n",
            "\n",
            "# Common names are x, y, z, intensity, rgb, rgba.\n",
            "string name      # Name of field\n",
            "uint32 offset    # Offset from start of point struct\n",
            "uint8  datatype  # Datatype enumeration, see above\n",
            "uint32 count     # How many elements in the field\n",
        )
    };
}

/// The `.msg` text of `sensor_msgs/msg/PointCloud2`.
macro_rules! point_cloud2_msg {
    () => {
        concat!(
            "# A collection of N-dimensional points stored as a binary blob whose\n",
            "# layout is described by the contents of the \"fields\" array.\n",
            "\n",
            "# Time of sensor data acquisition, and the coordinate frame of the points.\n",
            "std_msgs/Header header\n",
            "\n",
            "# 2D structure of the point cloud. An unordered cloud has height 1.\n",
            "uint32 height\n",
            "uint32 width\n",
            "\n",
            "# Describes the channels and their layout in the binary data blob.\n",
            "PointField[] fields\n",
            "\n",
            "bool    is_bigendian # Is this data bigendian?\n",
            "uint32  point_step   # Length of a point in bytes\n",
            "uint32  row_step     # Length of a row in bytes\n",
            "uint8[] data         # Actual point data, size is (row_step*height)\n",
            "\n",
            "bool is_dense        # True if there are no invalid points\n",
        )
    };
}

/// The `.msg` text of `sensor_msgs/msg/CompressedImage`.
macro_rules! compressed_image_msg {
    () => {
        concat!(
            "# A compressed image.\n",
            "\n",
            "std_msgs/Header header # Acquisition time, optical frame of the camera\n",
            "\n",
            "string format         # Format of the data (jpeg, png, ...)\n",
            "\n",
            "uint8[] data          # Compressed image buffer\n",
        )
    };
}

/// The `.msg` text of `sensor_msgs/msg/Image`.
macro_rules! image_msg {
    () => {
        concat!(
            "# An uncompressed image; (0, 0) is at the top-left corner.\n",
            "\n",
            "std_msgs/Header header # Acquisition time, optical frame of the camera\n",
            "\n",
            "uint32 height         # image height, that is, number of rows\n",
            "uint32 width          # image width, that is, number of columns\n",
            "\n",
            "string encoding       # Encoding of pixels (rgb8, mono8, 16UC1, ...)\n",
            "\n",
            "uint8 is_bigendian    # is this data bigendian?\n",
            "uint32 step           # Full row length in bytes\n",
            "uint8[] data          # actual matrix data, size is (step * rows)\n",
        )
    };
}

/// The `.msg` text of `sensor_msgs/msg/RegionOfInterest`.
macro_rules! region_of_interest_msg {
    () => {
        concat!(
            "# A subwindow of an image.\n",
            "\n",
            "uint32 x_offset  # Leftmost pixel of the ROI\n",
            "uint32 y_offset  # Topmost pixel of the ROI\n",
            "uint32 height    # Height of ROI\n",
            "uint32 width     # Width of ROI\n",
            "\n",
            "# True if a distinct rectified ROI should be calculated from the raw ROI.\n",
            "bool do_rectify\n",
        )
    };
}

/// The `.msg` text of `sensor_msgs/msg/CameraInfo`.
macro_rules! camera_info_msg {
    () => {
        concat!(
            "# Meta information (calibration) of a camera.\n",
            "\n",
            "# Time of image acquisition, optical frame of the camera.\n",
            "std_msgs/Header header\n",
            "\n",
            "# The image dimensions with which the camera was calibrated.\n",
            "uint32 height\n",
            "uint32 width\n",
            "\n",
            "# The distortion model used (plumb_bob, rational_polynomial, ...).\n",
            "string distortion_model\n",
            "\n",
            "# The distortion parameters, size depending on the distortion model.\n",
            "float64[] d\n",
            "\n",
            "# Intrinsic camera matrix for the raw (distorted) images.\n",
            "float64[9] k # 3x3 row-major matrix\n",
            "\n",
            "# Rectification matrix (stereo cameras only).\n",
            "float64[9] r # 3x3 row-major matrix\n",
            "\n",
            "# Projection/camera matrix of the rectified image.\n",
            "float64[12] p # 3x4 row-major matrix\n",
            "\n",
            "# Binning; 0 is considered the same as 1 (no subsampling).\n",
            "uint32 binning_x\n",
            "uint32 binning_y\n",
            "\n",
            "# Region of interest; all 0 is considered the full resolution.\n",
            "RegionOfInterest roi\n",
        )
    };
}

/// The `.msg` text of `geometry_msgs/msg/Vector3`.
macro_rules! vector3_msg {
    () => {
        concat!(
            "# This represents a vector in free space.\n",
            "\n",
            "float64 x\n",
            "float64 y\n",
            "float64 z\n",
        )
    };
}

/// The `.msg` text of `geometry_msgs/msg/Quaternion`.
macro_rules! quaternion_msg {
    () => {
        concat!(
            "# This represents an orientation in free space in quaternion form.\n",
            "\n",
            "float64 x 0\n",
            "float64 y 0\n",
            "float64 z 0\n",
            "float64 w 1\n",
        )
    };
}

/// The `.msg` text of `geometry_msgs/msg/Transform`.
macro_rules! transform_msg {
    () => {
        concat!(
            "# This represents the transform between two coordinate frames in free space.\n",
            "\n",
            "Vector3 translation\n",
            "Quaternion rotation\n",
        )
    };
}

/// The `.msg` text of `geometry_msgs/msg/TransformStamped`.
macro_rules! transform_stamped_msg {
    () => {
        concat!(
            "# The transform from coordinate frame child_frame_id to header.frame_id,\n",
            "# valid at header.stamp.\n",
            "\n",
            "# The frame id in the header is used as the reference frame of this transform.\n",
            "std_msgs/Header header\n",
            "\n",
            "# The frame id of the child frame to which this transform points.\n",
            "string child_frame_id\n",
            "\n",
            "# Translation and rotation in 3-dimensions of child_frame_id from header.frame_id.\n",
            "Transform transform\n",
        )
    };
}

/// The `.msg` text of `tf2_msgs/msg/TFMessage`.
macro_rules! tf_message_msg {
    () => {
        "geometry_msgs/TransformStamped[] transforms\n"
    };
}

/// The two-line delimiter rosbag2 writes before a dependency, preceded by the newline
/// rosbag2 adds after the previous text.
macro_rules! dependency {
    ($name:literal, $text:expr) => {
        concat!(
            "\n",
            "================================================================================\n",
            "MSG: ",
            $name,
            "\n",
            $text,
        )
    };
}

/// `ros2msg` schema data of `sensor_msgs/msg/PointCloud2`, as rosbag2 writes it.
pub const POINT_CLOUD2_DEFINITION: &str = concat!(
    point_cloud2_msg!(),
    dependency!("sensor_msgs/PointField", point_field_msg!()),
    dependency!("std_msgs/Header", header_msg!()),
    dependency!("builtin_interfaces/Time", time_msg!()),
);

/// `ros2msg` schema data of `sensor_msgs/msg/CompressedImage`, as rosbag2 writes it.
pub const COMPRESSED_IMAGE_DEFINITION: &str = concat!(
    compressed_image_msg!(),
    dependency!("std_msgs/Header", header_msg!()),
    dependency!("builtin_interfaces/Time", time_msg!()),
);

/// `ros2msg` schema data of `sensor_msgs/msg/Image`, as rosbag2 writes it.
pub const IMAGE_DEFINITION: &str = concat!(
    image_msg!(),
    dependency!("std_msgs/Header", header_msg!()),
    dependency!("builtin_interfaces/Time", time_msg!()),
);

/// `ros2msg` schema data of `sensor_msgs/msg/CameraInfo`, as rosbag2 writes it.
pub const CAMERA_INFO_DEFINITION: &str = concat!(
    camera_info_msg!(),
    dependency!("sensor_msgs/RegionOfInterest", region_of_interest_msg!()),
    dependency!("std_msgs/Header", header_msg!()),
    dependency!("builtin_interfaces/Time", time_msg!()),
);

/// `ros2msg` schema data of `tf2_msgs/msg/TFMessage`, as rosbag2 writes it.
pub const TF_MESSAGE_DEFINITION: &str = concat!(
    tf_message_msg!(),
    dependency!("geometry_msgs/TransformStamped", transform_stamped_msg!()),
    dependency!("geometry_msgs/Transform", transform_msg!()),
    dependency!("geometry_msgs/Quaternion", quaternion_msg!()),
    dependency!("geometry_msgs/Vector3", vector3_msg!()),
    dependency!("std_msgs/Header", header_msg!()),
    dependency!("builtin_interfaces/Time", time_msg!()),
);

// ---------------------------------------------------------------------------------------
// Encoding and decoding
// ---------------------------------------------------------------------------------------

/// Why a CDR payload could not be encoded or decoded.
#[derive(Debug, thiserror::Error)]
pub enum CdrError {
    /// The payload cannot even hold the 4-byte encapsulation header.
    #[error("CDR payload of {len} bytes is shorter than the 4-byte encapsulation header")]
    TooShort {
        /// Length of the payload.
        len: usize,
    },
    /// The encapsulation header names a representation other than plain CDR (for
    /// example parameter lists or XCDR2).
    #[error(
        "unsupported CDR representation identifier {:02x} {:02x} (expected 00 01 CDR_LE or 00 00 CDR_BE)",
        id[0],
        id[1]
    )]
    UnsupportedRepresentation {
        /// The first two bytes of the payload.
        id: [u8; 2],
    },
    /// The body is not a valid encoding of the type (truncated, bad string, bad bool, ...).
    #[error("cannot decode {type_name} from a {len}-byte CDR payload: {reason}")]
    Decode {
        /// Rust type that was being decoded.
        type_name: &'static str,
        /// Length of the payload, header included.
        len: usize,
        /// What `cdr-encoding` reported.
        reason: cdr_encoding::Error,
    },
    /// The value cannot be written as CDR (a `uint8[]` longer than `u32::MAX`, ...).
    #[error("cannot encode {type_name} as CDR: {reason}")]
    Encode {
        /// Rust type that was being encoded.
        type_name: &'static str,
        /// What `cdr-encoding` reported.
        reason: cdr_encoding::Error,
    },
}

/// Encodes `msg` as a CDR payload: the encapsulation header `00 01 00 00` (`CDR_LE`)
/// followed by the little-endian body, aligned relative to the start of the body.
pub fn encode<T: Serialize>(msg: &T) -> Result<Vec<u8>, CdrError> {
    let mut out = Vec::with_capacity(ENCAPSULATION_HEADER_LEN + 64);
    out.extend_from_slice(&[CDR_LE[0], CDR_LE[1], 0x00, 0x00]);
    // The serializer counts alignment from its own first byte, which is the body's.
    cdr_encoding::to_writer::<T, LittleEndian, _>(&mut out, msg).map_err(|reason| {
        CdrError::Encode {
            type_name: type_name::<T>(),
            reason,
        }
    })?;
    Ok(out)
}

/// Decodes a CDR payload (encapsulation header, then body) as a `T`.
///
/// Accepts `CDR_LE` (`00 01`) and `CDR_BE` (`00 00`); the two option bytes of the header
/// are ignored, and so are bytes after the end of the value (DDS pads payloads to a
/// multiple of 4). Never panics, and allocates no more than the payload's size whatever
/// the lengths it declares.
pub fn decode<'de, T: Deserialize<'de>>(bytes: &'de [u8]) -> Result<T, CdrError> {
    let Some((header, body)) = bytes.split_first_chunk::<ENCAPSULATION_HEADER_LEN>() else {
        return Err(CdrError::TooShort { len: bytes.len() });
    };
    // The deserializer counts alignment from the first byte of `body`, as CDR requires.
    let decoded = match [header[0], header[1]] {
        CDR_LE => cdr_encoding::from_bytes::<T, LittleEndian>(body),
        CDR_BE => cdr_encoding::from_bytes::<T, BigEndian>(body),
        id => return Err(CdrError::UnsupportedRepresentation { id }),
    };
    decoded
        .map(|(value, _consumed)| value)
        .map_err(|reason| CdrError::Decode {
            type_name: type_name::<T>(),
            len: bytes.len(),
            reason,
        })
}

// ---------------------------------------------------------------------------------------
// Conversion into the sensor model
// ---------------------------------------------------------------------------------------

impl Ros2Time {
    /// The time as a [`Stamp`].
    pub fn stamp(self) -> superflow_schemas::Stamp {
        superflow_schemas::Stamp::from_nanos(self.as_nanos())
    }
}

/// The transforms of a `tf2_msgs/msg/TFMessage`, each as `parent_from_child`
/// (`header.frame_id` is the parent). `is_static` is true for `/tf_static`.
pub fn transforms(
    msg: &TfMessage,
    is_static: bool,
) -> Vec<Result<superflow_schemas::sensor::StampedTransform, super::DecodeError>> {
    msg.transforms
        .iter()
        .map(|t| {
            let stamp = t.header.stamp.stamp();
            let tr = &t.transform.translation;
            let q = &t.transform.rotation;
            Ok(superflow_schemas::sensor::StampedTransform {
                stamp,
                parent_frame: t.header.frame_id.clone(),
                child_frame: t.child_frame_id.clone(),
                parent_from_child: super::isometry(
                    stamp,
                    &t.header.frame_id,
                    &t.child_frame_id,
                    [tr.x, tr.y, tr.z],
                    [q.x, q.y, q.z, q.w],
                )?,
                is_static,
            })
        })
        .collect()
}

/// A `sensor_msgs/msg/CameraInfo` as the intrinsics of the raw image: `k` and `d` with
/// its distortion model (`p` describes the rectified image and is not used).
pub fn camera_info(
    msg: &CameraInfo,
) -> Result<superflow_schemas::sensor::CameraCalibration, super::DecodeError> {
    super::calibration(
        msg.header.stamp.stamp(),
        &msg.header.frame_id,
        (msg.width, msg.height),
        &msg.k,
        &msg.distortion_model,
        &msg.d,
    )
}

#[cfg(test)]
mod tests {
    use std::collections::BTreeSet;
    use std::fmt::Debug;

    use serde::de::value::Error as ValueError;
    use serde::forward_to_deserialize_any;

    use super::*;

    fn header(sec: i32, nanosec: u32, frame_id: &str) -> Header {
        Header {
            stamp: Ros2Time { sec, nanosec },
            frame_id: frame_id.to_owned(),
        }
    }

    fn sample_point_cloud() -> PointCloud2 {
        let names = ["x", "y", "z", "intensity"];
        let fields = names
            .iter()
            .zip(0u32..)
            .map(|(name, i)| PointField {
                name: (*name).to_owned(),
                offset: 4 * i,
                datatype: PointField::FLOAT32,
                count: 1,
            })
            .collect();
        let points = 5u32;
        let data = (0..points * 16).map(|i| (i * 7 % 251) as u8).collect();
        PointCloud2 {
            header: header(1_700_000_000, 123_456_789, "lidar_top"),
            height: 1,
            width: points,
            fields,
            is_bigendian: false,
            point_step: 16,
            row_step: 16 * points,
            data,
            is_dense: true,
        }
    }

    fn sample_compressed_image() -> CompressedImage {
        CompressedImage {
            header: header(-3, 999_999_999, "cam_front"),
            format: "jpeg".to_owned(),
            data: vec![0xff, 0xd8, 0xff, 0xe0, 0x00, 0x10, 0xff, 0xd9],
        }
    }

    fn sample_image() -> Image {
        Image {
            header: header(12, 34, "cam_left"),
            height: 2,
            width: 3,
            encoding: "rgb8".to_owned(),
            is_bigendian: 0,
            step: 9,
            data: (0..18).collect(),
        }
    }

    fn sample_camera_info() -> CameraInfo {
        CameraInfo {
            header: header(5, 6, "cam_front"),
            height: 900,
            width: 1600,
            distortion_model: "plumb_bob".to_owned(),
            d: vec![-0.1, 0.01, 0.001, -0.002, 0.0],
            k: [1266.4, 0.0, 816.3, 0.0, 1266.4, 491.5, 0.0, 0.0, 1.0],
            r: [1.0, 0.0, 0.0, 0.0, 1.0, 0.0, 0.0, 0.0, 1.0],
            p: [
                1266.4, 0.0, 816.3, 0.0, 0.0, 1266.4, 491.5, 0.0, 0.0, 0.0, 1.0, 0.0,
            ],
            binning_x: 1,
            binning_y: 2,
            roi: RegionOfInterest {
                x_offset: 10,
                y_offset: 20,
                height: 30,
                width: 40,
                do_rectify: true,
            },
        }
    }

    fn sample_transform_stamped(child: &str) -> TransformStamped {
        TransformStamped {
            header: header(7, 8, "map"),
            child_frame_id: child.to_owned(),
            transform: Transform {
                translation: Vector3 {
                    x: 1.5,
                    y: -2.25,
                    z: 3.0,
                },
                rotation: Quaternion {
                    x: 0.0,
                    y: 0.0,
                    z: std::f64::consts::FRAC_1_SQRT_2,
                    w: std::f64::consts::FRAC_1_SQRT_2,
                },
            },
        }
    }

    fn sample_tf_message() -> TfMessage {
        TfMessage {
            transforms: vec![
                sample_transform_stamped("base_link"),
                sample_transform_stamped("lidar_top"),
                TransformStamped::default(),
            ],
        }
    }

    /// Encodes, checks the header, decodes and compares; also checks that the body
    /// is consumed to its last byte.
    fn round_trip<T>(msg: &T)
    where
        T: Serialize + DeserializeOwned + PartialEq + Debug,
    {
        let bytes = encode(msg).unwrap();
        assert_eq!(bytes[..4], [0x00, 0x01, 0x00, 0x00]);
        let back: T = decode(&bytes).unwrap();
        assert_eq!(&back, msg);
        let (_, consumed) =
            cdr_encoding::from_bytes::<T, LittleEndian>(&bytes[ENCAPSULATION_HEADER_LEN..])
                .unwrap();
        assert_eq!(consumed, bytes.len() - ENCAPSULATION_HEADER_LEN);
    }

    /// A `CDR_BE` payload of `msg`.
    fn encode_big_endian<T: Serialize>(msg: &T) -> Vec<u8> {
        let mut bytes = vec![0x00, 0x00, 0x00, 0x00];
        bytes.extend(cdr_encoding::to_vec::<T, BigEndian>(msg).unwrap());
        bytes
    }

    #[test]
    fn round_trips_every_message_type() {
        round_trip(&Ros2Time {
            sec: -1,
            nanosec: 500,
        });
        round_trip(&header(1, 2, ""));
        round_trip(&header(1, 2, "a frame with ünïcödé"));
        round_trip(&PointField {
            name: "rgb".to_owned(),
            offset: 16,
            datatype: PointField::UINT32,
            count: 1,
        });
        round_trip(&sample_point_cloud());
        round_trip(&PointCloud2::default());
        round_trip(&sample_compressed_image());
        round_trip(&sample_image());
        round_trip(&sample_camera_info());
        round_trip(&CameraInfo::default());
        round_trip(&RegionOfInterest::default());
        round_trip(&Vector3 {
            x: f64::MIN_POSITIVE,
            y: f64::MAX,
            z: -0.0,
        });
        round_trip(&Quaternion::default());
        round_trip(&Transform::default());
        round_trip(&sample_transform_stamped("x"));
        round_trip(&sample_tf_message());
        round_trip(&TfMessage::default());
    }

    #[test]
    fn header_encodes_to_hand_computed_bytes() {
        let bytes = encode(&header(1, 2, "map")).unwrap();
        #[rustfmt::skip]
        let expected = [
            0x00, 0x01, 0x00, 0x00, // encapsulation: CDR_LE, no options
            0x01, 0x00, 0x00, 0x00, // stamp.sec = 1
            0x02, 0x00, 0x00, 0x00, // stamp.nanosec = 2
            0x04, 0x00, 0x00, 0x00, // frame_id length, NUL included
            b'm', b'a', b'p', 0x00, // frame_id
        ];
        assert_eq!(bytes, expected);
        assert_eq!(decode::<Header>(&expected).unwrap(), header(1, 2, "map"));
    }

    #[test]
    fn transform_stamped_aligns_f64_to_body_start() {
        let msg = TransformStamped {
            header: header(1, 2, "map"),
            child_frame_id: "base".to_owned(),
            transform: Transform {
                translation: Vector3 {
                    x: 1.0,
                    y: -2.0,
                    z: 0.5,
                },
                rotation: Quaternion::default(),
            },
        };
        #[rustfmt::skip]
        let expected: Vec<u8> = [
            &[0x00, 0x01, 0x00, 0x00][..],          // encapsulation
            &[0x01, 0x00, 0x00, 0x00],              // body 0: stamp.sec
            &[0x02, 0x00, 0x00, 0x00],              // body 4: stamp.nanosec
            &[0x04, 0x00, 0x00, 0x00],              // body 8: frame_id length
            b"map\0",                               // body 12
            &[0x05, 0x00, 0x00, 0x00],              // body 16: child_frame_id length
            b"base\0",                              // body 20..25
            &[0x00; 7],                             // body 25..32: pad to 8 (body-relative)
            &[0, 0, 0, 0, 0, 0, 0xf0, 0x3f],        // body 32: translation.x = 1.0
            &[0, 0, 0, 0, 0, 0, 0x00, 0xc0],        // body 40: translation.y = -2.0
            &[0, 0, 0, 0, 0, 0, 0xe0, 0x3f],        // body 48: translation.z = 0.5
            &[0; 8],                                // body 56: rotation.x = 0
            &[0; 8],                                // body 64: rotation.y = 0
            &[0; 8],                                // body 72: rotation.z = 0
            &[0, 0, 0, 0, 0, 0, 0xf0, 0x3f],        // body 80: rotation.w = 1.0
        ]
        .concat();
        assert_eq!(expected.len(), 4 + 88);
        assert_eq!(encode(&msg).unwrap(), expected);
        assert_eq!(decode::<TransformStamped>(&expected).unwrap(), msg);
    }

    #[test]
    fn big_endian_payloads_decode_to_the_same_values() {
        #[rustfmt::skip]
        let header_be = [
            0x00, 0x00, 0x00, 0x00, // encapsulation: CDR_BE
            0x00, 0x00, 0x00, 0x01, // stamp.sec = 1
            0x00, 0x00, 0x00, 0x02, // stamp.nanosec = 2
            0x00, 0x00, 0x00, 0x04, // frame_id length
            b'm', b'a', b'p', 0x00,
        ];
        assert_eq!(decode::<Header>(&header_be).unwrap(), header(1, 2, "map"));

        fn same<T: Serialize + DeserializeOwned + PartialEq + Debug>(msg: &T) {
            let be = encode_big_endian(msg);
            assert_ne!(be[ENCAPSULATION_HEADER_LEN..], encode(msg).unwrap()[4..]);
            assert_eq!(&decode::<T>(&be).unwrap(), msg);
        }
        same(&sample_point_cloud());
        same(&sample_compressed_image());
        same(&sample_image());
        same(&sample_camera_info());
        same(&sample_tf_message());
    }

    #[test]
    fn trailing_padding_is_ignored() {
        let mut bytes = encode(&header(1, 2, "map!")).unwrap();
        bytes.extend_from_slice(&[0, 0, 0]);
        assert_eq!(decode::<Header>(&bytes).unwrap(), header(1, 2, "map!"));
    }

    #[test]
    fn short_buffers_and_other_representations_are_rejected() {
        for len in 0..4 {
            let bytes = [0x00, 0x01, 0x00][..len.min(3)].to_vec();
            assert!(matches!(
                decode::<Header>(&bytes),
                Err(CdrError::TooShort { len: l }) if l == bytes.len()
            ));
        }
        let body = &encode(&header(1, 2, "map")).unwrap()[2..];
        for id in [
            [0x00, 0x02],
            [0x00, 0x03],
            [0x00, 0x07],
            [0x01, 0x00],
            [0xff, 0xff],
        ] {
            let bytes = [&id[..], body].concat();
            let err = decode::<Header>(&bytes).unwrap_err();
            assert!(matches!(err, CdrError::UnsupportedRepresentation { id: got } if got == id));
            assert!(err.to_string().contains("representation"), "{err}");
        }
    }

    #[test]
    fn every_truncation_of_a_point_cloud_is_an_error() {
        let bytes = encode(&sample_point_cloud()).unwrap();
        for len in 0..bytes.len() {
            let result = decode::<PointCloud2>(&bytes[..len]);
            assert!(result.is_err(), "truncated to {len} bytes: {result:?}");
        }
        let be = encode_big_endian(&sample_point_cloud());
        for len in 0..be.len() {
            assert!(decode::<PointCloud2>(&be[..len]).is_err());
        }
    }

    #[test]
    fn huge_declared_lengths_are_errors_without_allocation() {
        // A sequence count of u32::MAX right at the start of the body, 16 bytes left.
        let mut tf = vec![0x00, 0x01, 0x00, 0x00, 0xff, 0xff, 0xff, 0xff];
        tf.extend_from_slice(&[0; 12]);
        assert_eq!(tf.len(), 20);
        assert!(matches!(
            decode::<TfMessage>(&tf),
            Err(CdrError::Decode { len: 20, .. })
        ));

        // `data` is the last field of these: patch its (empty) length to u32::MAX.
        fn patch_last_len<T: Serialize + DeserializeOwned + Debug>(msg: &T) {
            let mut bytes = encode(msg).unwrap();
            let at = bytes.len() - 4;
            bytes[at..].copy_from_slice(&[0xff; 4]);
            bytes.extend_from_slice(&[0; 8]);
            assert!(decode::<T>(&bytes).is_err());
        }
        patch_last_len(&CompressedImage::default());
        patch_last_len(&Image::default());

        // Huge string lengths, and huge counts of every sequence in the middle of a message.
        let mut frame = encode(&header(1, 2, "")).unwrap();
        frame[12..16].copy_from_slice(&[0xff; 4]);
        assert!(decode::<Header>(&frame).is_err());
        for msg_bytes in [
            encode(&sample_point_cloud()).unwrap(),
            encode(&sample_camera_info()).unwrap(),
            encode(&sample_tf_message()).unwrap(),
        ] {
            for at in 4..msg_bytes.len().saturating_sub(4) {
                let mut bytes = msg_bytes.clone();
                bytes[at..at + 4].copy_from_slice(&[0xff; 4]);
                let _ = decode::<PointCloud2>(&bytes);
                let _ = decode::<CameraInfo>(&bytes);
                let _ = decode::<TfMessage>(&bytes);
            }
        }
    }

    use crate::test_rng::TestRng as Rng;

    fn decode_all(bytes: &[u8]) {
        let _ = decode::<Header>(bytes);
        let _ = decode::<PointCloud2>(bytes);
        let _ = decode::<CompressedImage>(bytes);
        let _ = decode::<Image>(bytes);
        let _ = decode::<CameraInfo>(bytes);
        let _ = decode::<TfMessage>(bytes);
    }

    #[test]
    fn garbage_never_panics() {
        let mut rng = Rng(0x9e37_79b9_7f4a_7c15);
        for _ in 0..3000 {
            let len = rng.index(300);
            let mut bytes: Vec<u8> = (0..len).map(|_| rng.next() as u8).collect();
            if len >= 2 && rng.below(4) != 0 {
                bytes[0] = 0;
                bytes[1] = rng.below(2) as u8;
            }
            decode_all(&bytes);
        }
        // Valid messages with a few bytes flipped reach deeper into the decoders.
        let valid = [
            encode(&sample_point_cloud()).unwrap(),
            encode(&sample_compressed_image()).unwrap(),
            encode(&sample_image()).unwrap(),
            encode(&sample_camera_info()).unwrap(),
            encode(&sample_tf_message()).unwrap(),
        ];
        for _ in 0..3000 {
            let mut bytes = valid[rng.index(valid.len())].clone();
            for _ in 0..1 + rng.below(3) {
                let at = 4 + rng.index(bytes.len() - 4);
                bytes[at] = rng.next() as u8;
            }
            decode_all(&bytes);
        }
        assert!(decode::<Header>(&[0x00, 0x01, 0x00, 0x00, 0x01]).is_err());
        // Invalid UTF-8 and invalid bools are errors.
        let mut bad_utf8 = encode(&header(0, 0, "ab")).unwrap();
        bad_utf8[16] = 0xff;
        assert!(decode::<Header>(&bad_utf8).is_err());
        let mut bad_bool = encode(&RegionOfInterest::default()).unwrap();
        let last = bad_bool.len() - 1;
        bad_bool[last] = 2;
        assert!(decode::<RegionOfInterest>(&bad_bool).is_err());
    }

    #[test]
    fn megabyte_data_fields_are_one_octet_block() {
        let image = Image {
            header: header(1, 2, "cam"),
            height: 1024,
            width: 4096,
            encoding: "mono8".to_owned(),
            is_bigendian: 0,
            step: 4096,
            data: (0..4096 * 1024).map(|i: u32| (i % 253) as u8).collect(),
        };
        let bytes = encode(&image).unwrap();
        // 4 (encapsulation) + 8 (stamp) + 8 ("cam") + 8 (height, width) + 10 ("mono8")
        // + 1 (is_bigendian) + 1 (pad) + 4 (step) + 4 (count): then the pixels, verbatim.
        assert_eq!(bytes.len(), 48 + image.data.len());
        assert_eq!(bytes[48..], image.data[..]);
        let back: Image = decode(&bytes).unwrap();
        assert_eq!(back, image);
    }

    #[test]
    fn ros2_time_converts_to_and_from_nanoseconds() {
        let t = Ros2Time {
            sec: -2,
            nanosec: 300_000_000,
        };
        assert_eq!(t.as_nanos(), -1_700_000_000);
        assert_eq!(Ros2Time::from_nanos(-1_700_000_000), Some(t));
        assert_eq!(Ros2Time::from_nanos(i64::MAX), None);
        assert_eq!(PointField::datatype_size(PointField::FLOAT64), Some(8));
        assert_eq!(PointField::datatype_size(0), None);
    }

    // ----- schema texts -----

    const SEPARATOR: &str =
        "================================================================================";

    /// Probes the field names serde derives for `T`.
    struct FieldNames<'a>(&'a mut &'static [&'static str]);

    impl<'de> Deserializer<'de> for FieldNames<'_> {
        type Error = ValueError;

        fn deserialize_any<V: Visitor<'de>>(self, _: V) -> Result<V::Value, ValueError> {
            Err(serde::de::Error::custom("not a struct"))
        }

        fn deserialize_struct<V: Visitor<'de>>(
            self,
            _: &'static str,
            fields: &'static [&'static str],
            _: V,
        ) -> Result<V::Value, ValueError> {
            *self.0 = fields;
            Err(serde::de::Error::custom("probed"))
        }

        forward_to_deserialize_any! {
            bool i8 i16 i32 i64 i128 u8 u16 u32 u64 u128 f32 f64 char str string bytes
            byte_buf option unit unit_struct newtype_struct seq tuple tuple_struct map enum
            identifier ignored_any
        }
    }

    fn field_names<T: DeserializeOwned>() -> Vec<&'static str> {
        let mut fields: &'static [&'static str] = &[];
        let _ = T::deserialize(FieldNames(&mut fields));
        fields.to_vec()
    }

    /// The field lines of a `.msg` text as (type, name); constants left out.
    fn msg_fields(text: &str) -> Vec<(&str, &str)> {
        text.lines()
            .map(|line| line.split('#').next().unwrap_or("").trim())
            .filter(|line| !line.is_empty() && !line.contains('='))
            .map(|line| {
                let mut words = line.split_whitespace();
                (words.next().unwrap(), words.next().unwrap())
            })
            .collect()
    }

    /// The dependencies of a `.msg` text, named the way rosbag2 names them, sorted.
    fn msg_dependencies(text: &str, package: &str) -> BTreeSet<String> {
        const PRIMITIVES: [&str; 14] = [
            "bool", "byte", "char", "float32", "float64", "int8", "uint8", "int16", "uint16",
            "int32", "uint32", "int64", "uint64", "string",
        ];
        msg_fields(text)
            .into_iter()
            .map(|(ty, _)| ty.split('[').next().unwrap())
            .filter(|ty| !PRIMITIVES.contains(ty))
            .map(|ty| {
                if ty.contains('/') {
                    ty.to_owned()
                } else {
                    format!("{package}/{ty}")
                }
            })
            .collect()
    }

    /// The `.msg` text of a type, by its rosbag2 dependency name.
    fn msg_text(name: &str) -> &'static str {
        match name {
            "builtin_interfaces/Time" => time_msg!(),
            "std_msgs/Header" => header_msg!(),
            "sensor_msgs/PointField" => point_field_msg!(),
            "sensor_msgs/PointCloud2" => point_cloud2_msg!(),
            "sensor_msgs/CompressedImage" => compressed_image_msg!(),
            "sensor_msgs/Image" => image_msg!(),
            "sensor_msgs/RegionOfInterest" => region_of_interest_msg!(),
            "sensor_msgs/CameraInfo" => camera_info_msg!(),
            "geometry_msgs/Vector3" => vector3_msg!(),
            "geometry_msgs/Quaternion" => quaternion_msg!(),
            "geometry_msgs/Transform" => transform_msg!(),
            "geometry_msgs/TransformStamped" => transform_stamped_msg!(),
            "tf2_msgs/TFMessage" => tf_message_msg!(),
            other => panic!("no text for {other}"),
        }
    }

    /// The serde field names of the Rust mirror of a type.
    fn rust_fields(name: &str) -> Vec<&'static str> {
        match name {
            "builtin_interfaces/Time" => field_names::<Ros2Time>(),
            "std_msgs/Header" => field_names::<Header>(),
            "sensor_msgs/PointField" => field_names::<PointField>(),
            "sensor_msgs/PointCloud2" => field_names::<PointCloud2>(),
            "sensor_msgs/CompressedImage" => field_names::<CompressedImage>(),
            "sensor_msgs/Image" => field_names::<Image>(),
            "sensor_msgs/RegionOfInterest" => field_names::<RegionOfInterest>(),
            "sensor_msgs/CameraInfo" => field_names::<CameraInfo>(),
            "geometry_msgs/Vector3" => field_names::<Vector3>(),
            "geometry_msgs/Quaternion" => field_names::<Quaternion>(),
            "geometry_msgs/Transform" => field_names::<Transform>(),
            "geometry_msgs/TransformStamped" => field_names::<TransformStamped>(),
            "tf2_msgs/TFMessage" => field_names::<TfMessage>(),
            other => panic!("no Rust type for {other}"),
        }
    }

    /// Rebuilds the full text the way rosbag2's `get_full_text` does.
    fn rosbag2_full_text(root: &str) -> String {
        fn append(name: &str, seen: &mut BTreeSet<String>) -> String {
            let text = msg_text(name);
            let package = name.split('/').next().unwrap();
            let mut out = text.to_owned();
            for dep in msg_dependencies(text, package) {
                if seen.insert(dep.clone()) {
                    out.push('\n');
                    out.push_str(SEPARATOR);
                    out.push_str("\nMSG: ");
                    out.push_str(&dep);
                    out.push('\n');
                    out.push_str(&append(&dep, seen));
                }
            }
            out
        }
        append(root, &mut BTreeSet::new())
    }

    const ALL: [(&str, &str, &str); 5] = [
        (
            POINT_CLOUD2,
            "sensor_msgs/PointCloud2",
            POINT_CLOUD2_DEFINITION,
        ),
        (
            COMPRESSED_IMAGE,
            "sensor_msgs/CompressedImage",
            COMPRESSED_IMAGE_DEFINITION,
        ),
        (IMAGE, "sensor_msgs/Image", IMAGE_DEFINITION),
        (
            CAMERA_INFO,
            "sensor_msgs/CameraInfo",
            CAMERA_INFO_DEFINITION,
        ),
        (TF_MESSAGE, "tf2_msgs/TFMessage", TF_MESSAGE_DEFINITION),
    ];

    #[test]
    fn schema_texts_have_rosbag2_layout() {
        assert_eq!(SCHEMA_ENCODING, "ros2msg");
        assert_eq!(MESSAGE_ENCODING, "cdr");
        assert_eq!(SEPARATOR.len(), 80);
        for (schema_name, short_name, definition) in ALL {
            assert_eq!(schema_name.replace("/msg/", "/"), short_name);
            assert!(!definition.starts_with('='), "{schema_name}");
            assert!(definition.ends_with('\n'), "{schema_name}");
            assert!(definition.contains(&format!("\n\n{SEPARATOR}\nMSG: std_msgs/Header\n")));
            assert!(definition.contains(&format!("\n{SEPARATOR}\nMSG: builtin_interfaces/Time\n")));
            // Every separator line is exactly 80 '=' and is followed by a MSG: line.
            let lines: Vec<&str> = definition.lines().collect();
            for (i, line) in lines.iter().enumerate() {
                if line.starts_with('=') {
                    assert_eq!(*line, SEPARATOR, "{schema_name}");
                    assert!(lines[i + 1].starts_with("MSG: "), "{schema_name}");
                }
            }
            assert_eq!(rosbag2_full_text(short_name), definition, "{schema_name}");
        }
        assert!(POINT_CLOUD2_DEFINITION.contains("\nMSG: sensor_msgs/PointField\n"));
        assert!(POINT_CLOUD2_DEFINITION.contains("\nuint8 FLOAT64 = 8\n"));
        assert!(CAMERA_INFO_DEFINITION.contains("\nMSG: sensor_msgs/RegionOfInterest\n"));
        assert!(TF_MESSAGE_DEFINITION.contains("\nMSG: geometry_msgs/TransformStamped\n"));
        assert!(TF_MESSAGE_DEFINITION.contains("\nMSG: geometry_msgs/Quaternion\n"));
        assert_eq!(
            <PointCloud2 as Ros2Message>::SCHEMA_DEFINITION,
            POINT_CLOUD2_DEFINITION
        );
        assert_eq!(<TfMessage as Ros2Message>::SCHEMA_NAME, TF_MESSAGE);
    }

    #[test]
    fn schema_fields_match_the_rust_types() {
        for (schema_name, short_name, definition) in ALL {
            let separator = format!("{SEPARATOR}\n");
            let mut sections = definition.split(&separator);
            let mut named = vec![(short_name.to_owned(), sections.next().unwrap())];
            for section in sections {
                let (first, text) = section.split_once('\n').unwrap();
                named.push((first.strip_prefix("MSG: ").unwrap().to_owned(), text));
            }
            for (name, text) in named {
                let from_text: Vec<&str> = msg_fields(text)
                    .into_iter()
                    .map(|(_, field)| field)
                    .collect();
                assert_eq!(from_text, rust_fields(&name), "{schema_name}: {name}");
            }
        }
        let constants: Vec<&str> = point_field_msg!()
            .lines()
            .filter(|line| line.contains('='))
            .collect();
        assert_eq!(constants.len(), 8);
        for (line, value) in constants.iter().zip(1u8..) {
            assert!(line.ends_with(&format!("= {value}")), "{line}");
        }
    }
}
