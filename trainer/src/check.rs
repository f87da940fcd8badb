//! `superflow-trainer check`: the same steps on the same batch and the same initial
//! weights on several backends (the CPU's `flex` as the reference, then `wgpu` or
//! `cuda`), to check a GPU backend before a long run: the losses of every step compared
//! within a relative tolerance, and each backend's step time.
//!
//! The batch is a file as `superflow-pipeline batch` writes it (the `BatchHeader` bytes,
//! then the payload). Initial weights are drawn from the seed on the host, so every
//! backend starts from the same ones.

use crate::config::TrainerConfig;
use crate::error::TrainerError;
use crate::loss::LossValues;
use crate::train::Trainer;
use burn::tensor::Device;
use std::path::{Path, PathBuf};
use std::time::Instant;
use superflow_schemas::batch::{BatchHeader, BatchView};

/// A batch read from a file, its payload 8-byte aligned as in shared memory.
#[derive(Debug)]
pub struct BatchFile {
    /// Where it was read from.
    pub path: PathBuf,
    header: BatchHeader,
    payload: Vec<u64>,
    len: usize,
}

impl BatchFile {
    /// Reads and validates a batch file.
    pub fn read(path: &Path) -> Result<Self, TrainerError> {
        let bytes = std::fs::read(path).map_err(|e| TrainerError::io("reading", path, e))?;
        let header =
            BatchHeader::from_bytes(&bytes).ok_or_else(|| TrainerError::BatchFileTooShort {
                path: path.to_path_buf(),
                bytes: bytes.len(),
            })?;
        let body = &bytes[BatchHeader::SIZE..];
        let mut payload = vec![0u64; body.len().div_ceil(8)];
        bytemuck::cast_slice_mut::<u64, u8>(&mut payload)[..body.len()].copy_from_slice(body);
        let file = Self {
            path: path.to_path_buf(),
            header,
            payload,
            len: body.len(),
        };
        file.view()?;
        Ok(file)
    }

    /// The batch, as the trainer reads it from shared memory.
    pub fn view(&self) -> Result<BatchView<'_>, TrainerError> {
        let bytes = &bytemuck::cast_slice::<u64, u8>(&self.payload)[..self.len];
        BatchView::new(&self.header, bytes).map_err(|error| TrainerError::BatchFile {
            path: self.path.clone(),
            error,
        })
    }

    /// Header and payload bytes.
    pub fn bytes(&self) -> usize {
        BatchHeader::SIZE + self.len
    }
}

/// What one backend did.
#[derive(Debug, Clone)]
pub struct BackendRun {
    /// The backend's name.
    pub backend: String,
    /// Losses of every step.
    pub losses: Vec<LossValues>,
    /// Milliseconds of every step (the first includes the backend's warm-up: kernel
    /// compilation, allocations).
    pub step_ms: Vec<f64>,
    /// Seconds to build the trainer (weights drawn and uploaded).
    pub init_s: f64,
}

impl BackendRun {
    /// Median ms of the steps after the first.
    pub fn steady_ms(&self) -> f64 {
        let mut rest: Vec<f64> = self.step_ms.iter().skip(1).copied().collect();
        if rest.is_empty() {
            return self.step_ms.first().copied().unwrap_or(f64::NAN);
        }
        rest.sort_by(f64::total_cmp);
        rest[rest.len() / 2]
    }

    /// The largest relative difference of any loss term of any step from `reference`'s.
    pub fn worst_difference(&self, reference: &BackendRun) -> f64 {
        self.losses
            .iter()
            .zip(&reference.losses)
            .flat_map(|(a, b)| {
                [
                    (a.total, b.total),
                    (a.sc, b.sc),
                    (a.tc, b.tc),
                    (a.d2s, b.d2s),
                ]
                .map(|(x, y)| (x - y).abs() / y.abs().max(1e-12))
            })
            .fold(0.0, f64::max)
    }
}

/// `steps` training steps of a fresh trainer of `config` on `device` on `batch`.
pub fn run_backend(
    backend: crate::device::Backend,
    config: &TrainerConfig,
    device: &Device,
    batch: &BatchFile,
    steps: usize,
) -> Result<BackendRun, TrainerError> {
    let t = Instant::now();
    let mut trainer = Trainer::new(config.clone(), device)?;
    let init_s = t.elapsed().as_secs_f64();
    let view = batch.view()?;
    let mut run = BackendRun {
        backend: backend.to_string(),
        losses: Vec::with_capacity(steps),
        step_ms: Vec::with_capacity(steps),
        init_s,
    };
    for step in 1..=steps {
        let outcome = trainer.step(&view)?;
        tracing::info!(
            backend = backend.name(),
            step,
            loss = format_args!("{:.6}", outcome.losses.total),
            ms = format_args!("{:.1}", outcome.seconds * 1e3),
            "check step"
        );
        run.losses.push(outcome.losses);
        run.step_ms.push(outcome.seconds * 1e3);
    }
    drop(trainer);
    crate::device::settle(device);
    Ok(run)
}

#[cfg(test)]
#[allow(clippy::unwrap_used)]
mod tests {
    use super::*;

    fn run(totals: &[f64], ms: &[f64]) -> BackendRun {
        BackendRun {
            backend: "x".into(),
            losses: totals
                .iter()
                .map(|&t| LossValues {
                    total: t,
                    sc: t / 2.0,
                    tc: t / 4.0,
                    d2s: t / 4.0,
                })
                .collect(),
            step_ms: ms.to_vec(),
            init_s: 0.0,
        }
    }

    #[test]
    fn differences_are_relative_and_the_warm_up_step_is_left_out() {
        let a = run(&[4.0, 2.0], &[900.0, 10.0]);
        let b = run(&[4.0, 2.002], &[5.0, 5.0]);
        assert!((b.worst_difference(&a) - 1e-3).abs() < 1e-9);
        assert_eq!(a.steady_ms(), 10.0);
        assert_eq!(run(&[1.0], &[7.0]).steady_ms(), 7.0);
    }

    #[test]
    fn a_file_too_short_for_a_header_is_an_error_naming_it() {
        let path = std::env::temp_dir().join(format!("superflow-short-{}.bin", std::process::id()));
        std::fs::write(&path, [0u8; 10]).unwrap();
        let err = BatchFile::read(&path).unwrap_err().to_string();
        assert!(
            err.contains(&path.display().to_string()) && err.contains("shorter"),
            "{err}"
        );
        let _ = std::fs::remove_file(&path);
    }
}
