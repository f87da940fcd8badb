//! [`WeightsError`]: what can be wrong with a DINOv2 checkpoint file. A leaf of the
//! folder: the loader (`load.rs`) and the weight walk (`weights.rs`) both return it.

use std::path::PathBuf;
use superflow_common::InvalidSetting;

/// What can be wrong with a DINOv2 checkpoint file; every message names the file, and the
/// tensor where one is at fault (with its prefix).
#[derive(Debug, thiserror::Error)]
pub enum WeightsError {
    /// The file cannot be read.
    #[error("reading {}: {error}", path.display())]
    Read {
        /// The file.
        path: PathBuf,
        /// The I/O error.
        error: std::io::Error,
    },
    /// The file is not safetensors.
    #[error("parsing safetensors file {}: {error}", path.display())]
    Parse {
        /// The file.
        path: PathBuf,
        /// The parse error.
        error: safetensors::SafeTensorError,
    },
    /// No tensor is a DINOv2 class token.
    #[error(
        "{}: no DINOv2 class token (`cls_token` or `embeddings.cls_token`, possibly \
         prefixed) among its {tensors} tensors",
        path.display()
    )]
    NoClassToken {
        /// The file.
        path: PathBuf,
        /// Tensors in the file.
        tensors: usize,
    },
    /// Several tensors are class tokens.
    #[error(
        "{}: several class tokens ({}); expected one DINOv2 backbone",
        path.display(),
        names.iter().map(|name| format!("`{name}`")).collect::<Vec<_>>().join(", ")
    )]
    SeveralClassTokens {
        /// The file.
        path: PathBuf,
        /// The class tokens' names.
        names: Vec<String>,
    },
    /// A tensor marks an architecture this module does not implement.
    #[error("{}: tensor `{tensor}`: {why}", path.display())]
    Unsupported {
        /// The file.
        path: PathBuf,
        /// The tensor.
        tensor: String,
        /// What is not supported.
        why: &'static str,
    },
    /// A tensor the network needs is missing.
    #[error("{}: missing tensor `{tensor}`", path.display())]
    Missing {
        /// The file.
        path: PathBuf,
        /// The tensor.
        tensor: String,
    },
    /// A tensor has another number of axes.
    #[error("{}: tensor `{tensor}` has shape {shape:?}, expected {rank} axes", path.display())]
    Rank {
        /// The file.
        path: PathBuf,
        /// The tensor.
        tensor: String,
        /// Its shape.
        shape: Vec<usize>,
        /// The axes expected.
        rank: usize,
    },
    /// A tensor has another shape.
    #[error("{}: tensor `{tensor}` has shape {shape:?}, expected {expected:?}", path.display())]
    Shape {
        /// The file.
        path: PathBuf,
        /// The tensor.
        tensor: String,
        /// Its shape.
        shape: Vec<usize>,
        /// The shape expected.
        expected: Vec<usize>,
    },
    /// A tensor is not in f32, f16 or bf16.
    #[error("{}: tensor `{tensor}` has dtype {dtype}; expected F32, F16 or BF16", path.display())]
    Dtype {
        /// The file.
        path: PathBuf,
        /// The tensor.
        tensor: String,
        /// Its dtype.
        dtype: String,
    },
    /// The position embeddings are not a class token plus a square grid.
    #[error(
        "{}: tensor `{tensor}` holds {positions} positions, not a class token plus a square \
         grid",
        path.display()
    )]
    PositionGrid {
        /// The file.
        path: PathBuf,
        /// The tensor.
        tensor: String,
        /// Its positions.
        positions: usize,
    },
    /// The width is no preset's and not a multiple of 64: the head count is unknown.
    #[error(
        "{}: width {dim} (tensor `{tensor}`) is no preset's and not a multiple of 64; \
         the head count is unknown",
        path.display()
    )]
    UnknownHeads {
        /// The file.
        path: PathBuf,
        /// The width.
        dim: usize,
        /// The class token's name.
        tensor: String,
    },
    /// The shape read off the tensors is not a valid network.
    #[error("{}: inferred an invalid shape: {error}", path.display())]
    InvalidShape {
        /// The file.
        path: PathBuf,
        /// The setting at fault.
        error: InvalidSetting,
    },
}
