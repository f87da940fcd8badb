//! superflow's end-to-end tests, one test binary: the real binaries on the sample drives
//! in `recordings/`, the generator's rigs, the damaged recordings and the deployment
//! files. One binary links the whole stack (burn, wgpu, iceoryx2) once instead of once
//! per file, which keeps the test build's time and disk in bounds on a 2-core CI.
//!
//! `cargo test -p superflow-tests --test e2e MODULE::` runs one module, e.g.
//! `--test e2e replay::`. Tests of different modules run side by side in this one
//! process, so everything a test writes is named by the test and the process id
//! (`superflow_tests::process::prefix`, `superflow_tests::scratch`).

/// The `superflow-subscriber` binary of this package; the other binaries lie beside it
/// (the `subscriber` argument of `superflow_tests::process`).
const SUBSCRIBER: &str = env!("CARGO_BIN_EXE_superflow-subscriber");

mod bad_inputs;
mod batches;
mod camera_sync;
mod damaged_drives;
mod ddp;
mod deploy;
mod fleet;
mod index_cache;
mod ingest_layouts;
mod labels;
mod object_store;
mod projection;
mod python_package;
mod python_reference;
mod regenerate;
mod replay;
mod sample_drives;
mod samples;
mod service;
mod slic_sidecar;
mod trainer;
