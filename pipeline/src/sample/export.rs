//! A sample on disk, for looking at it: `.npy` arrays (numpy's format), `sample.json`
//! with what was chosen, and for every chosen image two PNGs — projected points coloured
//! by depth, and the superpixels with the points in their superpixel's colour. Those
//! pictures are how a user checks a calibration.

use super::recipe::SampleConfig;
use super::types::{Cloud, Frame, Sample};
use npyz::WriterBuilder;
use serde_json::json;
use std::fs::File;
use std::io::{BufWriter, Write};
use std::path::{Path, PathBuf};

/// Writing a sample failed.
#[derive(Debug, thiserror::Error)]
#[error("{path}: {source}")]
pub struct ExportError {
    /// The file.
    pub path: PathBuf,
    /// The error.
    pub source: std::io::Error,
}

fn io_error(path: &Path) -> impl FnOnce(std::io::Error) -> ExportError + '_ {
    move |source| ExportError {
        path: path.to_path_buf(),
        source,
    }
}

/// Writes one `.npy` array of `shape` from row-major `items`.
fn npy<T: npyz::AutoSerialize + Copy>(
    dir: &Path,
    name: &str,
    shape: &[u64],
    items: impl IntoIterator<Item = T>,
) -> Result<(), ExportError> {
    let path = dir.join(format!("{name}.npy"));
    let err = io_error(&path);
    let file = File::create(&path).map_err(|e| io_error(&path)(e))?;
    let write = || -> std::io::Result<()> {
        let mut out = BufWriter::new(file);
        let mut w = npyz::WriteOptions::new()
            .default_dtype()
            .shape(shape)
            .writer(&mut out)
            .begin_nd()?;
        w.extend(items)?;
        w.finish()?;
        out.flush()
    };
    write().map_err(err)
}

fn write_png(path: &Path, width: u32, height: u32, rgb: &[u8]) -> Result<(), ExportError> {
    let file = File::create(path).map_err(io_error(path))?;
    let mut encoder = png::Encoder::new(BufWriter::new(file), width, height);
    encoder.set_color(png::ColorType::Rgb);
    encoder.set_depth(png::BitDepth::Eight);
    let result = encoder
        .write_header()
        .and_then(|mut w| w.write_image_data(rgb).and_then(|()| w.finish()));
    result.map_err(|e| ExportError {
        path: path.to_path_buf(),
        source: std::io::Error::other(e),
    })
}

/// A perceptual-ish colour ramp (blue → cyan → green → yellow → red) for `x` in 0..1.
pub fn ramp(x: f32) -> [u8; 3] {
    let x = x.clamp(0.0, 1.0) * 4.0;
    let (r, g, b) = match x {
        x if x < 1.0 => (0.0, x, 1.0),
        x if x < 2.0 => (0.0, 1.0, 2.0 - x),
        x if x < 3.0 => (x - 2.0, 1.0, 0.0),
        x => (1.0, 4.0 - x, 0.0),
    };
    [(r * 255.0) as u8, (g * 255.0) as u8, (b * 255.0) as u8]
}

/// A stable, well-spread colour for an id.
pub fn id_colour(id: u32) -> [u8; 3] {
    let mut h = u64::from(id).wrapping_mul(0x9E37_79B9_7F4A_7C15);
    h ^= h >> 29;
    [
        (h >> 8) as u8 | 0x30,
        (h >> 24) as u8 | 0x30,
        (h >> 40) as u8 | 0x30,
    ]
}

fn dot(img: &mut [u8], width: usize, height: usize, row: usize, col: usize, c: [u8; 3]) {
    for r in row..(row + 2).min(height) {
        for k in col..(col + 2).min(width) {
            img[(r * width + k) * 3..][..3].copy_from_slice(&c);
        }
    }
}

fn cloud_arrays(dir: &Path, prefix: &str, cloud: &Cloud) -> Result<(), ExportError> {
    let n = cloud.xyz.len() as u64;
    npy(
        dir,
        &format!("{prefix}_points"),
        &[n, 4],
        cloud
            .xyz
            .iter()
            .zip(&cloud.intensity)
            .flat_map(|(p, i)| [p[0], p[1], p[2], *i]),
    )?;
    let p = &cloud.pairings;
    let np = p.len() as u64;
    npy(
        dir,
        &format!("{prefix}_pairing_point"),
        &[np],
        p.iter().map(|q| q.point),
    )?;
    npy(
        dir,
        &format!("{prefix}_pairing_camera"),
        &[np],
        p.iter().map(|q| q.camera),
    )?;
    npy(
        dir,
        &format!("{prefix}_pairing_uv"),
        &[np, 2],
        p.iter().flat_map(|q| [q.u, q.v]),
    )?;
    npy(
        dir,
        &format!("{prefix}_pairing_rowcol"),
        &[np, 2],
        p.iter().flat_map(|q| [q.row, q.col]),
    )?;
    npy(
        dir,
        &format!("{prefix}_pairing_depth"),
        &[np],
        p.iter().map(|q| q.depth),
    )?;
    npy(
        dir,
        &format!("{prefix}_pairing_superpixel"),
        &[np],
        p.iter().map(|q| q.superpixel),
    )?;
    let v = &cloud.voxels;
    npy(
        dir,
        &format!("{prefix}_voxel_coords"),
        &[v.coords.len() as u64, 3],
        v.coords.iter().flatten().copied(),
    )?;
    npy(
        dir,
        &format!("{prefix}_voxel_features"),
        &[v.coords.len() as u64, 4],
        cloud.voxel_features.iter().flatten().copied(),
    )?;
    npy(
        dir,
        &format!("{prefix}_point_to_voxel"),
        &[n],
        v.point_to_voxel.iter().copied(),
    )
}

fn cloud_json(cloud: &Cloud) -> serde_json::Value {
    json!({
        "points": cloud.xyz.len(),
        "pairings": cloud.pairings.len(),
        "voxels": cloud.voxels.coords.len(),
        "augmentation": cloud.augmentation,
        "levels": cloud.levels.iter().map(|l| json!({
            "stride": l.stride,
            "voxels": l.coords.len(),
            "neighbour_pairs": l.neighbours.pairs.len(),
            "down_pairs": l.down.as_ref().map(|d| d.pairs.len()),
        })).collect::<Vec<_>>(),
    })
}

fn overlays(
    dir: &Path,
    f: usize,
    frame: &Frame,
    config: &SampleConfig,
) -> Result<Vec<String>, ExportError> {
    let (w, h) = (config.image_width as usize, config.image_height as usize);
    let mut names = Vec::new();
    for (slot, image) in frame.images.iter().enumerate() {
        let mut by_depth = image.rgb.clone();
        let mut by_superpixel: Vec<u8> = image
            .rgb
            .chunks_exact(3)
            .zip(&image.superpixels)
            .flat_map(|(px, id)| {
                let c = id_colour(*id);
                [0, 1, 2].map(|k| ((u16::from(px[k]) + u16::from(c[k])) / 2) as u8)
            })
            .collect();
        for p in frame
            .cloud
            .pairings
            .iter()
            .filter(|p| p.camera as usize == slot)
        {
            let depth = (p.depth.max(1.0).ln() / 60f32.ln()).clamp(0.0, 1.0);
            let (r, c) = (p.row as usize, p.col as usize);
            dot(&mut by_depth, w, h, r, c, ramp(depth));
            dot(&mut by_superpixel, w, h, r, c, id_colour(p.superpixel));
        }
        for (kind, img) in [("depth", by_depth), ("superpixels", by_superpixel)] {
            let name = format!("frame{f}_cam{slot}_{}_{kind}.png", image.camera);
            write_png(&dir.join(&name), w as u32, h as u32, &img)?;
            names.push(name);
        }
    }
    Ok(names)
}

/// `sample.json`'s entry of one temporal frame.
fn frame_json(frame: &Frame) -> serde_json::Value {
    let mut cloud = cloud_json(&frame.cloud);
    cloud["offset_dt"] = json!(frame.offset);
    cloud["sweep"] = json!(frame.sweep);
    cloud["lidar_stamp_nanos"] = json!(frame.lidar_stamp.nanos());
    cloud["num_superpixels"] = json!(frame.num_superpixels);
    cloud["dropped_non_finite"] = json!(frame.dropped_non_finite);
    cloud["images"] = frame
        .images
        .iter()
        .map(|i| {
            json!({
                "camera": i.camera,
                "topic": i.topic,
                "stamp_nanos": i.stamp.nanos(),
                "scan_offset_ms": i.scan_offset_nanos as f64 * 1e-6,
                "native_width": i.native_size.0,
                "native_height": i.native_size.1,
                "flipped": i.flipped,
                "distortion": i.calibration.distortion.model_name(),
            })
        })
        .collect();
    cloud
}

/// `sample.json`'s entry of the dense cloud.
fn dense_json(sample: &Sample) -> serde_json::Value {
    let mut dense = cloud_json(&sample.dense);
    dense["stamps_nanos"] = json!(
        sample
            .dense_stamps
            .iter()
            .map(|s| s.nanos())
            .collect::<Vec<_>>()
    );
    dense["missing_sweeps"] = json!(sample.dense_missing);
    dense["dropped_non_finite"] = json!(sample.dense_dropped_non_finite);
    dense["points_per_sweep"] = json!(
        (0..sample.dense_stamps.len())
            .map(|s| sample
                .dense
                .source_sweep
                .iter()
                .filter(|&&x| x as usize == s)
                .count())
            .collect::<Vec<_>>()
    );
    dense
}

/// Writes `sample` into `dir` (created if needed): arrays `frame{f}_*` for each temporal
/// frame (time order) and `dense_*`, `sample.json`, and overlay PNGs. Returns the paths
/// written.
pub fn write_sample(
    sample: &Sample,
    config: &SampleConfig,
    drive_files: &str,
    dir: &Path,
) -> Result<Vec<PathBuf>, ExportError> {
    std::fs::create_dir_all(dir).map_err(io_error(dir))?;
    let (w, h) = (
        u64::from(config.image_width),
        u64::from(config.image_height),
    );
    let mut frames_json = Vec::new();
    let mut pngs = Vec::new();
    for (f, frame) in sample.frames.iter().enumerate() {
        let prefix = format!("frame{f}");
        cloud_arrays(dir, &prefix, &frame.cloud)?;
        let k = frame.images.len() as u64;
        npy(
            dir,
            &format!("{prefix}_images"),
            &[k, h, w, 3],
            frame.images.iter().flat_map(|i| i.rgb.iter().copied()),
        )?;
        npy(
            dir,
            &format!("{prefix}_superpixels"),
            &[k, h, w],
            frame
                .images
                .iter()
                .flat_map(|i| i.superpixels.iter().copied()),
        )?;
        pngs.extend(overlays(dir, f, frame, config)?);
        frames_json.push(frame_json(frame));
    }
    cloud_arrays(dir, "dense", &sample.dense)?;
    npy(
        dir,
        "dense_source_sweep",
        &[sample.dense.source_sweep.len() as u64],
        sample.dense.source_sweep.iter().copied(),
    )?;
    let doc = json!({
        "format": "superflow.sample/1",
        "drive": drive_files,
        "id": sample.id,
        "seed": sample.seed,
        "cameras": sample.cameras,
        "key_frame": sample.key_frame,
        "superpixels": if sample.class_superpixels { "class_map" } else { "slic" },
        "frames": frames_json,
        "dense": dense_json(sample),
        "stage_nanos": sample.times,
        "config": config,
        "png": pngs,
    });
    let path = dir.join("sample.json");
    let text = serde_json::to_string_pretty(&doc).map_err(|e| ExportError {
        path: path.clone(),
        source: std::io::Error::other(e),
    })?;
    std::fs::write(&path, text).map_err(io_error(&path))?;
    let mut written: Vec<PathBuf> = std::fs::read_dir(dir)
        .map_err(io_error(dir))?
        .filter_map(|e| e.ok().map(|e| e.path()))
        .collect();
    written.sort();
    Ok(written)
}
