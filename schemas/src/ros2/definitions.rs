//! The `ros2msg` schema texts of the top-level message types, byte for byte as rosbag2
//! writes them: the `.msg` text of each type (as a `macro_rules!` so the texts can be
//! `concat!`ed at compile time, and compared with the Rust types in the tests), and the
//! full `*_DEFINITION` texts with their dependencies.
//!
//! rosbag2 (`LocalMessageDefinitionSource::get_full_text`) writes the root type's `.msg`
//! file, then for each dependency not written yet, depth first and in the sorted order of
//! the type names as they appear in the field lines (a bare `Type` gets the package of
//! the file it is used in): "\n", 80 '=', "\n", "MSG: pkg/Type\n" and the dependency's
//! file. Every file ends with a newline, so a blank line precedes each separator.

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
