//! The trainer's integration tests, one test binary (the burn stack linked once): the
//! losses and the ViT against their PyTorch references, the sparse convolutions against
//! dense ones, wgpu against the CPU, the command line, and the lint over burn's row ops.
//!
//! `cargo test -p superflow-trainer --test integration MODULE::` runs one module.

mod cli;
mod losses;
mod rows_lint;
mod unet;
mod vit;
mod wgpu_ops;
