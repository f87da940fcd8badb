//! The service: an endless (or bounded) stream of batches over iceoryx2.
//!
//! * [`Schedule`] (`schedule.rs`) says which keyframes form batch `step` of `epoch` for
//!   stream `rank`: the epoch's seeded shuffle, dealt round-robin to
//!   `host_count × streams` global ranks (host `h` owns global ranks
//!   `h·streams .. (h+1)·streams`), cut into batches of `batch_size` (the last one of an
//!   epoch may be short — no keyframe is dropped). Every host computes the same shuffle
//!   from the seed, so hosts get disjoint shares that together cover each epoch exactly
//!   once, without talking to each other. A sample's draws are keyed by its position in
//!   the epoch, so the same keyframe gets the same sample whatever the world size or
//!   host count.
//! * A producer thread (`producer.rs`) builds batches ahead (`prefetch`) with rayon; the
//!   publisher loop (`serve.rs`, the calling thread) writes each one in place into a
//!   loaned iceoryx2 slice, sends it and wakes subscribers through the ready event
//!   (`ports.rs`). Where each stream is, shared by both and the control server, is
//!   `cursors.rs`; why the service fails, [`ServiceError`] (`error.rs`).
//! * A batch whose samples all failed to build is still published, as a lost batch
//!   (`BATCH_LOST`, nothing in it) at its place in the stream: subscribers count it and
//!   see their epochs end. A batch of which some samples failed goes out with the rest.
//! * Backpressure never loses a batch: the service does not overflow and the publisher
//!   retries until a full subscriber has room. While it waits it checks, every
//!   `dead_node_check_ms`, whether the subscriber's process has died; a dead one is
//!   cleaned up (iceoryx2 dead-node detection) and skipped, the others keep receiving.
//! * A subscriber resumes through the control service (`control.rs`): it names
//!   `(epoch, samples the whole job had consumed)` — or its own step — and the next
//!   batch of its stream is the one there; a job resumed on another number of ranks or
//!   hosts continues the epoch at that sample ([`Schedule`]).
//! * [`Metrics`] (`metrics.rs`) counts what happens, for the log and Prometheus;
//!   [`ServiceConfig`] (`config.rs`) is `[service]` of `pipeline.toml`.
//! * [`SideTasks`] (`side_tasks.rs`): the SIGINT/SIGTERM handlers that stop the service
//!   and the Prometheus endpoint.

mod config;
mod control;
mod cursors;
mod error;
mod metrics;
mod plan_id;
mod ports;
mod producer;
mod schedule;
mod serve;
mod side_tasks;

pub use config::{Mode, Order, ServiceConfig};
pub use error::ServiceError;
pub use metrics::Metrics;
pub use plan_id::PlanId;
pub use schedule::{Schedule, Slot};
pub use serve::serve;
pub use side_tasks::{SideTaskError, SideTasks};
/// Where the service starts: at a step of every stream (`--start-step`), or after the
/// samples of an epoch a job of any size had consumed (`--start-sample`; its
/// `global_batch` is not used).
pub use superflow_schemas::service::ResumeAt;
