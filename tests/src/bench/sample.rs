//! Sample-building throughput: samples/s of a [`SampleBuilder`] on a rayon pool of a
//! given size, and the CPU time per stage.
//!
//! Used by `cargo bench -p superflow-pipeline --bench sample` (through `#[path]`) and by
//! the summary bench of `superflow-tests`.

use rayon::prelude::*;
use std::time::Instant;
use superflow_pipeline::sample::SampleBuilder;
use superflow_pipeline::sample::StageTimes;

/// Builds `n` samples (epoch-major over the plan) on `threads` threads; returns
/// samples/s and the summed stage times.
pub fn throughput(
    builder: &SampleBuilder<'_>,
    n: usize,
    threads: usize,
) -> anyhow::Result<(f64, StageTimes)> {
    let pool = rayon::ThreadPoolBuilder::new()
        .num_threads(threads)
        .build()?;
    let per_epoch = builder.plan().keyframes.len();
    let started = Instant::now();
    let times = pool.install(|| {
        (0..n)
            .into_par_iter()
            .map(|i| {
                builder
                    .build((i / per_epoch) as u64, (i % per_epoch) as u64)
                    .map(|s| s.times)
            })
            .collect::<Result<Vec<_>, _>>()
    })?;
    let secs = started.elapsed().as_secs_f64();
    let mut total = StageTimes::default();
    for t in &times {
        total.add(t);
    }
    Ok((n as f64 / secs, total))
}

/// Rounds of [`one_and_all`]: each runs one core, then all cores.
pub const ROUNDS: usize = 3;

/// What [`one_and_all`] measured.
#[derive(Debug, Clone)]
pub struct Throughput {
    /// Samples/s on one core (median of the rounds).
    pub one: f64,
    /// Samples/s on all cores (median of the rounds).
    pub all: f64,
    /// All cores over one core: the median of the rounds' ratios, each round's two runs
    /// back to back (the VM's speed drifts by 10–30 % over minutes; within a round far
    /// less).
    pub scaling: f64,
    /// Stage times of the one-core runs, summed over the rounds (`ROUNDS · n` samples).
    pub times: StageTimes,
}

/// Samples/s on one core and on `cores` cores after a warm-up epoch (page cache,
/// allocator): [`ROUNDS`] rounds of `n` samples on one core then on `cores`.
pub fn one_and_all(
    builder: &SampleBuilder<'_>,
    n: usize,
    cores: usize,
) -> anyhow::Result<Throughput> {
    throughput(builder, builder.plan().keyframes.len(), cores)?;
    let (mut ones, mut alls, mut ratios) = (Vec::new(), Vec::new(), Vec::new());
    let mut times = StageTimes::default();
    for _ in 0..ROUNDS {
        let (one, t) = throughput(builder, n, 1)?;
        let (all, _) = throughput(builder, n, cores)?;
        times.add(&t);
        ones.push(one);
        alls.push(all);
        ratios.push(all / one);
    }
    Ok(Throughput {
        one: super::common::median(&ones),
        all: super::common::median(&alls),
        scaling: super::common::median(&ratios),
        times,
    })
}

/// ms per sample of decode, sweeps, images, projection, superpixels and voxels+maps, for
/// `times` summed over `n` samples.
pub fn stage_ms(times: &StageTimes, n: usize) -> [f64; 6] {
    [
        times.decode,
        times.sweeps,
        times.images,
        times.projection,
        times.superpixels,
        times.voxels,
    ]
    .map(|ns| ns as f64 / 1e6 / n as f64)
}

/// The stage columns of a bench table: [`stage_ms`] as cells.
pub fn stage_cells(times: &StageTimes, n: usize) -> String {
    stage_ms(times, n).map(|ms| format!("{ms:.1}")).join(" | ")
}
