//! Opening a run's services with the quality of service every process must agree on,
//! and the iceoryx2 configuration that isolates one deployment from another.

use super::error::ServiceSetupError;
use super::messages::{ResumeReply, ResumeRequest, ScheduleReply, ScheduleRequest};
use super::names::{control_service, ready_event_service, schedule_service};

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
    /// `trainer/python/superflow/wire.py` too, and a reader asking for more than an
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

#[cfg(test)]
mod tests {
    use super::*;
    use iceoryx2::prelude::ZeroCopySend;

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
