//! SLIC superpixels computed once per drive: `superflow-pipeline superpixels` writes a
//! `<drive>.slic.mcap` sidecar, and samples read their superpixels from it instead of
//! running SLIC on every image of every epoch (milliseconds an image, and a sample has
//! several images: a large part of the time of a sample that computes them).
//!
//! Each camera image of the drive is decoded, resized to the recipe's size exactly as a
//! sample does, segmented with the recipe's SLIC settings, and stored as a 16-bit grey
//! PNG of its labels in a `foxglove.CompressedImage` on `<image topic>/superflow_slic`,
//! stamped like the image. The channel's metadata names the image topic
//! ([`SLIC_IMAGE_TOPIC_KEY`]) and the settings ([`SLIC_SETTINGS_KEY`]); a sample uses the
//! sidecar only when they are the recipe's (else it runs SLIC itself and says so once).
//!
//! A sample that flips an image mirrors the stored labels, where SLIC run on the flipped
//! image would give nearly — not exactly — the mirrored segmentation (SLIC is not
//! mirror-symmetric); unflipped images get exactly the labels SLIC gives.

use super::error::SuperpixelsFault;
use super::recipe::SampleConfig;
use super::slic::slic;
use crate::decode::foxglove::{CompressedImage, Timestamp, decode};
use crate::decode::image::Target;
use crate::drive::SlicStream;
use crate::drive::discover::{SLIC_IMAGE_TOPIC_KEY, SLIC_SETTINGS_KEY};
use crate::drive::{CameraStream, Drive, FrameRef};
use crate::source::ChunkCache;
use foxglove::Encode;
use prost::Message as _;
use rayon::prelude::*;
use std::collections::BTreeMap;
use std::io::{BufWriter, Cursor};
use std::path::{Path, PathBuf};
use superflow_schemas::sensor::PixelFormat;

/// The sidecar's tag: `<drive>.slic.mcap`.
pub const SIDECAR_TAG: &str = "slic";

/// Images segmented between two writes (bounds memory; keeps the file in time order).
const BATCH: usize = 64;

/// What can go wrong writing a sidecar.
#[derive(Debug, thiserror::Error)]
pub enum SuperpixelsError {
    /// An image could not be read or decoded.
    #[error(transparent)]
    Read(#[from] crate::drive::ReadError),
    /// An image that cannot be segmented, or whose labels cannot be stored.
    #[error("{file}: {topic} at {stamp_ns} ns: {reason}")]
    Image {
        /// The drive's files.
        file: String,
        /// Image topic.
        topic: String,
        /// Image stamp.
        stamp_ns: i64,
        /// What is wrong.
        #[source]
        reason: ImageFailure,
    },
    /// Writing the sidecar failed.
    #[error("writing {path}: {source}")]
    Write {
        /// The sidecar.
        path: PathBuf,
        /// What failed.
        #[source]
        source: WriteFailure,
    },
}

/// Why an image cannot be segmented or its labels stored ([`SuperpixelsError::Image`]).
#[derive(Debug, thiserror::Error)]
pub enum ImageFailure {
    /// The image did not decode to RGB.
    #[error("not decoded as RGB")]
    NotRgb,
    /// A label that does not fit the PNG's 16-bit samples.
    #[error("label {0} does not fit 16 bits")]
    Label(u32),
    /// The PNG encoder.
    #[error(transparent)]
    Png(#[from] png::EncodingError),
    /// A stamp that a `foxglove.CompressedImage` cannot hold.
    #[error("stamp before 1970 or after 2106")]
    Stamp,
}

/// What failed writing a sidecar ([`SuperpixelsError::Write`]).
#[derive(Debug, thiserror::Error)]
pub enum WriteFailure {
    /// Creating, writing or renaming the file.
    #[error(transparent)]
    Io(#[from] std::io::Error),
    /// The MCAP writer.
    #[error(transparent)]
    Mcap(#[from] mcap::McapError),
    /// The message type has no schema to register.
    #[error("no schema for foxglove.CompressedImage")]
    NoSchema,
}

/// The settings a sidecar's labels depend on, as stored in its channel metadata.
pub fn settings_key(config: &SampleConfig) -> String {
    serde_json::json!({
        "version": 1,
        "width": config.image_width,
        "height": config.image_height,
        "image_reduced_decode": config.image_reduced_decode,
        "slic": config.slic,
    })
    .to_string()
}

/// Where the sidecar of `drive` goes: `<first file's stem>.slic.mcap` beside it.
pub fn sidecar_path(drive: &Drive) -> Option<PathBuf> {
    let suffix = format!(".{SIDECAR_TAG}.mcap");
    let main = drive.files.iter().map(|f| f.path()).find(|p| {
        !p.file_name()
            .and_then(|n| n.to_str())
            .is_some_and(|n| n.ends_with(&suffix))
    })?;
    let stem = main.file_stem()?.to_str()?;
    Some(main.with_file_name(format!("{stem}{suffix}")))
}

/// Whether every camera of `drive` has precomputed SLIC superpixels for `config`.
pub fn sidecar_matches(drive: &Drive, config: &SampleConfig) -> bool {
    let key = settings_key(config);
    !drive.cameras.is_empty()
        && drive
            .cameras
            .iter()
            .all(|c| c.slic.as_ref().is_some_and(|s| s.settings == key))
}

/// What [`write_sidecar`] wrote.
#[derive(Debug, Clone, PartialEq, Eq)]
pub struct SidecarSummary {
    /// The file.
    pub path: PathBuf,
    /// Label maps written (one per camera image that decoded).
    pub images: usize,
    /// Images that could not be read or decoded (a sample needing one fails on the
    /// image itself, with or without the sidecar): each error, naming file, topic and
    /// stamp.
    pub skipped: Vec<String>,
    /// Bytes of the file.
    pub bytes: u64,
}

/// The resized (unflipped) image of `frame` that a sample would segment.
fn resized_image(
    drive: &Drive,
    camera: &CameraStream,
    frame: &FrameRef,
    config: &SampleConfig,
    cache: &mut ChunkCache,
) -> Result<Vec<u8>, SuperpixelsError> {
    let scaled =
        drive.read_image_scaled(camera, frame, Target::Rgb, config.decode_scale(), cache)?;
    let image = scaled.image;
    if image.format != PixelFormat::Rgb8 {
        return Err(SuperpixelsError::Image {
            file: drive.file_list(),
            topic: camera.image_topic.clone(),
            stamp_ns: frame.stamp.nanos(),
            reason: ImageFailure::NotRgb,
        });
    }
    Ok(config.resized_rgb(&image, false))
}

/// `labels` (`width × height`, each below 2¹⁶) as a 16-bit grey PNG.
fn encode_labels(labels: &[u32], width: u32, height: u32) -> Result<Vec<u8>, ImageFailure> {
    let mut samples = Vec::with_capacity(labels.len() * 2);
    for &l in labels {
        let l = u16::try_from(l).map_err(|_| ImageFailure::Label(l))?;
        samples.extend_from_slice(&l.to_be_bytes());
    }
    let mut out = Vec::new();
    let mut encoder = png::Encoder::new(Cursor::new(&mut out), width, height);
    encoder.set_color(png::ColorType::Grayscale);
    encoder.set_depth(png::BitDepth::Sixteen);
    // "Up" rows (mostly zeros for label maps) unfilter as one vector add; the adaptive
    // choice picks Paeth, whose unfiltering is sequential (each byte waits for its left
    // neighbour), which makes reading a map slow.
    encoder.set_filter(png::Filter::Up);
    let mut writer = encoder.write_header()?;
    writer.write_image_data(&samples)?;
    writer.finish()?;
    Ok(out)
}

/// Decodes a label map written by [`encode_labels`]: the labels and their count
/// (largest + 1). `Err` says what is wrong.
fn decode_labels(
    png_bytes: &[u8],
    width: u32,
    height: u32,
) -> Result<(Vec<u32>, u32), SuperpixelsFault> {
    let decoder = png::Decoder::new(Cursor::new(png_bytes));
    let mut reader = decoder.read_info().map_err(SuperpixelsFault::Png)?;
    let info = reader.info();
    if (info.color_type, info.bit_depth) != (png::ColorType::Grayscale, png::BitDepth::Sixteen) {
        return Err(format!(
            "a {:?} {}-bit PNG, not 16-bit grey labels",
            info.color_type, info.bit_depth as u8
        )
        .into());
    }
    if (info.width, info.height) != (width, height) {
        return Err(format!(
            "labels are {}x{}, the recipe's images {width}x{height}",
            info.width, info.height
        )
        .into());
    }
    let mut samples = vec![0u8; 2 * width as usize * height as usize];
    reader
        .next_frame(&mut samples)
        .map_err(SuperpixelsFault::Png)?;
    let mut labels = Vec::with_capacity(samples.len() / 2);
    let mut largest = None;
    for b in samples.chunks_exact(2) {
        let label = u16::from_be_bytes([b[0], b[1]]);
        largest = largest.max(Some(label));
        labels.push(u32::from(label));
    }
    Ok((labels, largest.map_or(0, |m| u32::from(m) + 1)))
}

/// Reads the labels of the image stamped `stamp` from `stream` (sized `width × height`,
/// not flipped) and their count. `Err` says what is missing or wrong.
pub fn read_labels(
    drive: &Drive,
    stream: &SlicStream,
    stamp: superflow_schemas::Stamp,
    (width, height): (u32, u32),
    cache: &mut ChunkCache,
) -> Result<(Vec<u32>, u32), SuperpixelsFault> {
    let i = stream.frames.partition_point(|f| f.stamp < stamp);
    let frame = stream
        .frames
        .get(i)
        .filter(|f| f.stamp == stamp)
        .ok_or_else(|| {
            SuperpixelsFault::from("no precomputed SLIC labels for this image".to_string())
        })?;
    let message = drive
        .read_raw(frame, cache)
        .map_err(SuperpixelsFault::Read)?;
    let msg: CompressedImage =
        decode("foxglove.CompressedImage", message.data).map_err(SuperpixelsFault::Decode)?;
    decode_labels(&msg.data, width, height)
}

/// Segments every camera image of `drive` with `config`'s SLIC settings and writes the
/// labels to `path`; `progress` is called once per image.
pub fn write_sidecar(
    drive: &Drive,
    config: &SampleConfig,
    path: &Path,
    progress: &(dyn Fn() + Sync),
) -> Result<SidecarSummary, SuperpixelsError> {
    let write_error = |source: WriteFailure| SuperpixelsError::Write {
        path: path.to_path_buf(),
        source,
    };
    // Every image of every camera, in time order.
    let mut work: Vec<(usize, FrameRef)> = drive
        .cameras
        .iter()
        .enumerate()
        .flat_map(|(c, cam)| cam.frames.iter().map(move |f| (c, *f)))
        .collect();
    work.sort_by_key(|(c, f)| (f.stamp, *c));

    let tmp = path.with_extension("mcap.partial");
    let file = std::fs::File::create(&tmp).map_err(|e| write_error(e.into()))?;
    let mut writer = mcap::WriteOptions::new()
        .profile("")
        .library(format!("superflow-pipeline/{}", env!("CARGO_PKG_VERSION")))
        // PNG is compressed already: chunks stay plain, so reading one label map reads
        // its bytes instead of decompressing a chunk of a hundred.
        .compression(None)
        .create(BufWriter::new(file))
        .map_err(|e| write_error(e.into()))?;
    let schema =
        CompressedImage::get_schema().ok_or_else(|| write_error(WriteFailure::NoSchema))?;
    let schema_id = writer
        .add_schema(&schema.name, &schema.encoding, &schema.data)
        .map_err(|e| write_error(e.into()))?;
    let settings = settings_key(config);
    let mut channels = Vec::with_capacity(drive.cameras.len());
    for cam in &drive.cameras {
        let metadata = BTreeMap::from([
            (SLIC_IMAGE_TOPIC_KEY.to_string(), cam.image_topic.clone()),
            (SLIC_SETTINGS_KEY.to_string(), settings.clone()),
        ]);
        let topic = format!("{}/superflow_slic", cam.image_topic.trim_end_matches('/'));
        channels.push(
            writer
                .add_channel(schema_id, &topic, "protobuf", &metadata)
                .map_err(|e| write_error(e.into()))?,
        );
    }
    let mut sequences = vec![0u32; channels.len()];
    let mut skipped = Vec::new();
    for batch in work.chunks(BATCH) {
        let encoded = batch
            .par_iter()
            .map_init(
                || ChunkCache::new(2),
                |cache, (c, frame)| {
                    let labelled = labelled_image(drive, &drive.cameras[*c], frame, config, cache);
                    progress();
                    labelled
                },
            )
            .collect::<Result<Vec<_>, SuperpixelsError>>()?;
        for ((c, frame), data) in batch.iter().zip(encoded) {
            let data = match data {
                Ok(data) => data,
                Err(e) => {
                    tracing::warn!("no SLIC labels for an image that does not decode: {e}");
                    skipped.push(e);
                    continue;
                }
            };
            sequences[*c] += 1;
            let time = u64::try_from(frame.stamp.nanos()).unwrap_or_default();
            writer
                .write_to_known_channel(
                    &mcap::records::MessageHeader {
                        channel_id: channels[*c],
                        sequence: sequences[*c],
                        log_time: time,
                        publish_time: time,
                    },
                    &data,
                )
                .map_err(|e| write_error(e.into()))?;
        }
    }
    writer.finish().map_err(|e| write_error(e.into()))?;
    drop(writer);
    std::fs::rename(&tmp, path).map_err(|e| write_error(e.into()))?;
    let bytes = std::fs::metadata(path).map_or(0, |m| m.len());
    Ok(SidecarSummary {
        path: path.to_path_buf(),
        images: work.len() - skipped.len(),
        skipped,
        bytes,
    })
}

/// The encoded `foxglove.CompressedImage` of the SLIC labels of image `frame` of
/// `camera`; `Ok(Err(why))` when the image does not read or decode (skipped).
fn labelled_image(
    drive: &Drive,
    camera: &CameraStream,
    frame: &FrameRef,
    config: &SampleConfig,
    cache: &mut ChunkCache,
) -> Result<Result<Vec<u8>, String>, SuperpixelsError> {
    let rgb = match resized_image(drive, camera, frame, config, cache) {
        Ok(rgb) => rgb,
        Err(e) => return Ok(Err(e.to_string())),
    };
    let (width, height) = (config.image_width, config.image_height);
    let image_error = |reason: ImageFailure| SuperpixelsError::Image {
        file: drive.file_list(),
        topic: camera.image_topic.clone(),
        stamp_ns: frame.stamp.nanos(),
        reason,
    };
    let seg = slic(&rgb, width as usize, height as usize, &config.slic);
    let png = encode_labels(&seg.labels, width, height).map_err(image_error)?;
    let (sec, nsec) = frame.stamp.to_sec_nanosec();
    let timestamp = u32::try_from(sec)
        .ok()
        .and_then(|sec| Timestamp::new_checked(sec, nsec))
        .ok_or_else(|| image_error(ImageFailure::Stamp))?;
    Ok(Ok(CompressedImage {
        timestamp: Some(timestamp),
        frame_id: camera.frame_id.clone(),
        data: png.into(),
        format: "png".into(),
    }
    .encode_to_vec()))
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn labels_survive_the_png_and_wrong_ones_are_named() {
        let labels: Vec<u32> = (0..6 * 4).map(|i| (i * 2_731) % 60_001).collect();
        let png = encode_labels(&labels, 6, 4).unwrap();
        let (back, count) = decode_labels(&png, 6, 4).unwrap();
        assert_eq!(back, labels);
        assert_eq!(count, labels.iter().max().unwrap() + 1);
        assert!(
            decode_labels(&png, 4, 6)
                .unwrap_err()
                .to_string()
                .contains("6x4")
        );
        assert!(
            encode_labels(&[70_000], 1, 1)
                .unwrap_err()
                .to_string()
                .contains("70000")
        );
        assert!(decode_labels(&png[..png.len() / 2], 6, 4).is_err());
    }
}
