//! iceoryx2 service names shared by the pipeline and every subscriber.
//!
//! | service | pattern | who receives what |
//! |---|---|---|
//! | `superflow/<run>/batches` | publish-subscribe | broadcast: every subscriber sees every batch |
//! | `superflow/<run>/rank/<r>` | publish-subscribe | shard: rank `r` gets its disjoint share |
//! | `superflow/<run>/control` | request-response | a trainer tells the pipeline where it resumes |
//! | `superflow/<run>/schedule` | request-response | a subscriber asks how long its stream's epochs are and how many there are |
//! | `superflow/<run>/ready` | event | wakes subscribers when a batch was published |//!
//! What each file holds: the messages of the request-response services ([`messages`]),
//! the names of a run's services ([`names`]), how a process opens them with the shared
//! quality of service ([`open`]), and the errors of both sides ([`error`]).

mod error;
mod messages;
mod names;
mod open;

pub use error::{IpcError, ServiceSetupError};
pub use messages::{ResumeAt, ResumeReply, ResumeRequest, ScheduleReply, ScheduleRequest, UNKNOWN};
pub use names::{
    SERVICE_PREFIX, batches_service, control_service, rank_service, ready_event_service,
    schedule_service,
};
pub use open::{
    BatchService, ControlService, ReadyService, ScheduleService, iceoryx2_config,
    open_batch_service, open_control_service, open_ready_service, open_schedule_service, qos,
};
