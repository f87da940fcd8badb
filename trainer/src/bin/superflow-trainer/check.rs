//! `superflow-trainer check`: the same steps on several backends from the same initial
//! weights, compared with the first.

use crate::cli::{Args, CheckArgs};
use anyhow::Context as _;
use superflow_trainer::check::{self, BatchFile};
use superflow_trainer::device;

/// `superflow-trainer check`: the same steps on every backend, compared with the first.
pub fn check(args: &Args, c: &CheckArgs) -> anyhow::Result<Option<i32>> {
    let steps = args.steps.unwrap_or(3).max(1) as usize;
    let config = args.config()?;
    let batch = BatchFile::read(&c.batch)?;
    let view = batch.view()?;
    tracing::info!(
        batch = %c.batch.display(),
        bytes = batch.bytes(),
        samples = view.meta().sample_count,
        unet = ?config.model.unet,
        vit = ?config.model.vit,
        steps,
        "checking backends on one batch"
    );
    drop(view);
    let mut runs = Vec::new();
    for backend in &c.backends {
        let device = device::select(*backend, args.device_index)?;
        tracing::info!(%backend, ?device, "running");
        if let Some(gpu) = device::gpu_info(&device) {
            println!("{backend} device: {gpu}");
        }
        let run = check::run_backend(*backend, &config, &device, &batch, steps)
            .with_context(|| format!("backend {backend}"))?;
        runs.push(run);
    }
    let reference = &runs[0];
    println!(
        "| backend | init s | first step ms | ms / step (after the first) | steps/s | worst relative loss difference vs {} |",
        reference.backend
    );
    println!("|---|---:|---:|---:|---:|---:|");
    let mut worst = 0.0f64;
    let mut json = Vec::new();
    for run in &runs {
        let difference = run.worst_difference(reference);
        worst = worst.max(difference);
        let steady = run.steady_ms();
        println!(
            "| {} | {:.2} | {:.1} | {steady:.1} | {:.2} | {difference:.2e} |",
            run.backend,
            run.init_s,
            run.step_ms[0],
            1e3 / steady
        );
        json.push(serde_json::json!({
            "backend": run.backend,
            "init_s": run.init_s,
            "step_ms": run.step_ms,
            "losses": run.losses,
            "worst_relative_difference": difference,
        }));
    }
    if let Some(path) = &c.json {
        std::fs::write(path, serde_json::to_vec_pretty(&json)?)
            .with_context(|| format!("writing {}", path.display()))?;
    }
    if worst > c.tolerance {
        anyhow::bail!(
            "the backends disagree: a loss differs by {worst:.2e} (relative) from {}'s, more than --tolerance {:.0e}",
            reference.backend,
            c.tolerance
        );
    }
    tracing::info!(
        worst = format_args!("{worst:.2e}"),
        tolerance = c.tolerance,
        "the backends agree"
    );
    Ok(None)
}
