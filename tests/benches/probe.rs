//! Is the pretraining worth anything downstream? Pretrains the tiny presets for a fixed
//! budget on a longer labelled drive, then probes the pretrained backbone and an
//! untrained one of the same shape side by side (linear probe on frozen features, and
//! few-label fine-tuning), and prints the mIoUs.
//!
//! `cargo bench -p superflow-tests --bench probe [-- --keyframes N --steps N --epochs N
//! --finetune-fraction F --seeds N --orders global,blocks]`; the table goes to stdout,
//! progress to stderr.
//!
//! With `--seeds N` (1) every order of `--orders` (`global`) is pretrained `N` times, seeds
//! 0.. (the pipeline's `[sample] seed` and the trainer's `--seed`), and the table gives the
//! probes' mean ± standard deviation over the seeds: the seeds' spread is the noise an
//! order's difference must beat.
//!
//! 1. Release binaries of the generator, pipeline and trainer (`cargo build --release`).
//! 2. A labelled street drive of `--keyframes` keyframes (default 120: 60 s; generated,
//!    not committed) in `target/probe-bench/`.
//! 3. Pretraining: the pipeline (batches of 2) and `superflow-trainer --unet tiny --vit
//!    tiny --pixel-stride 4 --steps N` (default 300), with the RANDOM tiny ViT (no DINOv2
//!    weights offline): the 2D targets carry no semantics, so this measures what the
//!    chain teaches from geometry and superpixel structure alone.
//! 4. `superflow-trainer probe --json` of the pretrained checkpoint and of `random`:
//!    linear probe (all training sweeps) and fine-tuning on `--finetune-fraction` of them
//!    (default 0.1), the last quarter of the drive scored.

#![allow(clippy::unwrap_used, clippy::expect_used)]

use anyhow::Context as _;
use std::path::{Path, PathBuf};
use std::process::{Command, Stdio};
use std::time::Instant;
use superflow_tests::bench::common::{arg_count, arg_value, cores, load_average, root};

fn release(name: &str) -> PathBuf {
    root().join("target/release").join(name)
}

fn run(command: &mut Command, what: &str) -> anyhow::Result<String> {
    let out = command
        .current_dir(root())
        .stderr(Stdio::inherit())
        .output()
        .with_context(|| what.to_string())?;
    anyhow::ensure!(out.status.success(), "{what} failed");
    Ok(String::from_utf8_lossy(&out.stdout).into_owned())
}

/// One pretraining: the pipeline in `order` with `seed` streaming to the trainer for
/// `steps` steps into `out`; returns seconds and the loss means of the first and last 20
/// steps.
fn pretrain(
    drive: &Path,
    order: &str,
    seed: u64,
    steps: usize,
    out: &Path,
) -> anyhow::Result<(f64, f64, f64)> {
    let prefix = format!("sfprobe{}{order}{seed}", std::process::id());
    let config = out.with_extension("toml");
    std::fs::write(
        &config,
        format!("[sample]\nseed = {seed}\n\n[service]\norder = \"{order}\"\n"),
    )?;
    let mut pipeline = Command::new(release("superflow-pipeline"))
        .arg("--mcap")
        .arg(drive)
        .arg("--config")
        .arg(&config)
        .args(["--run", "probe", "--batch-size", "2"])
        .env("SUPERFLOW_IOX_PREFIX", &prefix)
        .env("RUST_LOG", "warn")
        .current_dir(root())
        .stdout(Stdio::null())
        .spawn()?;
    let t = Instant::now();
    let trained = run(
        Command::new(release("superflow-trainer"))
            .args([
                "--run",
                "probe",
                "--unet",
                "tiny",
                "--vit",
                "tiny",
                "--pixel-stride",
                "4",
            ])
            .args(["--seed", &seed.to_string()])
            .args([
                "--steps",
                &steps.to_string(),
                "--timeout-secs",
                "600",
                "--plot",
                "--out",
            ])
            .arg(out)
            .env("SUPERFLOW_IOX_PREFIX", &prefix)
            .env("RUST_LOG", "warn"),
        "pretraining",
    );
    let secs = t.elapsed().as_secs_f64();
    let _ = Command::new("kill")
        .args(["-TERM", &pipeline.id().to_string()])
        .status();
    let _ = pipeline.wait();
    trained?;
    let records = superflow_trainer::metrics::read(&out.join("metrics.jsonl"))?;
    let mean = |r: &[superflow_trainer::metrics::StepRecord]| {
        r.iter().map(|x| x.loss).sum::<f64>() / r.len().max(1) as f64
    };
    let first = mean(&records[..records.len().min(20)]);
    let last = mean(&records[records.len().saturating_sub(20)..]);
    Ok((secs, first, last))
}

/// Mean and sample standard deviation (0 for one value).
fn mean_std(values: &[f64]) -> (f64, f64) {
    let n = values.len().max(1) as f64;
    let mean = values.iter().sum::<f64>() / n;
    let var = values.iter().map(|v| (v - mean).powi(2)).sum::<f64>() / (n - 1.0).max(1.0);
    (mean, var.sqrt())
}

/// One probe: its JSON report and seconds.
fn probe(
    drive: &Path,
    checkpoint: &str,
    extra: &[&str],
) -> anyhow::Result<(serde_json::Value, f64)> {
    let t = Instant::now();
    let out = run(
        Command::new(release("superflow-trainer"))
            .args(["probe", "--mcap"])
            .arg(drive)
            .args(["--checkpoint", checkpoint, "--unet", "tiny", "--json"])
            .args(extra),
        &format!("probe {checkpoint} {extra:?}"),
    )?;
    let line = out.lines().last().context("no probe output")?;
    Ok((serde_json::from_str(line)?, t.elapsed().as_secs_f64()))
}

fn main() -> anyhow::Result<()> {
    let keyframes = arg_count("--keyframes")?.unwrap_or(120);
    let steps = arg_count("--steps")?.unwrap_or(300);
    let epochs = arg_count("--epochs")?.unwrap_or(20);
    let fraction: f64 = arg_value("--finetune-fraction").map_or(Ok(0.1), |v| v.parse())?;
    let cargo = std::env::var("CARGO").unwrap_or_else(|_| "cargo".into());
    run(
        Command::new(&cargo).args([
            "build",
            "--release",
            "--locked",
            "-p",
            "superflow-recordings",
            "-p",
            "superflow-pipeline",
            "-p",
            "superflow-trainer",
        ]),
        "cargo build --release",
    )?;
    let dir = root().join("target/probe-bench");
    let _ = std::fs::remove_dir_all(&dir);
    std::fs::create_dir_all(&dir)?;

    let t = Instant::now();
    run(
        Command::new(release("superflow-recordings"))
            .arg("--out")
            .arg(&dir)
            .args(["--keyframes", &keyframes.to_string()]),
        "generating the labelled drive",
    )?;
    let generate_s = t.elapsed().as_secs_f64();
    let drive = std::fs::read_dir(&dir)?
        .filter_map(|e| e.ok().map(|e| e.path()))
        .find(|p| {
            let name = p.file_name().unwrap_or_default().to_string_lossy();
            name.ends_with(".mcap") && name.matches('.').count() == 1
        })
        .context("the generator wrote no drive")?;
    eprintln!("drive {} ({generate_s:.0} s)", drive.display());

    let seeds = arg_count("--seeds")?.unwrap_or(1).max(1) as u64;
    let orders = arg_value("--orders").unwrap_or_else(|| "global".into());
    let orders: Vec<&str> = orders.split(',').filter(|o| !o.is_empty()).collect();
    let epochs = epochs.to_string();
    let fraction_text = fraction.to_string();
    let protocols: [(&str, Vec<&str>); 2] = [
        (
            "linear probe, all training sweeps",
            vec!["--epochs", &epochs],
        ),
        (
            "fine-tuning, few labels",
            vec![
                "--finetune",
                "--label-fraction",
                &fraction_text,
                "--epochs",
                "10",
            ],
        ),
    ];
    // (order, protocol) → mIoU and accuracy of each seed; per order the pretraining runs.
    let mut scores: Vec<(String, &str, Vec<f64>, Vec<f64>)> = Vec::new();
    let mut runs = Vec::new();
    for order in &orders {
        for seed in 0..seeds {
            let out = dir.join(format!("run-{order}-{seed}"));
            let (secs, first, last) = pretrain(&drive, order, seed, steps, &out)?;
            eprintln!(
                "{order}, seed {seed}: {steps} steps in {secs:.0} s, loss {first:.3} → {last:.3}"
            );
            runs.push(format!(
                "{order} seed {seed}: {secs:.0} s, loss {first:.3} → {last:.3}"
            ));
            let checkpoint = out.join("checkpoints");
            let checkpoint = checkpoint.to_str().context("path")?;
            for (name, extra) in &protocols {
                let (r, _) = probe(&drive, checkpoint, extra)?;
                let miou = r["miou"].as_f64().unwrap_or(f64::NAN) * 100.0;
                let accuracy = r["accuracy"].as_f64().unwrap_or(f64::NAN) * 100.0;
                match scores.iter_mut().find(|s| s.0 == *order && s.1 == *name) {
                    Some(entry) => {
                        entry.2.push(miou);
                        entry.3.push(accuracy);
                    }
                    None => scores.push((order.to_string(), name, vec![miou], vec![accuracy])),
                }
            }
        }
    }
    println!(
        "\nMachine: {} cores, load {}. Drive: {keyframes} keyframes ({}), generated in {generate_s:.0} s.",
        cores(),
        load_average(1),
        drive.file_name().unwrap_or_default().to_string_lossy()
    );
    println!(
        "Pretraining: tiny UNet + RANDOM tiny ViT, pixel stride 4, batches of 2, {steps} steps a run; {seeds} seed(s) per order ({}).\n",
        runs.join("; ")
    );
    println!("| protocol | backbone | order | mIoU % | accuracy % | seeds |");
    println!("|---|---|---|---:|---:|---:|");
    let cell = |values: &[f64]| {
        let (mean, std) = mean_std(values);
        if values.len() > 1 {
            format!("{mean:.2} ± {std:.2}")
        } else {
            format!("{mean:.2}")
        }
    };
    for (name, extra) in &protocols {
        for (order, protocol, mious, accuracies) in &scores {
            if protocol == name {
                println!(
                    "| {name} | pretrained | {order} | {} | {} | {} |",
                    cell(mious),
                    cell(accuracies),
                    mious.len()
                );
            }
        }
        let (r, _) = probe(&drive, "random", extra)?;
        println!(
            "| {name} | random | – | {:.2} | {:.2} | – |",
            r["miou"].as_f64().unwrap_or(f64::NAN) * 100.0,
            r["accuracy"].as_f64().unwrap_or(f64::NAN) * 100.0,
        );
    }
    Ok(())
}
