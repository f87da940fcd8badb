//! `superflow-pipeline inspect`: what a dataset holds, as text or as stable JSON.
//!
//! The JSON form ([`InspectReport`], `"format": "superflow.inspect/1"`) is a contract:
//! fields are only ever added, and a change of meaning bumps the format string.
//!
//! The report's model ([`model`]: what is serialized), how it is gathered from an
//! indexed dataset (`gather`) and its text for people (`text`) are one file each.

mod gather;
mod model;
mod text;

pub use model::{
    CameraReport, CameraTimingReport, ClassCount, DriveReport, FileReport, FrameEdge,
    InspectReport, LabelsReport,
};

/// The format identifier of the JSON report.
pub const INSPECT_FORMAT: &str = "superflow.inspect/1";
