//! [`ServiceError`]: why the service failed.

use superflow_common::InvalidSetting;
use superflow_schemas::batch::BatchError;
use superflow_schemas::service::{IpcError, ServiceSetupError};

/// A failure of the service.
#[derive(Debug, thiserror::Error)]
pub enum ServiceError {
    /// A service could not be opened or created (name, or iceoryx2 refused).
    #[error(transparent)]
    Setup(#[from] ServiceSetupError),
    /// iceoryx2 refused something else (the node, a port, a loan, a send).
    #[error(transparent)]
    Ipc(#[from] IpcError),
    /// A `[service]` setting out of range.
    #[error(transparent)]
    Invalid(#[from] InvalidSetting),
    /// More streams than keyframes: some ranks would get nothing.
    #[error(
        "{streams} stream(s) on each of {hosts} host(s) exceed the {keyframes} keyframes of the drives: some ranks would get nothing"
    )]
    TooManyStreams {
        /// Streams per host.
        streams: u32,
        /// Hosts.
        hosts: u32,
        /// Keyframes of the drives.
        keyframes: usize,
    },
    /// A batch could not be laid out or written.
    #[error("{service}: {source}")]
    Batch {
        /// The batch service.
        service: String,
        /// What is wrong.
        source: BatchError,
    },
    /// The dataset has no keyframe.
    #[error("the drives have no usable keyframe")]
    NoKeyframes,
    /// `--start-sample` beyond the epoch.
    #[error("--start-sample {sample} is past the end of an epoch of {samples} samples")]
    StartPastEpoch {
        /// The sample asked for.
        sample: u64,
        /// Samples per epoch.
        samples: usize,
    },
}

impl ServiceError {
    /// Wraps an iceoryx2 error with what was being done.
    pub(super) fn ipc<E: std::error::Error + Send + Sync + 'static>(
        what: impl Into<String>,
    ) -> impl FnOnce(E) -> Self {
        let wrap = IpcError::doing(what);
        move |source| Self::Ipc(wrap(source))
    }
}
