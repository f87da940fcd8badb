//! Asking the pipeline where this trainer's stream continues: when a run resumes
//! ([`super::start`]) and when a running session's pipeline restarts
//! ([`super::session`]).

use super::error::{ResumeRefused, RunError};
use crate::stream::StreamPosition;
use crate::subscribe::{ResumeAt, Subscription};
use std::time::Duration;

/// Asks the pipeline to continue this trainer's stream at `at`; the publisher that
/// answered, and the position its next batch has there. A refusal is a
/// [`ResumeRefused`] ([`RunError::run_complete`] tells a finished run).
pub fn ask_resume(
    subscription: &Subscription,
    run: &str,
    at: ResumeAt,
    timeout: Duration,
) -> Result<(u128, StreamPosition), RunError> {
    let reply = subscription
        .resume(at, timeout)
        .map_err(|source| RunError::AskResume {
            run: run.to_string(),
            source,
        })?;
    if reply.accepted != 1 {
        return Err(ResumeRefused::of(run, at, &reply).into());
    }
    Ok((
        reply.publisher(),
        StreamPosition::new(reply.epoch, reply.step),
    ))
}
