//! Scratch: nuScenes-sized drive, samples on one core, stage times.
#[allow(dead_code)]
#[path = "../../tests/src/bench/common.rs"]
mod common;
use superflow_pipeline::drive::{Dataset, IngestConfig};
use superflow_pipeline::sample::{SampleBuilder, SampleConfig};
use superflow_recordings::{Dialect, DriveOptions, generate_with};

fn main() -> anyhow::Result<()> {
    let n = common::arg_count("--samples")?.unwrap_or(24);
    let path = std::path::PathBuf::from("/tmp/nus_prof.mcap");
    if !path.exists() {
        let t = std::time::Instant::now();
        let opts = DriveOptions {
            duration_nanos: 2_000_000_000,
            cameras: 6,
            image_size: (800, 450),
            lidar_columns: 2168,
            chunk_size: 4 << 20,
        };
        let drive = generate_with(Dialect::Foxglove, &opts)?;
        std::fs::write(&path, &drive.mcap)?;
        eprintln!("generated in {:.1} s", t.elapsed().as_secs_f64());
    }
    let dataset = Dataset::open(std::slice::from_ref(&path), &IngestConfig::default())?;
    let builder = SampleBuilder::new(&dataset, SampleConfig::default())?;
    let pool = rayon::ThreadPoolBuilder::new().num_threads(1).build()?;
    let per = builder.plan().keyframes.len();
    let mut times = superflow_pipeline::sample::StageTimes::default();
    let t = std::time::Instant::now();
    let mut points = 0;
    pool.install(|| -> anyhow::Result<()> {
        for i in 0..n {
            let s = builder.build((i / per) as u64, (i % per) as u64)?;
            points += s.dense.xyz.len();
            times.add(&s.times);
        }
        Ok(())
    })?;
    let ms = |ns: u64| ns as f64 / 1e6 / n as f64;
    println!(
        "{n} samples, {:.1} ms/sample wall; dense points {}; decode {:.1} sweeps {:.1} images {:.1} proj {:.1} sp {:.1} voxels {:.1}",
        t.elapsed().as_secs_f64() * 1e3 / n as f64,
        points / n,
        ms(times.decode), ms(times.sweeps), ms(times.images), ms(times.projection), ms(times.superpixels), ms(times.voxels)
    );
    Ok(())
}
