//! iceoryx2 service names shared by the pipeline and every subscriber.
//!
//! | service | pattern | who receives what |
//! |---|---|---|
//! | `superflow/<run>/batches` | publish-subscribe | broadcast: every subscriber sees every batch |
//! | `superflow/<run>/rank/<r>` | publish-subscribe | shard: rank `r` gets its disjoint share |
//! | `superflow/<run>/control` | request-response | a trainer tells the pipeline where it resumes |
//! | `superflow/<run>/schedule` | request-response | a subscriber asks how long its stream's epochs are and how many there are |
//! | `superflow/<run>/ready` | event | wakes subscribers when a batch was published |

use crate::batch::BatchError;
use iceoryx2::prelude::ZeroCopySend;

/// Asks the pipeline to continue stream `rank` (0 in broadcast mode) at a position of
/// epoch `epoch`: by `sample` when known — the samples of the epoch the whole job (every
/// rank of every host) had consumed, which holds whatever the job's size — else by
/// `step` of this stream. The next batch published on that service is the one at that
/// position. Sent on the control service.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Default, ZeroCopySend)]
#[type_name("superflow::ResumeRequest")]
#[repr(C)]
pub struct ResumeRequest {
    /// Shard rank (0 for the broadcast stream).
    pub rank: u32,
    /// 1 when the request is for the broadcast stream.
    pub broadcast: u32,
    /// Epoch to resume at.
    pub epoch: u64,
    /// Step within that epoch (used when `sample` is [`UNKNOWN`]).
    pub step: u64,
    /// Samples of `epoch` the whole job had consumed ([`UNKNOWN`]: resume by `step`).
    pub sample: u64,
    /// Samples per step of the whole job that saved the position (batch size × streams
    /// of all hosts; [`UNKNOWN`] when not known). A `step` saved by a job of another
    /// size names another position: such a request is refused (reason 3).
    pub global_batch: u64,
}

/// A field a request does not know.
pub const UNKNOWN: u64 = u64::MAX;

/// Where a stream continues (a resume request) or a service starts.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum ResumeAt {
    /// At `step` of `epoch` of the stream: a position of a job of this size.
    Step {
        /// The epoch.
        epoch: u64,
        /// The step of the stream.
        step: u64,
    },
    /// After `sample` samples of `epoch`, consumed by the whole job (every rank and
    /// host) that saved the position with `global_batch` samples per step ([`UNKNOWN`]
    /// when not known): holds across a change of the job's size.
    Sample {
        /// The epoch.
        epoch: u64,
        /// Samples of it the job had consumed.
        sample: u64,
        /// Samples per step of the job that saved it.
        global_batch: u64,
    },
}

impl ResumeAt {
    /// The request of stream `rank` (`broadcast`: the broadcast stream).
    pub fn request(self, rank: u32, broadcast: bool) -> ResumeRequest {
        match self {
            ResumeAt::Step { epoch, step } => ResumeRequest::at_step(rank, broadcast, epoch, step),
            ResumeAt::Sample {
                epoch,
                sample,
                global_batch,
            } => ResumeRequest {
                sample,
                global_batch,
                ..ResumeRequest::at_step(rank, broadcast, epoch, UNKNOWN)
            },
        }
    }

    /// The epoch.
    pub fn epoch(self) -> u64 {
        match self {
            ResumeAt::Step { epoch, .. } | ResumeAt::Sample { epoch, .. } => epoch,
        }
    }
}

impl ResumeRequest {
    /// A request by step, the position's job size unknown.
    pub fn at_step(rank: u32, broadcast: bool, epoch: u64, step: u64) -> Self {
        Self {
            rank,
            broadcast: u32::from(broadcast),
            epoch,
            step,
            sample: UNKNOWN,
            global_batch: UNKNOWN,
        }
    }
}

/// The pipeline's answer to a [`ResumeRequest`].
#[derive(Debug, Clone, Copy, PartialEq, Eq, Default, ZeroCopySend)]
#[type_name("superflow::ResumeReply")]
#[repr(C)]
pub struct ResumeReply {
    /// 1: the stream continues at the requested position; 0: refused (see `reason`).
    pub accepted: u32,
    /// Why a request was refused: 0 accepted; [`ResumeReply::NO_SUCH_STREAM`] (1);
    /// [`ResumeReply::OUT_OF_RANGE`] (2); [`ResumeReply::OTHER_JOB_SIZE`] (3);
    /// [`ResumeReply::RUN_COMPLETE`] (4, and `epoch` holds the configured epoch count).
    pub reason: u32,
    /// Sequence number of the first batch at the new position (publisher-wide).
    pub next_sequence: u64,
    /// Low 64 bits of the id of the publisher that will send it (batches of an earlier,
    /// dead pipeline carry another id).
    pub publisher_lo: u64,
    /// High 64 bits of that id.
    pub publisher_hi: u64,
    /// Epoch of the first batch at the new position; refused with
    /// [`ResumeReply::RUN_COMPLETE`]: the epochs the pipeline serves (`--epochs`).
    pub epoch: u64,
    /// Its step in this stream (a request by sample names the step it became).
    pub step: u64,
}

impl ResumeReply {
    /// `reason`: no such stream (rank out of range, or the pipeline runs in the other
    /// mode).
    pub const NO_SUCH_STREAM: u32 = 1;
    /// `reason`: a position that does not exist: a step past its epoch's end, a sample
    /// past the epoch's samples, in an epoch before the last.
    pub const OUT_OF_RANGE: u32 = 2;
    /// `reason`: a step saved by a job of another size (`global_batch` differs): resume
    /// by sample.
    pub const OTHER_JOB_SIZE: u32 = 3;
    /// `reason`: the run is complete. The position is at or past the end of the
    /// configured epochs (`--epochs E`): epoch `E` or later, or the end of epoch `E - 1`
    /// (its last step + 1, or all its samples). Nothing is left to serve; the reply's
    /// `epoch` is `E`. A requeued job of a finished run gets this, not an error.
    pub const RUN_COMPLETE: u32 = 4;

    /// The publisher id (iceoryx2 `UniquePublisherId` value).
    pub fn publisher(&self) -> u128 {
        (u128::from(self.publisher_hi) << 64) | u128::from(self.publisher_lo)
    }
}

/// Asks the pipeline how its stream `rank` (0 in broadcast mode) is scheduled. Sent on
/// the schedule service; the answer comes from a thread of its own, so it never waits
/// behind a publisher blocked on a full queue.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Default, ZeroCopySend)]
#[type_name("superflow::ScheduleRequest")]
#[repr(C)]
pub struct ScheduleRequest {
    /// Shard rank (0 for the broadcast stream).
    pub rank: u32,
    /// 1 when the request is for the broadcast stream.
    pub broadcast: u32,
}

/// The pipeline's answer to a [`ScheduleRequest`]. With it a subscriber knows which batch
/// ends an epoch of its stream (step `steps - 1`, or `start_steps - 1` in epoch
/// `start_epoch`) and which ends the stream (that step of epoch `epochs - 1`): only
/// `--epochs` reached ends a stream, a pipeline stopped by a signal and restarted does
/// not. It also tells how many samples of an epoch the whole job has consumed at a
/// position ([`ScheduleReply::consumed`]): what a checkpoint keeps so that a job resumes
/// on any number of ranks and hosts.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Default, ZeroCopySend)]
#[type_name("superflow::ScheduleReply")]
#[repr(C)]
pub struct ScheduleReply {
    /// 1: the fields below hold the stream's schedule; 0: no such stream (rank out of
    /// range, or the pipeline runs in the other mode).
    pub known: u32,
    /// 0, reserved.
    pub reserved: u32,
    /// Batches per epoch of this stream.
    pub steps: u64,
    /// The fewest batches per epoch of any stream of the run, all hosts included: where
    /// data-parallel ranks stop an epoch together when the keyframes do not divide evenly.
    pub min_steps: u64,
    /// Epochs the pipeline serves (`--epochs`); 0: endless.
    pub epochs: u64,
    /// Low 64 bits of the id of the stream's publisher.
    pub publisher_lo: u64,
    /// High 64 bits of that id.
    pub publisher_hi: u64,
    /// Samples per epoch, all ranks and hosts together (every dataset group's keyframes
    /// times its repeat).
    pub samples: u64,
    /// Samples per step of the whole job: batch size × streams of all hosts.
    pub global_batch: u64,
    /// The epoch that starts part-way, at sample `start_sample` (a job resumed on
    /// another size: `--start-sample`, or a resume request by sample); every other epoch
    /// starts at sample 0.
    pub start_epoch: u64,
    /// See `start_epoch`.
    pub start_sample: u64,
    /// Batches of this stream in epoch `start_epoch`.
    pub start_steps: u64,
    /// The fewest batches of any stream in epoch `start_epoch`.
    pub start_min_steps: u64,
    /// The run's seed (`[sample] seed`): with `(epoch, sample)` it fixes every draw.
    pub seed: u64,
    /// This pipeline's host among `host_count` (`[service] host_rank`).
    pub host_rank: u32,
    /// Hosts whose pipelines share each epoch (`[service] host_count`).
    pub host_count: u32,
    /// Distinct keyframes of the whole dataset (every host's share, before the dataset
    /// groups' repeats).
    pub keyframes: u64,
    /// A digest of what defines the samples served: the seed, the sample recipe, the
    /// dataset groups with their repeats, and per drive its keyframes (count and
    /// stamps); never file paths. Every host of one job must show the same digest, or
    /// its pipelines deal different epochs and the hosts' shares overlap or leave gaps.
    pub plan_digest: u64,
}

impl ScheduleReply {
    /// The publisher id (iceoryx2 `UniquePublisherId` value).
    pub fn publisher(&self) -> u128 {
        (u128::from(self.publisher_hi) << 64) | u128::from(self.publisher_lo)
    }

    /// Whether `epoch` starts part-way (at `start_sample > 0`).
    fn part_way(&self, epoch: u64) -> bool {
        epoch == self.start_epoch && self.start_sample > 0
    }

    /// Batches of this stream in `epoch`.
    pub fn steps_in(&self, epoch: u64) -> u64 {
        if self.part_way(epoch) {
            self.start_steps
        } else {
            self.steps
        }
    }

    /// The fewest batches of any stream in `epoch`.
    pub fn min_steps_in(&self, epoch: u64) -> u64 {
        if self.part_way(epoch) {
            self.start_min_steps
        } else {
            self.min_steps
        }
    }

    /// Whether the batch at `(epoch, step)` is the last of its epoch in this stream.
    pub fn ends_epoch(&self, epoch: u64, step: u64) -> bool {
        self.known == 1 && step + 1 >= self.steps_in(epoch)
    }

    /// Whether the batch at `(epoch, step)` is the last of the stream.
    pub fn ends_stream(&self, epoch: u64, step: u64) -> bool {
        self.ends_epoch(epoch, step) && self.epochs > 0 && epoch + 1 >= self.epochs
    }

    /// The samples of `epoch` the whole job has consumed once every stream has taken its
    /// first `steps` batches of it (data-parallel ranks step together): the epoch's
    /// first sample plus `steps` global batches, at most the epoch. Keyframes are dealt
    /// round-robin, so those samples are exactly the epoch's first ones in its order.
    pub fn consumed(&self, epoch: u64, steps: u64) -> u64 {
        let first = if self.part_way(epoch) {
            self.start_sample.min(self.samples)
        } else {
            0
        };
        first
            + steps
                .saturating_mul(self.global_batch)
                .min(self.samples - first)
    }

    /// The step of this stream at which a resume by `sample` of `epoch` continues: the
    /// step boundary at that sample, or 0 when it falls inside a step (the pipeline then
    /// starts the epoch there, see `ResumeRequest`).
    pub fn step_at(&self, epoch: u64, sample: u64) -> u64 {
        let first = if self.part_way(epoch) {
            self.start_sample
        } else {
            0
        };
        match sample.checked_sub(first) {
            Some(taken) if self.global_batch > 0 && taken.is_multiple_of(self.global_batch) => {
                taken / self.global_batch
            }
            Some(taken) if self.global_batch > 0 && sample == self.samples => {
                taken.div_ceil(self.global_batch)
            }
            _ => 0,
        }
    }
}

/// Quality of service of a batch service, the same for every process that opens it
/// (iceoryx2 refuses to open a service with incompatible settings). Lossless:
/// no safe overflow, so a full subscriber queue makes the publisher wait.
pub mod qos {
    /// Subscribers per batch service (trainers, probes, Python readers).
    pub const MAX_SUBSCRIBERS: usize = 8;
    /// Largest receive queue a subscriber may ask for (batches).
    pub const MAX_BUFFER: usize = 4;
    /// Batches a subscriber may hold at once. The Python package's `max_held` (batches
    /// released while views of them are alive, plus the current one) is bounded by it.
    /// Every process opening a service must agree: raising it means raising it in
    /// `trainer/python/superflow/stream.py` too, and a reader asking for more than an
    /// older pipeline created the service with cannot open it.
    pub const MAX_BORROWED: usize = 2;
    /// Publishers: the pipeline, plus one restarting while the old one is cleaned up.
    pub const MAX_PUBLISHERS: usize = 2;
    /// Nodes attached to one service.
    pub const MAX_NODES: usize = 16;
}

/// The batch service type: `[u8]` payload with a [`crate::batch::BatchHeader`] user header.
pub type BatchService = iceoryx2::service::port_factory::publish_subscribe::PortFactory<
    iceoryx2::prelude::ipc::Service,
    [u8],
    crate::batch::BatchHeader,
>;

/// iceoryx2 refusing an operation on a node or port (creating the node or a port, a
/// loan, a send, a receive, a request), with what was being done. Both sides of the
/// service report it.
#[derive(Debug, thiserror::Error)]
#[error("{what}: {source}")]
pub struct IpcError {
    /// What was being done, naming the service.
    pub what: String,
    /// iceoryx2's error.
    pub source: Box<dyn std::error::Error + Send + Sync>,
}

impl IpcError {
    /// `map_err(IpcError::doing("creating the publisher of superflow/run/batches"))`.
    pub fn doing<E: std::error::Error + Send + Sync + 'static>(
        what: impl Into<String>,
    ) -> impl FnOnce(E) -> Self {
        let what = what.into();
        move |source| Self {
            what,
            source: Box::new(source),
        }
    }
}

/// A service that cannot be set up: a bad name or prefix, or iceoryx2 refusing to open
/// or create it (e.g. another process opened it with incompatible settings).
#[derive(Debug, thiserror::Error)]
pub enum ServiceSetupError {
    /// The run name is not valid.
    #[error(transparent)]
    Run(#[from] BatchError),
    /// iceoryx2 does not accept the service name.
    #[error("service name `{name}`: {source}")]
    Name {
        /// The name.
        name: String,
        /// iceoryx2's reason.
        source: iceoryx2::service::service_name::ServiceNameError,
    },
    /// Opening or creating a batch service failed.
    #[error("opening service `{name}`: {source}")]
    Batch {
        /// The service.
        name: String,
        /// iceoryx2's reason.
        source: iceoryx2::service::builder::publish_subscribe::PublishSubscribeOpenOrCreateError,
    },
    /// Opening or creating a ready event service failed.
    #[error("opening service `{name}`: {source}")]
    Ready {
        /// The service.
        name: String,
        /// iceoryx2's reason.
        source: iceoryx2::service::builder::event::EventOpenOrCreateError,
    },
    /// Opening or creating the control service failed.
    #[error("opening service `{name}`: {source}{}", other_layout(.source, "ResumeRequest or ResumeReply"))]
    Control {
        /// The service.
        name: String,
        /// iceoryx2's reason.
        source: iceoryx2::service::builder::request_response::RequestResponseOpenOrCreateError,
    },
    /// Opening or creating the schedule service failed.
    #[error("opening the schedule service `{name}`: {source}{}", other_layout(.source, "ScheduleReply"))]
    Schedule {
        /// The service.
        name: String,
        /// iceoryx2's reason.
        source: iceoryx2::service::builder::request_response::RequestResponseOpenOrCreateError,
    },
    /// The iceoryx2 prefix breaks the rule.
    #[error("iceoryx2 prefix `{prefix}` must be 1..=32 of A-Z a-z 0-9 _ -")]
    Prefix {
        /// The prefix.
        prefix: String,
    },
    /// iceoryx2 does not accept the prefix as a file name.
    #[error("iceoryx2 prefix `{prefix}`: {source}")]
    PrefixFile {
        /// The prefix.
        prefix: String,
        /// iceoryx2's reason.
        source: iceoryx2::prelude::SemanticStringError,
    },
}

/// What to add to iceoryx2's refusal of a request-response service whose request or
/// reply type (`types`) another process created with another layout: which process
/// and what to do, since iceoryx2 names only the error.
fn other_layout(
    source: &iceoryx2::service::builder::request_response::RequestResponseOpenOrCreateError,
    types: &str,
) -> String {
    use iceoryx2::service::builder::request_response::{
        RequestResponseOpenError, RequestResponseOpenOrCreateError,
    };
    match source {
        RequestResponseOpenOrCreateError::RequestResponseOpenError(
            RequestResponseOpenError::IncompatibleRequestOrResponseType,
        ) => format!(
            " — a process of another superflow version created it with another {types} layout: run the pipeline and every trainer or reader of the run from one version"
        ),
        _ => String::new(),
    }
}

/// `name` as an iceoryx2 service name.
fn service_name(name: &str) -> Result<iceoryx2::prelude::ServiceName, ServiceSetupError> {
    name.try_into().map_err(|source| ServiceSetupError::Name {
        name: name.to_string(),
        source,
    })
}

/// Opens (or creates) the batch service `name` with the [`qos`] settings.
pub fn open_batch_service(
    node: &iceoryx2::prelude::Node<iceoryx2::prelude::ipc::Service>,
    name: &str,
) -> Result<BatchService, ServiceSetupError> {
    node.service_builder(&service_name(name)?)
        .publish_subscribe::<[u8]>()
        .user_header::<crate::batch::BatchHeader>()
        .enable_safe_overflow(false)
        .history_size(0)
        .subscriber_max_buffer_size(qos::MAX_BUFFER)
        .subscriber_max_borrowed_samples(qos::MAX_BORROWED)
        .max_subscribers(qos::MAX_SUBSCRIBERS)
        .max_publishers(qos::MAX_PUBLISHERS)
        .max_nodes(qos::MAX_NODES)
        .open_or_create()
        .map_err(|source| ServiceSetupError::Batch {
            name: name.to_string(),
            source,
        })
}

/// The event service that wakes subscribers of `batch_service`.
pub type ReadyService =
    iceoryx2::service::port_factory::event::PortFactory<iceoryx2::prelude::ipc::Service>;

/// Opens (or creates) the wake-up event service of a batch service.
pub fn open_ready_service(
    node: &iceoryx2::prelude::Node<iceoryx2::prelude::ipc::Service>,
    batch_service: &str,
) -> Result<ReadyService, ServiceSetupError> {
    let name = ready_event_service(batch_service);
    node.service_builder(&service_name(&name)?)
        .event()
        .max_nodes(qos::MAX_NODES)
        .max_listeners(qos::MAX_SUBSCRIBERS)
        .max_notifiers(qos::MAX_PUBLISHERS)
        .open_or_create()
        .map_err(|source| ServiceSetupError::Ready { name, source })
}

/// The schedule service type (request-response).
pub type ScheduleService = iceoryx2::service::port_factory::request_response::PortFactory<
    iceoryx2::prelude::ipc::Service,
    ScheduleRequest,
    (),
    ScheduleReply,
    (),
>;

/// Opens (or creates) the schedule service of a run.
pub fn open_schedule_service(
    node: &iceoryx2::prelude::Node<iceoryx2::prelude::ipc::Service>,
    run: &str,
) -> Result<ScheduleService, ServiceSetupError> {
    let name = schedule_service(run)?;
    node.service_builder(&service_name(&name)?)
        .request_response::<ScheduleRequest, ScheduleReply>()
        .max_clients(qos::MAX_SUBSCRIBERS * 4)
        .max_servers(qos::MAX_PUBLISHERS)
        .max_nodes(qos::MAX_NODES * 2)
        .open_or_create()
        .map_err(|source| ServiceSetupError::Schedule { name, source })
}

/// The control service type (request-response).
pub type ControlService = iceoryx2::service::port_factory::request_response::PortFactory<
    iceoryx2::prelude::ipc::Service,
    ResumeRequest,
    (),
    ResumeReply,
    (),
>;

/// Opens (or creates) the control service of a run.
pub fn open_control_service(
    node: &iceoryx2::prelude::Node<iceoryx2::prelude::ipc::Service>,
    run: &str,
) -> Result<ControlService, ServiceSetupError> {
    let name = control_service(run)?;
    node.service_builder(&service_name(&name)?)
        .request_response::<ResumeRequest, ResumeReply>()
        .max_clients(qos::MAX_SUBSCRIBERS * 4)
        .max_servers(qos::MAX_PUBLISHERS)
        .max_nodes(qos::MAX_NODES * 2)
        .open_or_create()
        .map_err(|source| ServiceSetupError::Control { name, source })
}

/// The iceoryx2 configuration of superflow processes. `prefix` (from
/// `SUPERFLOW_IOX_PREFIX` in the binaries) isolates one deployment's shared-memory
/// files and service names from another's on the same host (each test uses its own).
pub fn iceoryx2_config(
    prefix: Option<&str>,
) -> Result<iceoryx2::config::Config, ServiceSetupError> {
    let mut config = iceoryx2::config::Config::default();
    if let Some(prefix) = prefix {
        let valid = !prefix.is_empty()
            && prefix.len() <= 32
            && prefix
                .bytes()
                .all(|b| b.is_ascii_alphanumeric() || b == b'_' || b == b'-');
        if !valid {
            return Err(ServiceSetupError::Prefix {
                prefix: prefix.to_string(),
            });
        }
        use iceoryx2::prelude::SemanticString as _;
        config.global.prefix = iceoryx2::prelude::FileName::new(format!("{prefix}_").as_bytes())
            .map_err(|source| ServiceSetupError::PrefixFile {
                prefix: prefix.to_string(),
                source,
            })?;
    }
    Ok(config)
}

/// Prefix of every service name.
pub const SERVICE_PREFIX: &str = "superflow";

/// The broadcast service of a run: `superflow/<run>/batches`.
pub fn batches_service(run: &str) -> Result<String, BatchError> {
    crate::batch::validate_run_name(run)?;
    Ok(format!("{SERVICE_PREFIX}/{run}/batches"))
}

/// The shard service of one data-parallel rank: `superflow/<run>/rank/<rank>`.
pub fn rank_service(run: &str, rank: u32) -> Result<String, BatchError> {
    crate::batch::validate_run_name(run)?;
    Ok(format!("{SERVICE_PREFIX}/{run}/rank/{rank}"))
}

/// The control (resume) service of a run: `superflow/<run>/control`.
pub fn control_service(run: &str) -> Result<String, BatchError> {
    crate::batch::validate_run_name(run)?;
    Ok(format!("{SERVICE_PREFIX}/{run}/control"))
}

/// The schedule service of a run: `superflow/<run>/schedule`.
pub fn schedule_service(run: &str) -> Result<String, BatchError> {
    crate::batch::validate_run_name(run)?;
    Ok(format!("{SERVICE_PREFIX}/{run}/schedule"))
}

/// The wake-up event service that goes with a batch service: `<service>/ready`.
pub fn ready_event_service(batch_service: &str) -> String {
    format!("{batch_service}/ready")
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn names_follow_the_design() {
        assert_eq!(batches_service("exp1").unwrap(), "superflow/exp1/batches");
        assert_eq!(rank_service("exp1", 3).unwrap(), "superflow/exp1/rank/3");
        assert_eq!(control_service("exp1").unwrap(), "superflow/exp1/control");
        assert_eq!(schedule_service("exp1").unwrap(), "superflow/exp1/schedule");
        assert_eq!(
            ready_event_service("superflow/exp1/rank/3"),
            "superflow/exp1/rank/3/ready"
        );
        assert!(batches_service("a/b").is_err());
    }

    #[test]
    fn a_schedule_says_which_batches_end_an_epoch_and_the_stream() {
        let reply = ScheduleReply {
            known: 1,
            steps: 3,
            min_steps: 2,
            epochs: 2,
            ..ScheduleReply::default()
        };
        assert!(!reply.ends_epoch(0, 1) && reply.ends_epoch(0, 2));
        assert!(!reply.ends_stream(0, 2) && !reply.ends_stream(1, 1));
        assert!(reply.ends_stream(1, 2));
        let endless = ScheduleReply { epochs: 0, ..reply };
        assert!(endless.ends_epoch(7, 2) && !endless.ends_stream(7, 2));
        assert!(!ScheduleReply::default().ends_epoch(0, 0));
    }

    #[test]
    fn a_schedule_counts_what_the_job_consumed_and_the_part_way_epoch() {
        // 22 samples an epoch, 2 ranks of batches of 3: 6 a step. Epoch 4 resumed at 10.
        let reply = ScheduleReply {
            known: 1,
            steps: 4,
            min_steps: 3,
            samples: 22,
            global_batch: 6,
            start_epoch: 4,
            start_sample: 10,
            start_steps: 2,
            start_min_steps: 2,
            ..ScheduleReply::default()
        };
        assert_eq!(reply.consumed(3, 0), 0);
        assert_eq!(reply.consumed(3, 2), 12);
        assert_eq!(reply.consumed(3, 4), 22, "at most the epoch");
        assert_eq!(reply.consumed(4, 0), 10);
        assert_eq!(reply.consumed(4, 1), 16);
        assert_eq!(reply.consumed(4, 2), 22);
        assert_eq!((reply.steps_in(4), reply.steps_in(5)), (2, 4));
        assert_eq!((reply.min_steps_in(4), reply.min_steps_in(0)), (2, 3));
        assert!(reply.ends_epoch(4, 1) && !reply.ends_epoch(5, 1));
        assert_eq!(reply.step_at(3, 12), 2);
        assert_eq!(reply.step_at(3, 22), 4);
        assert_eq!(
            reply.step_at(3, 13),
            0,
            "inside a step: the epoch starts there"
        );
        assert_eq!(reply.step_at(4, 16), 1);
    }

    /// The offsets `BATCH_FORMAT.md` documents and the Python package mirrors.
    #[test]
    fn reply_layouts_match_the_documented_offsets() {
        use std::mem::{offset_of, size_of};
        assert_eq!(size_of::<ScheduleReply>(), 128);
        assert_eq!(offset_of!(ScheduleReply, start_min_steps), 88);
        assert_eq!(offset_of!(ScheduleReply, seed), 96);
        assert_eq!(offset_of!(ScheduleReply, host_rank), 104);
        assert_eq!(offset_of!(ScheduleReply, host_count), 108);
        assert_eq!(offset_of!(ScheduleReply, keyframes), 112);
        assert_eq!(offset_of!(ScheduleReply, plan_digest), 120);
        assert_eq!(size_of::<ResumeReply>(), 48);
        assert_eq!(offset_of!(ResumeReply, epoch), 32);
        assert_eq!(size_of::<ResumeRequest>(), 40);
        assert_eq!(
            [
                ResumeReply::NO_SUCH_STREAM,
                ResumeReply::OUT_OF_RANGE,
                ResumeReply::OTHER_JOB_SIZE,
                ResumeReply::RUN_COMPLETE
            ],
            [1, 2, 3, 4]
        );
    }

    /// The schedule reply of an earlier version (before the plan fields): a peer that
    /// created the service with it is named, with what to do.
    #[derive(Debug, Clone, Copy, Default, ZeroCopySend)]
    #[type_name("superflow::ScheduleReply")]
    #[repr(C)]
    struct EarlierScheduleReply {
        known: u32,
        reserved: u32,
        fields: [u64; 11],
    }

    #[test]
    fn a_schedule_service_of_another_layout_is_named() {
        use iceoryx2::prelude::*;
        let prefix = format!("sfschedlayout{}", std::process::id());
        let config = iceoryx2_config(Some(&prefix)).unwrap();
        let node = NodeBuilder::new()
            .config(&config)
            .create::<ipc::Service>()
            .unwrap();
        let name = schedule_service("layout").unwrap();
        let earlier = node
            .service_builder(&name.as_str().try_into().unwrap())
            .request_response::<ScheduleRequest, EarlierScheduleReply>()
            .max_clients(qos::MAX_SUBSCRIBERS * 4)
            .max_servers(qos::MAX_PUBLISHERS)
            .max_nodes(qos::MAX_NODES * 2)
            .open_or_create()
            .unwrap();
        let err = open_schedule_service(&node, "layout").unwrap_err();
        assert!(matches!(err, ServiceSetupError::Schedule { .. }), "{err}");
        let text = err.to_string();
        assert!(
            text.contains("opening the schedule service `superflow/layout/schedule`"),
            "{text}"
        );
        assert!(
            text.contains("another ScheduleReply layout: run the pipeline and every trainer"),
            "{text}"
        );
        drop(earlier);
    }

    #[test]
    fn a_bad_prefix_is_named() {
        assert!(iceoryx2_config(Some("ok_prefix-1")).is_ok());
        for bad in ["", "a/b", &"x".repeat(33)] {
            let err = iceoryx2_config(Some(bad)).unwrap_err();
            assert!(matches!(err, ServiceSetupError::Prefix { .. }), "{err}");
            assert!(err.to_string().contains("must be 1..=32"), "{err}");
        }
    }
}
