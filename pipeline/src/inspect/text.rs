//! The report for people: what `inspect` prints without `--json`.

use super::model::{DriveReport, InspectReport, LabelsReport};
use crate::drive::Role;
use std::fmt::Write as _;

impl InspectReport {
    /// The report for people: the dataset's groups and rigs, then every drive.
    pub fn to_text(&self) -> String {
        let mut parts = Vec::new();
        if let Some(fleet) = &self.fleet {
            parts.push(format!(
                "== dataset: {} drive(s), {} group(s), {} rig(s), {} samples an epoch\n{}\n",
                self.drives.len(),
                fleet.groups.len(),
                fleet.rigs.len(),
                fleet.samples_per_epoch,
                fleet.lines().join("\n")
            ));
        }
        parts.extend(self.drives.iter().enumerate().map(|(i, d)| {
            format!(
                "== drive {} of {}\n{}",
                i + 1,
                self.drives.len(),
                d.to_text()
            )
        }));
        parts.join("\n")
    }
}

impl LabelsReport {
    /// The report for people: a few lines.
    fn to_text(&self) -> String {
        let mut out = String::new();
        match &self.form {
            Some(form) => {
                let _ = writeln!(
                    out,
                    "\nlabels: {form}; {} of {} sweeps labelled",
                    self.sweeps_labelled, self.sweeps
                );
            }
            None => {
                let _ = writeln!(out, "\nlabels: not readable");
            }
        }
        if !self.raw_ids.is_empty() {
            let ids: Vec<String> = self
                .raw_ids
                .iter()
                .map(|(id, n)| format!("{id}: {n}"))
                .collect();
            let _ = writeln!(out, "  raw ids (points): {}", ids.join(", "));
        }
        if !self.classes.is_empty() {
            let classes: Vec<String> = self
                .classes
                .iter()
                .map(|c| match c.name.as_str() {
                    "" => format!("{}: {}", c.id, c.points),
                    name => format!("{} {name}: {}", c.id, c.points),
                })
                .collect();
            let _ = writeln!(out, "  training classes (points): {}", classes.join(", "));
        }
        if let Some(e) = &self.first_error {
            let _ = writeln!(out, "  {} sweeps failed; first: {e}", self.errors);
        }
        out
    }
}

impl DriveReport {
    /// The report for people.
    pub fn to_text(&self) -> String {
        let mut out = String::new();
        for f in &self.files {
            let _ = writeln!(
                out,
                "file {} ({} bytes, profile {:?}, {})",
                f.path, f.bytes, f.profile, f.library
            );
            for d in &f.damage {
                let _ = writeln!(out, "  damage: {d}");
            }
        }
        let _ = writeln!(out, "dialect {}", self.dialect);
        let _ = writeln!(out, "\nchannels");
        for c in &self.channels {
            let role = match &c.role {
                Role::Ignored(why) => format!("ignored ({why})"),
                other => other.name().to_string(),
            };
            let rate = c.rate_hz.map_or("-".to_string(), |r| format!("{r:.1} Hz"));
            let _ = writeln!(
                out,
                "  {:<40} {:<28} {:>6} msgs {:>9}  {}",
                c.topic, c.schema, c.message_count, rate, role
            );
        }
        let _ = writeln!(
            out,
            "\nlidar {} in frame {} ({} sweeps)",
            self.lidar_topic.as_deref().unwrap_or("-"),
            self.lidar_frame.as_deref().unwrap_or("-"),
            self.lidar_sweeps
        );
        let _ = writeln!(out, "\ncameras");
        for c in &self.cameras {
            let _ = writeln!(
                out,
                "  {:<16} {}x{} {:<20} {:>4} images {:>6}  frame {}  calibration {}  superpixels {}",
                c.name,
                c.width.unwrap_or(0),
                c.height.unwrap_or(0),
                c.distortion_model.as_deref().unwrap_or("uncalibrated"),
                c.images,
                c.rate_hz.map_or("-".to_string(), |r| format!("{r:.1} Hz")),
                c.frame_id,
                c.calibration_topic.as_deref().unwrap_or("-"),
                c.superpixel_topic.as_deref().unwrap_or("-"),
            );
            if let Some(slic) = &c.slic_topic {
                let _ = writeln!(out, "  {:<16} SLIC superpixels {slic}", "");
            }
        }
        let _ = writeln!(
            out,
            "\nframe tree (map {}, ego {})",
            self.map_frame.as_deref().unwrap_or("?"),
            self.ego_frame.as_deref().unwrap_or("?")
        );
        for e in &self.frame_tree {
            let _ = writeln!(
                out,
                "  {} -> {} ({}, {} samples)",
                e.parent, e.child, e.kind, e.samples
            );
        }
        if let Some(d) = self.duration_secs {
            let _ = writeln!(
                out,
                "\ntime span {d:.3} s; usable keyframes (0.5 s): {}",
                self.usable_keyframes
            );
        }
        let t = &self.camera_timing;
        if !t.scan_ms.is_empty() {
            let _ = writeln!(
                out,
                "LiDAR scans the cameras at (ms from the sweep stamp, {}):",
                t.timing
            );
            for (camera, moments) in &t.scan_ms {
                let ms: Vec<String> = moments.iter().map(|m| format!("{m:+.1}")).collect();
                let _ = writeln!(out, "  {camera}: {}", ms.join(" and "));
            }
        }
        if let Some([median, max]) = t.worst_offset_ms {
            let _ = writeln!(
                out,
                "keyframes (least camera offset): {}; worst camera offset median {median:.1} ms, max {max:.1} ms",
                t.keyframes
            );
        }
        if let Some(labels) = &self.labels {
            out.push_str(&labels.to_text());
        }
        let _ = writeln!(out, "skipped {} messages", self.skipped.total());
        for (kind, e) in &self.skipped.entries {
            let _ = writeln!(out, "  {kind}: {} (first: {})", e.count, e.first);
        }
        if let Some(p) = &self.problems {
            let _ = writeln!(out, "\nnot trainable: {p}");
        }
        out
    }
}
