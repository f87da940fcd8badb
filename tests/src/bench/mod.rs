//! The measurement code of the benchmarks, in one place: `cargo bench -p superflow-tests
//! --bench summary` runs it all into one table, and the per-area benches of
//! `superflow-pipeline` (`ingest`, `sample`, `transport`) and `superflow-trainer` (`step`)
//! include these files through `#[path]` (those crates cannot depend on this one: it
//! depends on both) for their detailed tables.

pub mod common;
pub mod sample;
pub mod train;
pub mod transport;
