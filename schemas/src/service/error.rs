//! The errors of setting up and using a run's services, on both sides.

use crate::batch::BatchError;

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
