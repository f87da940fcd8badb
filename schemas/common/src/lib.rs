//! What the pipeline and the trainer share besides the batch contract
//! (`superflow-schemas`), so that the trainer needs nothing of the pipeline to train:
//!
//! * [`memory`]: the binaries' global allocator (mimalloc, keeping the pages it frees);
//! * [`invalid`]: [`InvalidSetting`], the one error every `validate` of a configuration
//!   (`pipeline.toml`, `trainer.toml`) returns;
//! * [`logging`]: the binaries' log subscriber;
//! * [`exit`]: the binaries' exit codes, one scheme for all, and how they print an error.

pub mod exit;
pub mod invalid;
pub mod logging;
pub mod memory;

pub use invalid::InvalidSetting;
