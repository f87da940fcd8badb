//! The pipeline on nuScenes-sized drives: samples/s on one core and on all cores, where
//! the time of a sample goes (ms per stage), SLIC instead of class maps, and the batch
//! write against one plain write of its bytes.
//!
//! `cargo bench -p superflow-pipeline --bench speed` (options: `-- --samples N` (48),
//! `--slic-samples N` (12), `--sizes 800x450,1600x900`, `--ros2-sizes 800x450`,
//! `--columns N` (LiDAR columns a sweep, 1084: ~33 k returns; 700 gives the ~21 k of a
//! nuScenes sweep), `--kernel-maps none` (the recipe's `kernel_maps`: level-0 voxels
//! only, for networks that build their own maps; `unet`, every level's, by default),
//! `--regenerate`).
//!
//! `--loop N` builds N class-map samples of the first size one after the other on one
//! thread (after a warm-up epoch) and prints ms a sample and its stages, nothing else:
//! the run to profile (`perf record`) and to alternate between two builds.
//!
//! A last table sets a sample's decoding beside what the libraries alone cost for the same
//! work (`speed/floor.rs`): the chunks and bytes a sample decompresses (counted) at
//! libzstd's speed on the drive's chunks, and its JPEGs and PNG class maps decoded by
//! libjpeg-turbo and the `png` crate on their own.
//!
//! It also draws where a class-map sample's time goes on one core, drive by drive
//! (`target/bench-drives/speed.svg`, `speed/chart.rs`): the libraries' part of decoding,
//! the rest of decoding, and the pipeline's stages, against the target for that camera
//! size.
//!
//! SLIC is measured twice: computed per sample, and read from the `<drive>.slic.mcap`
//! sidecar that `superflow-pipeline superpixels` writes (written once into
//! `target/bench-drives/…/slic/`, beside a link to the drive).
//!
//! The drives come from the generator (`superflow-recordings --preset nuscenes`): a
//! 32-beam LiDAR at 20 Hz (~33 k returns a sweep, its lasers firing 1.152 µs apart as an
//! HDL-32E's), six JPEG cameras at ~12 Hz triggered as the beam passes them, class maps
//! as PNG in a `<drive>.superpixels.mcap` sidecar, zstd chunks; in the nuscenes2mcap
//! layout (Foxglove protobuf, motion-compensated sweeps, undistorted images) at each
//! `--sizes`, and as a rosbag2 recording (CDR, raw sweeps with a time per point that
//! the pipeline de-skews, distorted images) at each `--ros2-sizes`, class maps only
//! (SLIC does not depend on the layout). They are written once under
//! `target/bench-drives/v<generator version>-<compression>-<JPEG coding>-<chunk
//! size>-<length>-beams<interval>/` (8 s each) and reused while all of these are the
//! same.

#[path = "speed/chart.rs"]
mod chart;
#[allow(dead_code)]
#[path = "../../tests/src/bench/common.rs"]
mod common;
#[path = "speed/floor.rs"]
mod floor;
#[path = "speed/order.rs"]
mod order;
#[allow(dead_code)]
#[path = "../../tests/src/bench/sample.rs"]
mod sample;
#[allow(dead_code)]
#[path = "../../tests/src/bench/transport.rs"]
mod transport;

use common::{arg_count, arg_value, cores, flag, load_average};
use sample::{one_and_all, stage_cells, stage_ms, throughput};
use std::path::PathBuf;
use std::time::Instant;
use superflow_pipeline::batch::{BatchPlan, BatchShape};
use superflow_pipeline::drive::{Dataset, IngestConfig};
use superflow_pipeline::sample::recipe::{KernelMaps, SuperpixelSource};
use superflow_pipeline::sample::sidecar;
use superflow_pipeline::sample::{Sample, SampleBuilder, SampleConfig};
use superflow_recordings::{Dialect, DriveOptions, GENERATOR_VERSION, generate_with};

/// The pipeline binary's allocator (see `superflow_pipeline::memory`).
#[global_allocator]
static ALLOCATOR: superflow_common::memory::Allocator = superflow_common::memory::Allocator;

/// Samples in the batch of the batch-write measurement (the service's default).
const BATCH: usize = 4;

/// Writes (or finds) the nuScenes-sized drive of `width × height` in `dialect`; returns
/// its path.
fn drive(
    dialect: Dialect,
    width: u32,
    height: u32,
    columns: Option<usize>,
    regenerate: bool,
) -> anyhow::Result<PathBuf> {
    let mut options = DriveOptions::nuscenes(width, height);
    let default_columns = options.lidar_columns;
    if let Some(columns) = columns {
        options.lidar_columns = columns;
    }
    let dir = PathBuf::from(env!("CARGO_MANIFEST_DIR"))
        .join("../target/bench-drives")
        .join(format!(
            "v{GENERATOR_VERSION}-{}-{}-{}k-{}s-beams{}ns",
            options.foxglove_compression.name(),
            options.jpeg_coding.name(),
            options.chunk_size / 1024,
            options.duration_secs(),
            options.beam_interval_nanos
        ))
        .join(if options.lidar_columns == default_columns {
            String::new()
        } else {
            format!("columns{}", options.lidar_columns)
        });
    std::fs::create_dir_all(&dir)?;
    let path = dir.join(format!("{}.mcap", options.drive_name(dialect)));
    if path.exists() && !regenerate {
        return Ok(path);
    }
    let started = Instant::now();
    let generated = generate_with(dialect, &options)?;
    if let (Some(name), Some(bytes)) = (options.sidecar_name(dialect), &generated.sidecar) {
        std::fs::write(dir.join(name), bytes)?;
    }
    std::fs::write(&path, &generated.mcap)?;
    eprintln!(
        "generated {} ({:.1} MB) in {:.1} s",
        path.display(),
        generated.mcap.len() as f64 / 1e6,
        started.elapsed().as_secs_f64()
    );
    Ok(path)
}

/// The drive at `path` beside a SLIC sidecar written by `superflow-pipeline
/// superpixels` (in a `slic/` directory next to it, through a link, so that the plain
/// drive keeps running SLIC per sample), opened.
fn slic_sidecar_drive(path: &std::path::Path, regenerate: bool) -> anyhow::Result<Dataset> {
    let dir = path.with_file_name("slic");
    std::fs::create_dir_all(&dir)?;
    let link = dir.join(path.file_name().unwrap_or_default());
    if !link.exists() {
        std::os::unix::fs::symlink(path, &link)?;
    }
    let dataset = Dataset::open(std::slice::from_ref(&link), &IngestConfig::default())?;
    let config = SampleConfig::default();
    if regenerate || !sidecar::sidecar_matches(&dataset.drives[0], &config) {
        let out = sidecar::sidecar_path(&dataset.drives[0])
            .ok_or_else(|| anyhow::anyhow!("no sidecar path for {}", link.display()))?;
        let started = Instant::now();
        let written = sidecar::write_sidecar(&dataset.drives[0], &config, &out, &|| {})?;
        eprintln!(
            "wrote {} ({} label maps) in {:.1} s",
            out.display(),
            written.images,
            started.elapsed().as_secs_f64()
        );
        return Ok(Dataset::open(
            std::slice::from_ref(&link),
            &IngestConfig::default(),
        )?);
    }
    Ok(dataset)
}

/// A sample's decoding on one core beside the libraries alone: runs of `n` samples on
/// one core (the decode stage of the fastest; the chunks and bytes its files decompressed
/// per sample, counted in the first), and the cost of that work and of the sample's
/// images with libzstd, libjpeg-turbo and `png` alone: the table's row, and those three
/// costs (ms per sample).
fn floor_row(
    name: &str,
    builder: &SampleBuilder<'_>,
    dataset: &Dataset,
    path: &std::path::Path,
    n: usize,
) -> anyhow::Result<(String, [Option<f64>; 3])> {
    let counted = || -> (u64, u64) {
        let files = dataset.drives.iter().flat_map(|d| &d.files);
        files.fold((0, 0), |(c, b), f| {
            let d = f.decompressed();
            (c + d.chunks, b + d.bytes)
        })
    };
    let before = counted();
    let (_, times) = throughput(builder, n, 1)?;
    let after = counted();
    // The decode stage is taken as the fastest of 3 runs too, as the libraries' times
    // are (one run against best-of-3 read up to 1.5× in a slow hour of the VM).
    let mut decode_ns = times.decode;
    for _ in 1..floor::ROUNDS {
        decode_ns = decode_ns.min(throughput(builder, n, 1)?.1.decode);
    }
    let per_sample = |v: u64| v as f64 / n as f64;
    let chunks = per_sample(after.0 - before.0);
    let mb = per_sample(after.1 - before.1) / 1e6;
    let config = builder.config();
    let images = f64::from(config.temporal_frames * config.cameras);
    let (w, h) = (config.image_width as usize, config.image_height as usize);
    let zstd = floor::zstd_ms_per_mb(path)?.map(|ms| ms * mb);
    let jpeg = floor::jpeg_ms(path, w, h)?.map(|ms| ms * images);
    let pngs = floor::png_ms(&path.with_extension("superpixels.mcap"))?;
    let png = pngs.map(|(png_crate, own)| png_crate.min(own) * images);
    let sum: f64 = [zstd, jpeg, png].iter().flatten().sum();
    let cell = |v: Option<f64>| v.map_or("–".into(), |v| format!("{v:.1}"));
    let decode = decode_ns as f64 / 1e6 / n as f64;
    let png_cell = match pngs {
        Some((png_crate, _)) => format!("{} ({:.1})", cell(png), png_crate * images),
        None => cell(None),
    };
    let row = format!(
        "| {name} | {chunks:.1} | {mb:.1} | {} | {} | {png_cell} | {sum:.1} | {decode:.1} | {:.2}× |",
        cell(zstd),
        cell(jpeg),
        decode / sum
    );
    Ok((row, [zstd, jpeg, png]))
}

/// Rounds of the batch-write measurement.
const WRITE_ROUNDS: usize = 31;

/// Producer ms per batch of [`BATCH`] samples (plan + write every section into a
/// zeroed payload, as into a fresh loan), ms of one plain copy of the same bytes, and
/// the ratio; also the batch size in bytes. Each round zeroes the payload (not timed),
/// writes the batch, then copies as many bytes over it: the ratio is the median of the
/// rounds' ratios, which this VM's drift (10–30 % within minutes) moves far less than
/// either time alone.
fn batch_write(samples: &[Sample], shape: BatchShape) -> anyhow::Result<(f64, f64, f64, usize)> {
    let plan = BatchPlan::new(samples, shape)?;
    let len = plan.layout().payload_len();
    let mut payload = vec![0u8; len];
    let source = vec![7u8; len];
    let (mut writes, mut copies, mut ratios) = (Vec::new(), Vec::new(), Vec::new());
    for _ in 0..WRITE_ROUNDS {
        payload.fill(0);
        let t = Instant::now();
        BatchPlan::new(samples, shape)?.write_zeroed(samples, &mut payload)?;
        let write = t.elapsed().as_secs_f64() * 1e3;
        std::hint::black_box(&payload);
        let t = Instant::now();
        payload.copy_from_slice(&source);
        let copy = t.elapsed().as_secs_f64() * 1e3;
        std::hint::black_box(&payload);
        writes.push(write);
        copies.push(copy);
        ratios.push(write / copy);
    }
    Ok((
        common::median(&writes),
        common::median(&copies),
        common::median(&ratios),
        len,
    ))
}

/// The target for a sample of `width × height` cameras on one core, ms
/// (nuScenes' 1600×900 and the 800×450 of its many conversions).
fn target_ms(width: u32, height: u32) -> Option<f64> {
    match (width, height) {
        (800, 450) => Some(20.0),
        (1600, 900) => Some(40.0),
        _ => None,
    }
}

/// `WIDTHxHEIGHT`.
fn parse_size(size: &str) -> anyhow::Result<(u32, u32)> {
    size.split_once('x')
        .and_then(|(w, h)| Some((w.parse::<u32>().ok()?, h.parse::<u32>().ok()?)))
        .ok_or_else(|| anyhow::anyhow!("{size}: expected WIDTHxHEIGHT"))
}

/// Minor page faults of this process so far (`/proc/self/stat`, the 10th field).
fn minor_faults() -> anyhow::Result<u64> {
    let stat = std::fs::read_to_string("/proc/self/stat")?;
    let rest = stat.rsplit_once(')').map_or("", |(_, r)| r);
    let field = rest.split_whitespace().nth(10 - 3).unwrap_or("0");
    Ok(field.parse()?)
}

/// `--loop N`: `n` class-map samples of the drive at `path` one after the other on one
/// thread, after a warm-up epoch; prints ms a sample and its stages. With `--order
/// blocks` the dataset is `copies` copies of the drive in the `blocks` order (the
/// service's defaults) and `n` is rounded up to whole epochs.
fn profile_loop(
    path: &std::path::Path,
    n: usize,
    maps: KernelMaps,
    blocks: Option<usize>,
) -> anyhow::Result<()> {
    let paths = match blocks {
        Some(copies) => order::copies(path, copies)?,
        None => vec![path.to_path_buf()],
    };
    let dataset = Dataset::open(&paths, &IngestConfig::default())?;
    let config = SampleConfig {
        superpixels: SuperpixelSource::Channel,
        kernel_maps: maps,
        ..SampleConfig::default()
    };
    let mut builder = SampleBuilder::new(&dataset, config)?;
    if blocks.is_some() {
        builder = builder.with_order(order::ORDERS[1].1);
    }
    let points: usize = builder
        .build(0, 0)?
        .frames
        .iter()
        .map(|f| f.cloud.xyz.len())
        .sum();
    let len = builder.epoch_len();
    let n = if blocks.is_some() {
        n.div_ceil(len) * len
    } else {
        n
    };
    // Whole epochs in order from epoch 1 (epoch 0 warms up), one thread.
    let pool = rayon::ThreadPoolBuilder::new().num_threads(1).build()?;
    let run = |epochs: std::ops::Range<usize>, count: usize| {
        pool.install(
            || -> anyhow::Result<(f64, superflow_pipeline::sample::StageTimes)> {
                let mut times = superflow_pipeline::sample::StageTimes::default();
                let started = Instant::now();
                for i in epochs.start * len..epochs.start * len + count {
                    times.add(&builder.build((i / len) as u64, (i % len) as u64)?.times);
                }
                Ok((count as f64 / started.elapsed().as_secs_f64(), times))
            },
        )
    };
    run(0..1, len)?;
    let faults = minor_faults()?;
    let (per_s, times) = run(1..2, n)?;
    let faults = minor_faults()? - faults;
    println!(
        "{}: {n} samples on 1 thread{}, {:.0} points a frame: {:.2} ms a sample | {} | {faults} minor faults",
        path.display(),
        if blocks.is_some() { ", blocks" } else { "" },
        points as f64 / builder.config().temporal_frames as f64,
        1e3 / per_s,
        stage_cells(&times, n)
    );
    Ok(())
}

/// `--orders`: the `global` and `blocks` orders side by side at each size, in the
/// builder and in the service (`speed/order.rs`).
fn orders(
    sizes: &str,
    columns: Option<usize>,
    maps: KernelMaps,
    regenerate: bool,
) -> anyhow::Result<()> {
    println!(
        "850 drives of 40 keyframes (nuScenes' trainval), one epoch, the orders alone (3 seeds)"
    );
    println!(
        "| ranks × batch | order | open blocks | distinct drives in a global batch % | rank batches from distinct blocks % | steps a block stays open on its rank |"
    );
    println!("|---|---|---:|---:|---:|---:|");
    for row in order::statistics() {
        println!("{row}");
    }
    println!();
    let copies = arg_count("--copies")?.unwrap_or(3);
    let epochs = arg_count("--epochs")?.unwrap_or(3) as u64;
    let cores = cores();
    let binary = PathBuf::from(env!("CARGO_BIN_EXE_superflow-pipeline"));
    println!(
        "{copies} copies of the nuScenes-sized drive (nuscenes2mcap layout, class maps), default recipe{}; {epochs} epochs after a warm-up one, batches of 4 built in turn (a batch's samples in parallel); load average {} at start",
        columns.map_or(String::new(), |c| format!(", {c} LiDAR columns")),
        load_average(3)
    );
    println!(
        "| size | order | ms/sample 1 core | samples/s {cores} cores | decode | sweeps | images | projection | superpixels | voxels+maps | frames found built % | frames held, most MB |"
    );
    println!("|---|---|---:|---:|---:|---:|---:|---:|---:|---:|---:|---:|");
    let mut services = Vec::new();
    for size in sizes.split(',').filter(|s| !s.is_empty()) {
        let (w, h) = parse_size(size)?;
        let path = drive(Dialect::Foxglove, w, h, columns, regenerate)?;
        let paths = order::copies(&path, copies)?;
        for (name, run) in order::runs(&paths, maps, epochs, cores)? {
            println!("{}", order::row(size, name, &run));
        }
        for (name, _) in order::ORDERS {
            let (cpu_ms, samples, wall) = order::service(&binary, &paths, name, epochs)?;
            // One epoch more: the marginal cost of an epoch, and what start-up costs.
            let (cpu_more, samples_more, _) = order::service(&binary, &paths, name, epochs + 1)?;
            let total = |ms: f64, n: u64| ms * n as f64;
            let marginal = (total(cpu_more, samples_more) - total(cpu_ms, samples))
                / (samples_more - samples).max(1) as f64;
            let start_s = (total(cpu_ms, samples) - marginal * samples as f64) / 1e3;
            services.push(format!(
                "| {size} | {name} | {cpu_ms:.1} | {marginal:.1} | {start_s:.2} | {samples} | {wall:.1} |"
            ));
        }
    }
    println!(
        "stage columns: ms a sample on 1 core; blocks: 8 keyframes, 16 open (the service's defaults)"
    );
    println!();
    println!(
        "| size | order | service CPU ms/sample | of which an epoch's, ms/sample | start-up CPU s | samples | wall s |"
    );
    println!("|---|---|---:|---:|---:|---:|---:|");
    for row in services {
        println!("{row}");
    }
    println!(
        "the service: superflow-pipeline --epochs {epochs} --batch-size 2 from a warm index cache, every batch received; its process CPU (user + system, start-up included) over the samples; an epoch's: the difference to a run of one epoch more; start-up: the rest"
    );
    Ok(())
}

fn main() -> anyhow::Result<()> {
    superflow_common::memory::keep_freed_pages();
    superflow_common::memory::small_pages_only();
    let n = arg_count("--samples")?.unwrap_or(48);
    let n_slic = arg_count("--slic-samples")?.unwrap_or(12);
    let sizes = arg_value("--sizes").unwrap_or_else(|| "800x450,1600x900".into());
    let ros2_sizes = arg_value("--ros2-sizes").unwrap_or_else(|| "800x450".into());
    let regenerate = flag("--regenerate");
    let columns = arg_count("--columns")?;
    let maps = match arg_value("--kernel-maps").as_deref() {
        None | Some("unet") => KernelMaps::Unet,
        Some("none") => KernelMaps::None,
        Some(other) => anyhow::bail!("--kernel-maps {other}: expected unet or none"),
    };
    if flag("--orders") {
        return orders(&sizes, columns, maps, regenerate);
    }
    if let Some(n) = arg_count("--loop")? {
        let size = sizes.split(',').next().unwrap_or_default();
        let (w, h) = parse_size(size)?;
        let path = drive(Dialect::Foxglove, w, h, columns, regenerate)?;
        let blocks = match arg_value("--order").as_deref() {
            None | Some("global") => None,
            Some("blocks") => Some(arg_count("--copies")?.unwrap_or(3)),
            Some(other) => anyhow::bail!("--order {other}: expected global or blocks"),
        };
        return profile_loop(&path, n, maps, blocks);
    }
    let cores = cores();
    let recipe = match maps {
        KernelMaps::Unet => "default recipe",
        KernelMaps::None => "default recipe but kernel_maps = \"none\" (level-0 voxels, no map)",
    };
    println!(
        "nuScenes-sized drives (nuscenes2mcap layout; ROS 2: rosbag2 CDR, raw sweeps with a time per point, distorted images), {recipe}; {} rounds of {n} samples on 1 core then {cores} ({n_slic} with SLIC), load average {} at start",
        sample::ROUNDS,
        load_average(3)
    );
    println!(
        "| drive | superpixels | ms/sample 1 core | samples/s 1 core | samples/s {cores} cores | scaling | decode | sweeps | images | projection | superpixels | voxels+maps |"
    );
    println!("|---|---|---:|---:|---:|---:|---:|---:|---:|---:|---:|---:|");
    let mut batch_rows = Vec::new();
    let mut floor_rows = Vec::new();
    let mut bars = Vec::new();
    let mut runs = Vec::new();
    for (dialect, list) in [(Dialect::Foxglove, &sizes), (Dialect::Ros2, &ros2_sizes)] {
        for size in list.split(',').filter(|s| !s.is_empty()) {
            let (w, h) = parse_size(size)?;
            runs.push((dialect, w, h));
        }
    }
    for (dialect, w, h) in runs {
        let mut name = match dialect {
            Dialect::Foxglove => format!("{w}×{h}"),
            Dialect::Ros2 => format!("{w}×{h} ROS 2"),
        };
        if let Some(columns) = columns {
            name.push_str(&format!(", {columns} columns"));
        }
        let path = drive(dialect, w, h, columns, regenerate)?;
        let dataset = Dataset::open(std::slice::from_ref(&path), &IngestConfig::default())?;
        // SLIC does not depend on the layout: its rows are the Foxglove drives'.
        let slic_dataset = match dialect {
            Dialect::Foxglove => Some(slic_sidecar_drive(&path, regenerate)?),
            Dialect::Ros2 => None,
        };
        let mut rows = vec![(SuperpixelSource::Channel, n, &dataset, "class map (PNG)")];
        if let Some(slic_dataset) = &slic_dataset {
            rows.push((SuperpixelSource::Slic, n_slic, &dataset, "SLIC"));
            rows.push((
                SuperpixelSource::Slic,
                n,
                slic_dataset,
                "SLIC from its sidecar",
            ));
        }
        for (source, count, data, label) in rows {
            let config = SampleConfig {
                superpixels: source,
                kernel_maps: maps,
                ..SampleConfig::default()
            };
            let builder = SampleBuilder::new(data, config)?;
            let run = one_and_all(&builder, count, cores)?;
            let (one, all) = (run.one, run.all);
            println!(
                "| {name} | {label} | {:.1} | {one:.1} | {all:.1} | {:.2}× | {} |",
                1e3 / one,
                run.scaling,
                stage_cells(&run.times, count * sample::ROUNDS),
            );
            if source == SuperpixelSource::Channel {
                let samples = (0..BATCH as u64)
                    .map(|i| builder.build(0, i % builder.plan().keyframes.len() as u64))
                    .collect::<Result<Vec<_>, _>>()?;
                let shape = BatchShape::of(builder.config());
                batch_rows.push((name.clone(), batch_write(&samples, shape)?));
                let (row, libraries) = floor_row(&name, &builder, data, &path, n)?;
                floor_rows.push(row);
                bars.push(chart::Bar {
                    name: name.clone(),
                    total: 1e3 / one,
                    libraries,
                    stages: stage_ms(&run.times, count * sample::ROUNDS),
                    target: target_ms(w, h),
                });
            }
        }
    }
    println!(
        "samples/s: medians of the rounds; scaling: median of the rounds' ratios; stage columns: ms per sample on 1 core (decode: 5 sweeps, 9 JPEGs, 9 PNG class maps)"
    );
    println!();
    println!("| drive | batch of {BATCH} | producer write ms | one copy of its bytes ms | ratio |");
    println!("|---|---:|---:|---:|---:|");
    for (name, (write, copy, ratio, len)) in batch_rows {
        println!(
            "| {name} | {:.1} MB | {write:.2} | {copy:.2} | {ratio:.2}× |",
            len as f64 / 1e6,
        );
    }
    println!(
        "producer write: plan + every section into a zeroed payload (a fresh loan); copy: one memcpy of as many bytes; medians of {WRITE_ROUNDS} rounds, each a write then a copy (ratio: median of the rounds' ratios)"
    );
    println!();
    println!(
        "| drive | chunks a sample | MB decompressed | libzstd alone ms | JPEGs, libjpeg-turbo alone ms | PNG class maps alone ms | sum ms | decode stage ms | decode / sum |"
    );
    println!("|---|---:|---:|---:|---:|---:|---:|---:|---:|");
    for row in floor_rows {
        println!("{row}");
    }
    println!(
        "3 runs of {n} class-map samples on 1 core: the decode stage of the fastest, chunks and bytes its files decompressed per sample, that many MB at libzstd's speed on the drive's chunks, the sample's JPEGs decoded by libjpeg-turbo at the scale the recipe decodes them, its PNG class maps by the faster of the png crate and the pipeline's grey reader (the png crate's in brackets); fastest of 3 rounds"
    );
    let picture =
        PathBuf::from(env!("CARGO_MANIFEST_DIR")).join("../target/bench-drives/speed.svg");
    std::fs::write(&picture, chart::svg(&bars)?)?;
    let picture = picture.canonicalize()?;
    println!();
    println!(
        "where a class-map sample's time goes: {} (the libraries' parts scaled to the decode stage's mean when they exceed it)",
        picture.display()
    );
    Ok(())
}
