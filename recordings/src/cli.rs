//! The command line of `superflow-recordings`: its flags ([`Args`]), the drive settings
//! they ask for ([`Args::drive_options`]) and the run that writes the files ([`run`]).
//! The binary only parses the flags, sets up logging and maps an error to the exit code.

use crate::{
    CameraTrigger, ClassMapStorage, Dialect, DriveOptions, GeneratedDrive, LidarLabels, damaged,
    generate_with,
};
use anyhow::Context as _;
use clap::{Parser, ValueEnum};
use std::path::{Path, PathBuf};

/// Drive presets.
#[derive(Debug, Clone, Copy, PartialEq, Eq, ValueEnum)]
enum Preset {
    /// The sample drives of `recordings/drives/`.
    Sample,
    /// A nuScenes-sized drive (`DriveOptions::nuscenes`): 32 beams, 1084 columns, six
    /// cameras at `--image-size`, staggered triggers, PNG class-map sidecar, 2 s.
    Nuscenes,
}

/// `--trigger` values.
#[derive(Debug, Clone, Copy, PartialEq, Eq, ValueEnum)]
enum Trigger {
    /// Fixed phases (the sample drives).
    Fixed,
    /// Each camera fires as the LiDAR beam passes the centre of its view (nuScenes).
    Staggered,
}

/// `--class-maps` values.
#[derive(Debug, Clone, Copy, PartialEq, Eq, ValueEnum)]
enum ClassMaps {
    /// Raw Mono8 images in the drive (the sample drives).
    InDrive,
    /// PNGs in `<drive>.superpixels.mcap` next to the drive.
    PngSidecar,
}

/// `--labels` values.
#[derive(Debug, Clone, Copy, PartialEq, Eq, ValueEnum)]
enum Labels {
    /// No per-point labels.
    None,
    /// A `label` field in the Foxglove clouds, a `<drive>.labels.mcap` sidecar for ROS 2
    /// (the sample drives).
    Native,
    /// A `label` field in the clouds of either dialect.
    InCloud,
    /// A `<drive>.labels.mcap` sidecar in either dialect.
    Sidecar,
}

/// Generates the sample drives of `recordings/` (deterministic: same bytes every run).
#[derive(Debug, Parser)]
#[command(version, about)]
pub struct Args {
    /// Directory to write `<drive>.mcap`, `<drive>.superpixels.mcap` (with a class-map
    /// sidecar), `<drive>.labels.mcap` (with a labels sidecar) and `<drive>.truth.json`
    /// into.
    #[arg(long, default_value = "recordings/drives")]
    out: PathBuf,
    /// Only this dialect; both by default.
    #[arg(long, value_enum)]
    dialect: Option<Dialect>,
    /// Start from this preset; the flags below change it. A nuScenes drive is named
    /// `nuscenes_<dialect>_<W>x<H>`, never overwriting the sample drives.
    #[arg(long, value_enum, default_value = "sample")]
    preset: Preset,
    /// Camera image size `WxH`: for the nuScenes preset 800x450 (default) or 1600x900;
    /// for the sample preset any size (the sample drives: 480x270).
    #[arg(long, value_name = "WxH")]
    image_size: Option<String>,
    /// Length of the drive in seconds (the sample drives: 3). A sample-preset drive of
    /// another length is named `street_<dialect>_<secs>s`, never over the sample drives.
    #[arg(long, conflicts_with = "keyframes")]
    duration_secs: Option<f64>,
    /// Length of the drive in keyframes of the default recipe (0.5 s each; the sample
    /// drives: 6): `--keyframes 120` is a 60 s drive.
    #[arg(long)]
    keyframes: Option<u32>,
    /// Cameras of the rig, the first N in nuScenes order (the sample drives: 6).
    #[arg(long)]
    cameras: Option<usize>,
    /// LiDAR beams, 2..=128 (the sample drives: 16; other counts spread over
    /// -30.67°..+10.67°).
    #[arg(long)]
    beams: Option<usize>,
    /// Camera triggering.
    #[arg(long, value_enum)]
    trigger: Option<Trigger>,
    /// Where the class maps go.
    #[arg(long, value_enum)]
    class_maps: Option<ClassMaps>,
    /// Where the LiDAR's per-point labels go (the sample preset: native; nuscenes: none).
    #[arg(long, value_enum)]
    labels: Option<Labels>,
    /// Write the damaged recordings (`recordings/damaged/`, from a short drive) into this
    /// directory instead of the sample drives.
    #[arg(long, value_name = "DIR")]
    damaged: Option<PathBuf>,
}

impl Args {
    /// The drive options the flags ask for.
    pub fn drive_options(&self) -> anyhow::Result<DriveOptions> {
        let mut options = match self.preset {
            Preset::Sample => {
                let mut options = DriveOptions::default();
                if let Some(size) = &self.image_size {
                    options.image_size = parse_size(size)?;
                }
                options
            }
            Preset::Nuscenes => {
                let (w, h) = parse_size(self.image_size.as_deref().unwrap_or("800x450"))?;
                DriveOptions::nuscenes(w, h)
            }
        };
        let secs = self.duration_secs.or_else(|| {
            self.keyframes
                .map(|k| f64::from(k) * superflow_schemas::time::KEYFRAME_INTERVAL_SECS)
        });
        if let Some(secs) = secs {
            anyhow::ensure!(
                (0.05..=3600.0).contains(&secs),
                "--duration-secs must be 0.05..=3600 (one LiDAR sweep at least), --keyframes 1..=7200"
            );
            options.duration_nanos = (secs * 1e9).round() as i64;
        }
        if let Some(labels) = self.labels {
            options.labels = match labels {
                Labels::None => LidarLabels::None,
                Labels::Native => LidarLabels::Native,
                Labels::InCloud => LidarLabels::InCloud,
                Labels::Sidecar => LidarLabels::Sidecar,
            };
        }
        if let Some(cameras) = self.cameras {
            anyhow::ensure!((1..=6).contains(&cameras), "--cameras must be 1..=6");
            options.cameras = cameras;
        }
        if let Some(beams) = self.beams {
            anyhow::ensure!((2..=128).contains(&beams), "--beams must be 2..=128");
            options.beams = beams;
        }
        if let Some(trigger) = self.trigger {
            options.camera_trigger = match trigger {
                Trigger::Fixed => CameraTrigger::Fixed,
                Trigger::Staggered => CameraTrigger::Staggered,
            };
        }
        if let Some(class_maps) = self.class_maps {
            options.class_maps = match class_maps {
                ClassMaps::InDrive => ClassMapStorage::InDrive,
                ClassMaps::PngSidecar => ClassMapStorage::PngSidecar,
            };
        }
        if self.preset == Preset::Sample {
            // Never over the sample drives: a drive of another length or rig is named after
            // what differs.
            options.name = options.sample_name();
        }
        Ok(options)
    }
}

/// Parses `WxH` (`800x450`) into a non-zero size JPEG can hold.
fn parse_size(text: &str) -> anyhow::Result<(u32, u32)> {
    let invalid = || anyhow::anyhow!("--image-size {text:?}: expected WxH, e.g. 800x450");
    let (w, h) = text
        .split_once(['x', 'X'])
        .ok_or_else(invalid)
        .and_then(|(w, h)| Ok((w.trim().parse::<u32>()?, h.trim().parse::<u32>()?)))
        .map_err(|_: anyhow::Error| invalid())?;
    anyhow::ensure!(
        (16..=8192).contains(&w) && (16..=8192).contains(&h),
        "--image-size {text:?}: each side must be 16..=8192 pixels"
    );
    Ok((w, h))
}

/// Writes `bytes` to `dir/name`; returns the path.
fn write(dir: &Path, name: &str, bytes: &[u8]) -> anyhow::Result<PathBuf> {
    let path = dir.join(name);
    std::fs::write(&path, bytes).with_context(|| format!("writing {}", path.display()))?;
    Ok(path)
}

/// Writes a generated drive's files into `dir`; returns the drive's path.
fn write_drive(
    dir: &Path,
    options: &DriveOptions,
    dialect: Dialect,
    drive: &GeneratedDrive,
) -> anyhow::Result<PathBuf> {
    let stem = options.drive_name(dialect);
    let mcap = write(dir, &format!("{stem}.mcap"), &drive.mcap)?;
    if let (Some(bytes), Some(name)) = (&drive.sidecar, options.sidecar_name(dialect)) {
        let path = write(dir, &name, bytes)?;
        tracing::info!(sidecar = %path.display(), bytes = bytes.len(), "wrote class-map sidecar");
    }
    if let (Some(bytes), Some(name)) = (&drive.labels_sidecar, options.labels_sidecar_name(dialect))
    {
        let path = write(dir, &name, bytes)?;
        tracing::info!(sidecar = %path.display(), bytes = bytes.len(), "wrote labels sidecar");
    }
    write(dir, &format!("{stem}.truth.json"), &drive.truth_json()?)?;
    Ok(mcap)
}

/// Writes what `args` ask for: the damaged recordings, or the drives of each dialect with
/// their sidecars and ground truth.
pub fn run(args: &Args) -> anyhow::Result<()> {
    if let Some(dir) = &args.damaged {
        for file in damaged::write_damaged(dir)? {
            tracing::info!(
                file = %dir.join(&file.name).display(),
                bytes = file.bytes.len(),
                damage = %file.damage,
                "wrote damaged recording"
            );
        }
        return Ok(());
    }
    let options = args.drive_options()?;
    std::fs::create_dir_all(&args.out)
        .with_context(|| format!("creating {}", args.out.display()))?;
    for dialect in Dialect::ALL {
        if args.dialect.is_some_and(|d| d != dialect) {
            continue;
        }
        let started = std::time::Instant::now();
        let drive = generate_with(dialect, &options)?;
        let path = write_drive(&args.out, &options, dialect, &drive)?;
        let sweeps = &drive.truth.lidar.sweeps;
        let points: u64 = sweeps.iter().map(|s| s.points).sum();
        tracing::info!(
            drive = %path.display(),
            bytes = drive.mcap.len(),
            sweeps = sweeps.len(),
            points_per_sweep = points / (sweeps.len().max(1) as u64),
            landmarks = drive.truth.landmarks.len(),
            secs = started.elapsed().as_secs_f64(),
            "wrote drive"
        );
    }
    Ok(())
}
