//! Deterministic generator of the sample drives in `recordings/`.
//!
//! A drive is simulated once per dialect through a small procedural street
//! ([`scene::Scene`]): the ego weaves along the road at 8 m/s, a spinning 16-beam LiDAR
//! ([`sim::simulate_sweep`]) fires 300 columns per 20 Hz revolution, each column at its own
//! instant, and six surround cameras ([`render::render_camera`]) ray-cast every pixel at ~12 Hz
//! from the same scene, so a LiDAR point projects onto the object it hit. Each camera also
//! gets a per-pixel class map, the "superpixels" a vision foundation model would give.
//! Returns and pixels also carry the id of the scene box they hit (ground truth for
//! checks, never written).
//!
//! [`DriveOptions`] changes the rig and the layout: beams, columns, image size, camera
//! triggers ([`CameraTrigger`]), class maps in the drive or in a PNG sidecar
//! ([`ClassMapStorage`]), the LiDAR's per-point labels (each return's class) as a cloud
//! field or in a `<drive>.labels.mcap` sidecar ([`LidarLabels`]);
//! [`DriveOptions::nuscenes`] is a nuScenes-sized drive for benchmarks.
//!
//! The drive is then written in one of two real-world dialects ([`Dialect`]) — the
//! nuScenes-converter Foxglove protobuf layout or a ROS 2 rosbag2 layout — together with
//! a [`truth::GroundTruth`] JSON. Everything is a pure function of the code: running
//! `superflow-recordings --out recordings` reproduces the committed files byte for byte;
//! [`cli`] turns that command line into the generator's settings and writes the files.
//!
//! ```no_run
//! let drive = superflow_recordings::generate(superflow_recordings::Dialect::Ros2)?;
//! std::fs::write("drive.mcap", &drive.mcap)?;
//! # Ok::<(), Box<dyn std::error::Error>>(())
//! ```

pub mod cli;
pub mod damaged;
pub mod dialect;
pub mod drive;
pub mod encode;
pub mod error;
pub mod foxglove;
pub mod generate;
pub mod options;
pub mod out;
pub mod render;
pub mod ros2;
pub mod sample_drive;
pub mod scene;
pub mod sim;
pub mod simulation;
pub mod srgb;
pub mod trigger;
pub mod truth;

pub use dialect::Dialect;
pub use drive::GeneratedDrive;
pub use encode::{encode_jpeg, encode_png_mono};
pub use error::GenerateError;
pub use generate::{generate, generate_with};
pub use options::{
    CameraTrigger, ChunkCompression, ClassMapStorage, DriveOptions, JpegCoding, LidarLabels,
};
pub use sample_drive::{
    GENERATOR_VERSION, IMAGE_SIZE, JPEG_QUALITY, SCENE_SEED, sample_drive_path, sample_drives_dir,
};
pub use simulation::{Simulation, simulate, simulate_with};
