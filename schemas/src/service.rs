//! iceoryx2 service names shared by the pipeline and every subscriber.
//!
//! | service | pattern | who receives what |
//! |---|---|---|
//! | `superflow/<run>/batches` | publish-subscribe | broadcast: every subscriber sees every batch |
//! | `superflow/<run>/rank/<r>` | publish-subscribe | shard: rank `r` gets its disjoint share |
//! | `superflow/<run>/control` | request-response | a trainer tells the pipeline where it resumes |
//! | `superflow/<run>/ready` | event | wakes subscribers when a batch was published |

use crate::batch::BatchError;

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
        assert_eq!(
            ready_event_service("superflow/exp1/rank/3"),
            "superflow/exp1/rank/3/ready"
        );
        assert!(batches_service("a/b").is_err());
    }
}
