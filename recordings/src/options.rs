//! [`DriveOptions`]: what to simulate and how to write it — the sample drives'
//! settings by default, a short drive for the damaged recordings, and a nuScenes-sized
//! drive for benchmarks.

use crate::dialect::Dialect;
use crate::sample_drive::{DURATION_NANOS, IMAGE_SIZE};

/// When the cameras fire.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Default)]
pub enum CameraTrigger {
    /// Every camera at a fixed phase: 5 ms after the drive's start plus 7.5 ms per camera
    /// index (the sample drives).
    #[default]
    Fixed,
    /// As nuScenes' rig: each camera fires when the spinning LiDAR's beam passes the
    /// centre of its field of view ([`crate::trigger::trigger_phase_nanos`]).
    Staggered,
}

impl CameraTrigger {
    /// The CLI spelling (`fixed`, `staggered`).
    pub fn name(self) -> &'static str {
        match self {
            CameraTrigger::Fixed => "fixed",
            CameraTrigger::Staggered => "staggered",
        }
    }
}

/// How the camera images are coded as JPEG.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Default)]
pub enum JpegCoding {
    /// Huffman tables optimized per image, which the encoder (jpeg-encoder) writes as one
    /// scan per colour component (the sample drives). A decoder then holds the whole
    /// image's coefficients before the first pixel.
    #[default]
    OptimizedPerComponent,
    /// The standard Huffman tables in one interleaved scan: what libjpeg, OpenCV and
    /// camera drivers write by default (the nuScenes-sized bench drives).
    StandardInterleaved,
}

impl JpegCoding {
    /// A short name (`optimized`, `interleaved`), for file and directory names.
    pub fn name(self) -> &'static str {
        match self {
            JpegCoding::OptimizedPerComponent => "optimized",
            JpegCoding::StandardInterleaved => "interleaved",
        }
    }
}

/// How the chunks of a Foxglove drive are compressed (ROS 2 drives are always zstd, as
/// `ros2 bag record` writes them).
#[derive(Debug, Clone, Copy, PartialEq, Eq, Default)]
pub enum ChunkCompression {
    /// LZ4 frames (the sample drives).
    #[default]
    Lz4,
    /// zstd frames (the nuScenes-sized bench drives): what mcap's writers default to, so
    /// what nuscenes2mcap writes since it moved to foxglove-sdk (the 2022–24 converter
    /// asked for LZ4).
    Zstd,
}

impl ChunkCompression {
    /// The compression as mcap's writer takes it.
    pub fn mcap(self) -> mcap::Compression {
        match self {
            ChunkCompression::Lz4 => mcap::Compression::Lz4,
            ChunkCompression::Zstd => mcap::Compression::Zstd,
        }
    }

    /// Its name in a chunk record (`lz4`, `zstd`).
    pub fn name(self) -> &'static str {
        match self {
            ChunkCompression::Lz4 => "lz4",
            ChunkCompression::Zstd => "zstd",
        }
    }
}

/// Where the per-pixel class maps ("superpixels") go.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Default)]
pub enum ClassMapStorage {
    /// Raw Mono8 images on `/CAM_*/superpixels` in the drive file (the sample drives).
    #[default]
    InDrive,
    /// 8-bit grey PNGs (`CompressedImage`, format `png`) on the same topics, in a sidecar
    /// file `<drive>.superpixels.mcap` ([`crate::drive::GeneratedDrive::sidecar`]).
    PngSidecar,
}

impl ClassMapStorage {
    /// The CLI spelling (`in-drive`, `png-sidecar`).
    pub fn name(self) -> &'static str {
        match self {
            ClassMapStorage::InDrive => "in-drive",
            ClassMapStorage::PngSidecar => "png-sidecar",
        }
    }
}

/// The tag of the class-map sidecar: `<drive>.superpixels.mcap`.
pub const SIDECAR_TAG: &str = "superpixels";

/// The tag of the labels sidecar: `<drive>.labels.mcap`.
pub const LABELS_SIDECAR_TAG: &str = "labels";

/// Where the per-point semantic labels of the LiDAR go (each return's
/// [`crate::sim::Return::class`], the ids of [`crate::scene::CLASSES`]).
#[derive(Debug, Clone, Copy, PartialEq, Eq, Default)]
pub enum LidarLabels {
    /// No labels (the damaged recordings, the nuScenes-sized drive).
    None,
    /// As the sample drives have them: a field in the Foxglove clouds, a sidecar for
    /// ROS 2 ([`LidarLabels::resolve`]).
    #[default]
    Native,
    /// A UINT8 `label` field after the cloud's other fields.
    InCloud,
    /// A `<drive>.labels.mcap` sidecar: per sweep a cloud with one UINT8 `label` field, the
    /// sweep's stamp, frame and point order, on `<lidar topic>/labels`.
    Sidecar,
}

impl LidarLabels {
    /// The CLI spelling (`none`, `native`, `in-cloud`, `sidecar`).
    pub fn name(self) -> &'static str {
        match self {
            LidarLabels::None => "none",
            LidarLabels::Native => "native",
            LidarLabels::InCloud => "in-cloud",
            LidarLabels::Sidecar => "sidecar",
        }
    }

    /// What this means in `dialect`: [`LidarLabels::Native`] becomes
    /// [`LidarLabels::InCloud`] for Foxglove (a nuScenes-lidarseg conversion) and
    /// [`LidarLabels::Sidecar`] for ROS 2 (labels produced after the recording).
    pub fn resolve(self, dialect: Dialect) -> Self {
        match (self, dialect) {
            (LidarLabels::Native, Dialect::Foxglove) => LidarLabels::InCloud,
            (LidarLabels::Native, Dialect::Ros2) => LidarLabels::Sidecar,
            (other, _) => other,
        }
    }
}

/// What to simulate: the sample drives use [`DriveOptions::default`]; shorter, smaller
/// drives (the source of `recordings/damaged/`) and larger ones ([`DriveOptions::nuscenes`])
/// change it.
#[derive(Debug, Clone, PartialEq)]
pub struct DriveOptions {
    /// File stem of the drive, `{dialect}` standing for the dialect's name
    /// (`street_{dialect}` for the sample drives).
    pub name: String,
    /// Length of the drive, nanoseconds (3 s for the sample drives).
    pub duration_nanos: i64,
    /// The first this many cameras of the rig, in nuScenes order (6 for the sample drives).
    pub cameras: usize,
    /// Camera image size (480×270 for the sample drives; K scales with it).
    pub image_size: (u32, u32),
    /// LiDAR firings per revolution (300 for the sample drives).
    pub lidar_columns: usize,
    /// LiDAR beams (16 for the sample drives: -25°..+5°; other counts spread evenly over
    /// an HDL-32E-like -30.67°..+10.67°, see [`crate::sim::beam_elevations`]).
    pub beams: usize,
    /// Time between the firings of two successive beams of a column, lowest first,
    /// nanoseconds: 0 fires a column's beams at once (the sample drives); an HDL-32E
    /// fires its lasers 1.152 µs apart, so every point of a raw sweep has its own time.
    pub beam_interval_nanos: i64,
    /// When the cameras fire ([`CameraTrigger::Fixed`] for the sample drives).
    pub camera_trigger: CameraTrigger,
    /// Where the class maps go ([`ClassMapStorage::InDrive`] for the sample drives).
    pub class_maps: ClassMapStorage,
    /// Where the LiDAR's per-point labels go ([`LidarLabels::Native`] for the sample
    /// drives).
    pub labels: LidarLabels,
    /// MCAP chunk size, bytes (512 KiB for the sample drives).
    pub chunk_size: u64,
    /// Chunk compression of a Foxglove drive and its sidecars (LZ4 for the sample drives).
    pub foxglove_compression: ChunkCompression,
    /// How camera images are coded (optimized tables, one scan per component, for the
    /// sample drives).
    pub jpeg_coding: JpegCoding,
}

impl Default for DriveOptions {
    /// The sample drives of `recordings/drives/`.
    fn default() -> Self {
        Self {
            name: "street_{dialect}".into(),
            duration_nanos: DURATION_NANOS,
            cameras: 6,
            image_size: IMAGE_SIZE,
            lidar_columns: 300,
            beams: 16,
            beam_interval_nanos: 0,
            camera_trigger: CameraTrigger::Fixed,
            class_maps: ClassMapStorage::InDrive,
            labels: LidarLabels::Native,
            chunk_size: 512 * 1024,
            foxglove_compression: ChunkCompression::Lz4,
            jpeg_coding: JpegCoding::OptimizedPerComponent,
        }
    }
}

impl DriveOptions {
    /// A short, small drive: 1.5 s (3 keyframes at 0.5 s), the front and front-right
    /// cameras at 240×136, 60 LiDAR columns, 32 KiB chunks (so that damage to one chunk
    /// costs a small part of the file), no labels. About 0.4 MB per dialect.
    pub fn short() -> Self {
        Self {
            duration_nanos: 1_500_000_000,
            cameras: 2,
            image_size: (240, 136),
            lidar_columns: 60,
            labels: LidarLabels::None,
            chunk_size: 32 * 1024,
            ..Self::default()
        }
    }

    /// A nuScenes-sized drive for benchmarks: 8 s (16 keyframes at 2 Hz), a 32-beam LiDAR
    /// with 1084 firings per 20 Hz revolution, six cameras at `width × height` triggered
    /// as the beam passes them, class maps as PNGs in a sidecar, no labels, chunks of
    /// 1 MiB (the Python mcap writer's default, which nuscenes2mcap 2022–24 and
    /// mcap_ros2 use) compressed with zstd as the current nuscenes2mcap writes them. Long
    /// enough that samples in shuffled order read most of their chunks afresh, as they do
    /// on a real drive. Its stem is `nuscenes_{dialect}_<width>x<height>`.
    pub fn nuscenes(width: u32, height: u32) -> Self {
        Self {
            name: format!("nuscenes_{{dialect}}_{width}x{height}"),
            duration_nanos: 8_000_000_000,
            cameras: 6,
            image_size: (width, height),
            lidar_columns: 1084,
            beams: 32,
            beam_interval_nanos: 1_152,
            camera_trigger: CameraTrigger::Staggered,
            class_maps: ClassMapStorage::PngSidecar,
            labels: LidarLabels::None,
            chunk_size: 1024 * 1024,
            foxglove_compression: ChunkCompression::Zstd,
            jpeg_coding: JpegCoding::StandardInterleaved,
        }
    }

    /// A sample-preset drive of another rig: `cameras` cameras (the first of the rig, in
    /// nuScenes order: front, front right, ...) at `image_size`, a LiDAR of `beams` beams.
    /// Named after what differs from the sample drives,
    /// `street_{dialect}[_<N>cam][_<W>x<H>][_<B>beams]`, never over them. A fleet
    /// mixes such drives with the 6-camera ones.
    pub fn rig(cameras: usize, image_size: (u32, u32), beams: usize) -> Self {
        let mut options = Self {
            cameras,
            image_size,
            beams,
            ..Self::default()
        };
        options.name = options.sample_name();
        options
    }

    /// The name of a sample-preset drive with these options: `street_{dialect}` and a
    /// suffix for each way it differs from the sample drives (length, cameras, image
    /// size, beams).
    pub fn sample_name(&self) -> String {
        let sample = Self::default();
        let mut name = String::from("street_{dialect}");
        if self.duration_nanos != sample.duration_nanos {
            name += &format!("_{}s", self.duration_secs());
        }
        if self.cameras != sample.cameras {
            name += &format!("_{}cam", self.cameras);
        }
        if self.image_size != sample.image_size {
            name += &format!("_{}x{}", self.image_size.0, self.image_size.1);
        }
        if self.beams != sample.beams {
            name += &format!("_{}beams", self.beams);
        }
        name
    }

    /// The drive length in seconds, as the writers' descriptions spell it.
    pub fn duration_secs(&self) -> f64 {
        self.duration_nanos as f64 * 1e-9
    }

    /// File stem of the drive in `dialect` (`street_ros2`, `nuscenes_foxglove_800x450`).
    pub fn drive_name(&self, dialect: Dialect) -> String {
        self.name.replace("{dialect}", dialect.name())
    }

    /// File name of the class-map sidecar in `dialect`, if the class maps go to one.
    pub fn sidecar_name(&self, dialect: Dialect) -> Option<String> {
        (self.class_maps == ClassMapStorage::PngSidecar)
            .then(|| format!("{}.{SIDECAR_TAG}.mcap", self.drive_name(dialect)))
    }

    /// File name of the labels sidecar in `dialect`, if the labels go to one.
    pub fn labels_sidecar_name(&self, dialect: Dialect) -> Option<String> {
        (self.labels.resolve(dialect) == LidarLabels::Sidecar)
            .then(|| format!("{}.{LABELS_SIDECAR_TAG}.mcap", self.drive_name(dialect)))
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn names_follow_the_dialect_and_presets_keep_their_own_stem() {
        let default = DriveOptions::default();
        for dialect in Dialect::ALL {
            assert_eq!(default.drive_name(dialect), dialect.drive_name());
            assert_eq!(
                DriveOptions::short().drive_name(dialect),
                dialect.drive_name()
            );
            assert_eq!(default.sidecar_name(dialect), None);
            assert_eq!(DriveOptions::short().labels_sidecar_name(dialect), None);
        }
        assert_eq!(default.labels_sidecar_name(Dialect::Foxglove), None);
        assert_eq!(
            default.labels_sidecar_name(Dialect::Ros2).as_deref(),
            Some("street_ros2.labels.mcap")
        );
        let two = DriveOptions::rig(2, (640, 360), 32);
        assert_eq!(
            two.drive_name(Dialect::Ros2),
            "street_ros2_2cam_640x360_32beams"
        );
        let one = DriveOptions::rig(1, crate::sample_drive::IMAGE_SIZE, 16);
        assert_eq!(one.drive_name(Dialect::Foxglove), "street_foxglove_1cam");
        assert_eq!(
            DriveOptions::default().sample_name(),
            DriveOptions::default().name
        );
        let nuscenes = DriveOptions::nuscenes(800, 450);
        assert_eq!(
            nuscenes.drive_name(Dialect::Foxglove),
            "nuscenes_foxglove_800x450"
        );
        assert_eq!(
            nuscenes.sidecar_name(Dialect::Ros2).as_deref(),
            Some("nuscenes_ros2_800x450.superpixels.mcap")
        );
    }
}
