//! The ground truth written next to each drive (`<drive>.truth.json`): what a reader of
//! the MCAP must find, and what geometry must reproduce.

use nalgebra::{Isometry3, Quaternion, Translation3, UnitQuaternion};
use serde::{Deserialize, Serialize};

/// A rigid transform as JSON: translation in metres and a unit quaternion `[x, y, z, w]`.
#[derive(Debug, Clone, Copy, PartialEq, Serialize, Deserialize)]
pub struct PoseTruth {
    /// Translation `[x, y, z]`.
    pub translation: [f64; 3],
    /// Rotation `[x, y, z, w]`.
    pub rotation_xyzw: [f64; 4],
}

impl From<&Isometry3<f64>> for PoseTruth {
    fn from(iso: &Isometry3<f64>) -> Self {
        let t = iso.translation.vector;
        let q = iso.rotation.quaternion();
        Self {
            translation: [t.x, t.y, t.z],
            rotation_xyzw: [q.i, q.j, q.k, q.w],
        }
    }
}

impl PoseTruth {
    /// The transform as an isometry.
    pub fn isometry(&self) -> Isometry3<f64> {
        let [x, y, z, w] = self.rotation_xyzw;
        let [tx, ty, tz] = self.translation;
        Isometry3::from_parts(
            Translation3::new(tx, ty, tz),
            UnitQuaternion::from_quaternion(Quaternion::new(w, x, y, z)),
        )
    }
}

/// One channel of the file.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct ChannelTruth {
    /// Topic name.
    pub topic: String,
    /// Schema name (`foxglove.PointCloud`, `sensor_msgs/msg/PointCloud2`, ...).
    pub schema_name: String,
    /// Schema encoding (`protobuf`, `ros2msg`, `jsonschema`).
    pub schema_encoding: String,
    /// Message encoding (`protobuf`, `cdr`, `json`).
    pub message_encoding: String,
    /// Messages written on the channel.
    pub message_count: u64,
    /// What the channel carries: `lidar`, `image`, `calibration`, `superpixels`,
    /// `transforms`, `static_transforms` or `other`.
    pub role: String,
}

/// One LiDAR sweep.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct SweepTruth {
    /// The message's stamp.
    pub stamp_nanos: i64,
    /// Points in the message.
    pub points: u64,
}

/// The LiDAR.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct LidarTruth {
    /// Topic of the sweeps.
    pub topic: String,
    /// Frame of the points.
    pub frame_id: String,
    /// Revolutions per second.
    pub rate_hz: f64,
    /// Beams (rings).
    pub beams: u32,
    /// Firings per revolution.
    pub columns: u32,
    /// Whether points are expressed in the LiDAR frame at the sweep stamp (`true`) or
    /// at their own firing time, given by a per-point time field (`false`).
    pub motion_compensated: bool,
    /// `sweep_end` or `sweep_start`: which instant of the revolution the stamp is.
    pub stamp_at: String,
    /// The LiDAR mount.
    pub ego_from_lidar: PoseTruth,
    /// Every sweep, in time order.
    pub sweeps: Vec<SweepTruth>,
}

/// One camera.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct CameraTruth {
    /// Camera name (`CAM_FRONT`, ...).
    pub name: String,
    /// Topic of the images.
    pub image_topic: String,
    /// Topic of the calibration.
    pub calibration_topic: String,
    /// Topic of the per-pixel class maps.
    pub superpixel_topic: String,
    /// The optical frame.
    pub frame_id: String,
    /// Image width.
    pub width: u32,
    /// Image height.
    pub height: u32,
    /// `K`, row-major.
    pub k: [f64; 9],
    /// ROS distortion model name (empty for none).
    pub distortion_model: String,
    /// Distortion coefficients.
    pub d: Vec<f64>,
    /// The camera's optical frame in the ego frame.
    pub ego_from_camera: PoseTruth,
    /// Stamps of its images.
    pub stamps_nanos: Vec<i64>,
}

/// The ego pose at one instant.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct PoseSample {
    /// When.
    pub stamp_nanos: i64,
    /// The ego frame in the map frame.
    pub map_from_ego: PoseTruth,
}

/// Where a camera sees a landmark.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct Observation {
    /// Camera name.
    pub camera: String,
    /// Stamp of the camera image.
    pub stamp_nanos: i64,
    /// Pixel `(u, v)` in the raw image (OpenCV convention: pixel centres at integers).
    pub pixel: [f64; 2],
    /// Depth along the optical axis, metres.
    pub depth: f64,
    /// Whether nothing occludes the landmark.
    pub visible: bool,
}

/// A fixed 3D point of the scene and its expected pixels.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct Landmark {
    /// What the point is (`building_left_3/corner_6`).
    pub name: String,
    /// Position in the map frame.
    pub point_in_map: [f64; 3],
    /// Every camera image (at the observation instant) whose strict bounds contain it.
    pub observations: Vec<Observation>,
}

/// Frame names of the drive.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct FramesTruth {
    /// The fixed world frame.
    pub map: String,
    /// The vehicle frame.
    pub ego: String,
    /// The LiDAR frame.
    pub lidar: String,
}

/// Everything the generator knows about a drive it wrote.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct GroundTruth {
    /// Drive name (file stem).
    pub drive: String,
    /// `foxglove` or `ros2`.
    pub dialect: String,
    /// MCAP header profile.
    pub profile: String,
    /// Chunk compression.
    pub compression: String,
    /// Version of the generator that wrote it.
    pub generator_version: u32,
    /// Scene seed.
    pub seed: u64,
    /// First instant of the drive.
    pub start_stamp_nanos: i64,
    /// End of the drive.
    pub end_stamp_nanos: i64,
    /// Class names by id.
    pub classes: Vec<String>,
    /// Frame names.
    pub frames: FramesTruth,
    /// Every channel.
    pub channels: Vec<ChannelTruth>,
    /// The LiDAR.
    pub lidar: LidarTruth,
    /// The cameras.
    pub cameras: Vec<CameraTruth>,
    /// Ego poses at every LiDAR and camera stamp.
    pub ego_poses: Vec<PoseSample>,
    /// Landmarks and their expected pixels.
    pub landmarks: Vec<Landmark>,
    /// The class-map sidecar file, when the class maps are not in the drive (absent from
    /// the JSON otherwise).
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub sidecar: Option<SidecarTruth>,
    /// The LiDAR's per-point labels, when written (absent from the JSON otherwise). The
    /// label of every point is its return's class
    /// ([`crate::simulation::Simulation::sweep_classes`] recomputes them).
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub labels: Option<LabelsTruth>,
}

/// Where the LiDAR's per-point labels are and what they hold.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct LabelsTruth {
    /// `field` (a field of the LiDAR clouds) or `sidecar` (parallel clouds in
    /// `<drive>.labels.mcap`, one per sweep, same stamp, frame and point order).
    pub form: String,
    /// Topic of the labelled clouds: the LiDAR's, or the sidecar's label clouds'.
    pub topic: String,
    /// Name of the label field.
    pub field: String,
    /// Its type (`uint8`), the ids of [`GroundTruth::classes`].
    pub datatype: String,
    /// Points per class id over every sweep (index = id).
    pub points_per_class: Vec<u64>,
    /// The sidecar file and its channels (sidecar form only).
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub sidecar: Option<SidecarTruth>,
}

/// A sidecar file (`<drive>.<tag>.mcap`, next to the drive) and its channels.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct SidecarTruth {
    /// File name (`street_ros2.superpixels.mcap`).
    pub file: String,
    /// Every channel of the sidecar.
    pub channels: Vec<ChannelTruth>,
}
