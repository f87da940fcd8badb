//! The names of a run's services: `superflow/<run>/...`.

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
}
