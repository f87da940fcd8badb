//! Per-step metrics: one JSON object per line (`superflow.metrics/1`), and an optional
//! SVG of the loss curves at the end of a run.

use crate::error::TrainerError;
use serde::{Deserialize, Serialize};
use std::fs::{File, OpenOptions};
use std::io::{BufWriter, Write as _};
use std::path::{Path, PathBuf};

/// One training step.
#[derive(Debug, Clone, Default, PartialEq, Serialize, Deserialize)]
pub struct StepRecord {
    /// Optimizer step (1-based: the number of steps taken after this one).
    pub step: u64,
    /// Stream position of the batch.
    pub epoch: u64,
    /// See `epoch`.
    pub batch: u64,
    /// Weighted total loss.
    pub loss: f64,
    /// `L_sc`.
    pub l_sc: f64,
    /// `L_tc`.
    pub l_tc: f64,
    /// `L_d2s`.
    pub l_d2s: f64,
    /// Learning rate used by this step.
    pub lr: f64,
    /// Time spent waiting for the batch, ms.
    pub wait_ms: f64,
    /// Time spent on the step (tensors, forward, backward, update), ms.
    pub step_ms: f64,
    /// Samples per second over wait + step.
    pub samples_per_s: f64,
    /// Samples in the batch.
    pub samples: usize,
    /// Points, pairings and level-0 voxels of the batch.
    pub points: usize,
    /// See `points`.
    pub pairings: usize,
    /// See `points`.
    pub voxels: usize,
    /// `sample_ids` of the batch: (epoch, index in epoch) per sample.
    pub sample_ids: Vec<[u64; 2]>,
    /// 64-bit hash of the trainable parameters after this step's update: equal on the
    /// ranks of a data-parallel job (`superflow_trainer::sync::params_hash`).
    #[serde(default)]
    pub params_hash: u64,
    /// The step over all ranks of a data-parallel job (`--ddp`).
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub ddp: Option<DdpRecord>,
}

/// A data-parallel step as all ranks took it.
#[derive(Debug, Clone, Default, PartialEq, Serialize, Deserialize)]
pub struct DdpRecord {
    /// This rank.
    pub rank: u32,
    /// Ranks in the job.
    pub world_size: u32,
    /// Total loss averaged over all ranks' samples (what the update followed).
    pub loss: f64,
    /// Samples of all ranks (this rank's may be 0: its shard's epoch ended first).
    pub samples: usize,
    /// Time in the gradient all-reduce (flatten, reduce, unflatten), ms.
    pub reduce_ms: f64,
    /// Bytes each rank put into the all-reduce.
    pub reduce_bytes: usize,
}

/// Appends step records to a JSON-lines file.
#[derive(Debug)]
pub struct MetricsWriter {
    path: PathBuf,
    out: BufWriter<File>,
}

impl MetricsWriter {
    /// Opens `path` for appending (a resumed run continues the same file).
    pub fn open(path: &Path) -> Result<Self, TrainerError> {
        if let Some(parent) = path.parent().filter(|p| !p.as_os_str().is_empty()) {
            std::fs::create_dir_all(parent).map_err(|e| TrainerError::io("creating", parent, e))?;
        }
        let file = OpenOptions::new()
            .create(true)
            .append(true)
            .open(path)
            .map_err(|e| TrainerError::io("opening", path, e))?;
        Ok(Self {
            path: path.to_path_buf(),
            out: BufWriter::new(file),
        })
    }

    /// Writes one line and flushes it (a killed trainer loses no finished step).
    pub fn write(&mut self, record: &StepRecord) -> Result<(), TrainerError> {
        serde_json::to_writer(&mut self.out, record).map_err(|error| TrainerError::Json {
            path: self.path.clone(),
            error,
        })?;
        self.out
            .write_all(b"\n")
            .and_then(|()| self.out.flush())
            .map_err(|e| TrainerError::io("writing", &self.path, e))
    }
}

/// Keeps the records of steps `..= step` of a metrics file and drops the rest: a run
/// resumed from its checkpoint at `step` redoes the later steps, so the file keeps one
/// record per trained step (the lineage of the model). A last line cut short by a
/// kill is dropped too. Returns how many records were dropped; the file is replaced
/// atomically (written aside, then renamed).
pub fn truncate_after(path: &Path, step: u64) -> Result<usize, TrainerError> {
    let text = match std::fs::read_to_string(path) {
        Ok(text) => text,
        Err(e) if e.kind() == std::io::ErrorKind::NotFound => return Ok(0),
        Err(e) => return Err(TrainerError::io("reading", path, e)),
    };
    let lines: Vec<&str> = text.lines().filter(|l| !l.trim().is_empty()).collect();
    let mut kept = String::with_capacity(text.len());
    let mut dropped = 0;
    for (i, line) in lines.iter().enumerate() {
        match serde_json::from_str::<StepRecord>(line) {
            Ok(record) if record.step <= step => {
                kept.push_str(line);
                kept.push('\n');
            }
            Ok(_) => dropped += 1,
            // Only the last line can be partial (each line is flushed whole).
            Err(_) if i + 1 == lines.len() && !text.ends_with('\n') => dropped += 1,
            Err(error) => {
                return Err(TrainerError::JsonLine {
                    path: path.to_path_buf(),
                    line: i + 1,
                    error,
                });
            }
        }
    }
    if dropped > 0 {
        let aside = path.with_extension("jsonl.tmp");
        std::fs::write(&aside, kept).map_err(|e| TrainerError::io("writing", &aside, e))?;
        std::fs::rename(&aside, path).map_err(|e| TrainerError::io("replacing", path, e))?;
    }
    Ok(dropped)
}

/// Reads a metrics file (for plots and tests).
pub fn read(path: &Path) -> Result<Vec<StepRecord>, TrainerError> {
    let text = std::fs::read_to_string(path).map_err(|e| TrainerError::io("reading", path, e))?;
    text.lines()
        .filter(|l| !l.trim().is_empty())
        .enumerate()
        .map(|(i, l)| {
            serde_json::from_str(l).map_err(|error| TrainerError::JsonLine {
                path: path.to_path_buf(),
                line: i + 1,
                error,
            })
        })
        .collect()
}

/// A plotted curve: name, value of a step, colour.
type Series = (&'static str, fn(&StepRecord) -> f64, &'static str);

/// Draws the loss terms against the step as an SVG (axes, ticks, legend; opens in any
/// browser, no font or plotting library needed).
pub fn plot_svg(records: &[StepRecord], path: &Path) -> Result<(), TrainerError> {
    if records.is_empty() {
        return Err(TrainerError::NothingToPlot);
    }
    // Writing into a String cannot fail.
    let svg = svg(records).unwrap_or_default();
    std::fs::write(path, svg).map_err(|e| TrainerError::io("writing", path, e))
}

/// The SVG text of [`plot_svg`] (`records` is not empty).
fn svg(records: &[StepRecord]) -> Result<String, std::fmt::Error> {
    use std::fmt::Write as _;
    let (w, h, left, right, top, bottom) = (960.0, 540.0, 70.0, 20.0, 30.0, 50.0);
    let x0 = records.first().map_or(0, |r| r.step) as f64;
    let x1 = (records.last().map_or(1, |r| r.step) as f64).max(x0 + 1.0);
    let series: [Series; 4] = [
        ("total", |r| r.loss, "#000000"),
        ("L_sc", |r| r.l_sc, "#1f77b4"),
        ("L_tc", |r| r.l_tc, "#ff7f0e"),
        ("L_d2s", |r| r.l_d2s, "#2ca02c"),
    ];
    let y1 = records
        .iter()
        .flat_map(|r| series.iter().map(move |s| (s.1)(r)))
        .filter(|v| v.is_finite())
        .fold(1e-6_f64, f64::max)
        * 1.05;
    let px = |x: f64| left + (x - x0) / (x1 - x0) * (w - left - right);
    let py = |y: f64| h - bottom - y / y1 * (h - top - bottom);
    let mut svg = String::new();
    writeln!(
        svg,
        r#"<svg xmlns="http://www.w3.org/2000/svg" width="{w}" height="{h}" font-family="sans-serif" font-size="12">"#
    )?;
    writeln!(svg, r#"<rect width="100%" height="100%" fill="white"/>"#)?;
    writeln!(
        svg,
        r#"<path d="M{l} {t} V{b} H{r}" stroke="black" fill="none"/>"#,
        l = left,
        t = top,
        b = h - bottom,
        r = w - right
    )?;
    for i in 0..=5 {
        let (xv, yv) = (x0 + (x1 - x0) * f64::from(i) / 5.0, y1 * f64::from(i) / 5.0);
        writeln!(
            svg,
            r#"<text x="{:.1}" y="{:.1}" text-anchor="middle">{:.0}</text>"#,
            px(xv),
            h - bottom + 18.0,
            xv
        )?;
        writeln!(
            svg,
            r#"<text x="{:.1}" y="{:.1}" text-anchor="end">{:.3}</text>"#,
            left - 6.0,
            py(yv) + 4.0,
            yv
        )?;
    }
    writeln!(
        svg,
        r#"<text x="{:.1}" y="{:.1}" text-anchor="middle">step</text>"#,
        (left + w - right) / 2.0,
        h - 12.0
    )?;
    writeln!(
        svg,
        r#"<text x="16" y="{:.1}" transform="rotate(-90 16 {:.1})" text-anchor="middle">loss</text>"#,
        (top + h - bottom) / 2.0,
        (top + h - bottom) / 2.0
    )?;
    for (i, (name, value, color)) in series.iter().enumerate() {
        let points: Vec<String> = records
            .iter()
            .filter(|r| value(r).is_finite())
            .map(|r| format!("{:.1},{:.1}", px(r.step as f64), py(value(r))))
            .collect();
        writeln!(
            svg,
            r#"<polyline points="{}" stroke="{color}" fill="none" stroke-width="1.5"/>"#,
            points.join(" ")
        )?;
        let ly = top + 16.0 * i as f64 + 8.0;
        writeln!(
            svg,
            r#"<path d="M{} {ly} h20" stroke="{color}" stroke-width="2"/><text x="{}" y="{}">{name}</text>"#,
            w - right - 110.0,
            w - right - 84.0,
            ly + 4.0
        )?;
    }
    writeln!(svg, "</svg>")?;
    Ok(svg)
}

#[cfg(test)]
mod tests {
    #![allow(clippy::unwrap_used)]
    use super::*;

    #[test]
    fn truncation_keeps_the_lineage_up_to_the_checkpoint() {
        let dir = std::env::temp_dir().join(format!("sf-metrics-{}", std::process::id()));
        std::fs::create_dir_all(&dir).unwrap();
        let path = dir.join("metrics.jsonl");
        let _ = std::fs::remove_file(&path);
        assert_eq!(truncate_after(&path, 3).unwrap(), 0, "no file yet");
        let mut w = MetricsWriter::open(&path).unwrap();
        for step in 1..=5 {
            w.write(&StepRecord {
                step,
                sample_ids: vec![[0, step]],
                ..StepRecord::default()
            })
            .unwrap();
        }
        drop(w);
        // A kill in the middle of a line.
        let mut f = OpenOptions::new().append(true).open(&path).unwrap();
        f.write_all(b"{\"step\":6,\"epo").unwrap();
        drop(f);
        assert_eq!(truncate_after(&path, 3).unwrap(), 3);
        let steps: Vec<u64> = read(&path).unwrap().iter().map(|r| r.step).collect();
        assert_eq!(steps, [1, 2, 3]);
        assert_eq!(truncate_after(&path, 3).unwrap(), 0);
        // A damaged line in the middle is an error, not a silent loss.
        std::fs::write(&path, "{\"bad\n{\"step\":1}\n").unwrap();
        assert!(truncate_after(&path, 3).is_err());
        std::fs::remove_dir_all(&dir).unwrap();
    }
}
