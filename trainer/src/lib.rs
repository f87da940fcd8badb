//! `superflow-trainer` as a library: [`subscribe`] receives the pipeline's batches over
//! iceoryx2 (blocking on the ready event, not spinning) and asks the pipeline to resume a
//! stream at a position. The networks and losses arrive with the trainer issue.
//!
//! ```no_run
//! use std::time::Duration;
//! use superflow_trainer::subscribe::{Subscription, Target};
//!
//! let iox = superflow_schemas::service::iceoryx2_config(None)?;
//! let subscription = Subscription::open("default", Target::Rank(0), &iox, 2)?;
//! if let Some(batch) = subscription.receive(Duration::from_secs(30))? {
//!     let view = batch.view()?;
//!     println!("epoch {} step {}: {} samples", view.meta().epoch, view.meta().step,
//!              view.meta().sample_count);
//! }
//! # Ok::<(), Box<dyn std::error::Error>>(())
//! ```

pub mod checkpoint;
pub mod config;
pub mod init;
pub mod inputs;
pub mod loss;
pub mod metrics;
pub mod model;
pub mod schedule;
pub mod sparse;
pub mod subscribe;
pub mod train;
pub mod vit;
