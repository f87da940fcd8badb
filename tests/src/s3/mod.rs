//! Object storage under test: a real S3-speaking server on 127.0.0.1 ([`S3Server`], moto
//! in a child python process) and an HTTP proxy in front of it that adds latency, a
//! bandwidth cap and faults and counts the requests ([`FaultProxy`], per a
//! [`FaultPlan`]). The pipeline's object-storage reader is tested and benchmarked against
//! them, through `object_store` as in production, without any cloud account.
//!
//! Needs python3 with moto (`pip install -r tests/python/requirements.txt`); the tests
//! that use it fail, not skip, without it.

#![allow(clippy::unwrap_used, clippy::expect_used)] // test support fails loudly

mod plan;
mod proxy;
mod server;
#[cfg(test)]
mod tests;

pub use plan::{Counters, FaultCounts, FaultPlan, FaultScope, PlanError, RequestKind};
pub use proxy::FaultProxy;
pub use server::{Credentials, S3Server};
