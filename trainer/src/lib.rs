//! `superflow-trainer` as a library: SuperFlow pretraining of a 3D network on the batches a
//! `superflow-pipeline` publishes. The modules, in the order a batch flows through them:
//!
//! 1. [`subscribe`]: a [`Subscription`](subscribe::Subscription) receives the run's batches
//!    over iceoryx2 shared memory (blocking on the ready event, not spinning) as
//!    [`Received`](subscribe::Received), and asks the pipeline to resume the stream at a
//!    position.
//! 2. [`stream`]: a [`StreamTracker`](stream::StreamTracker) decides, from each batch's
//!    position and publisher, whether to train on it, skip it (already trained) or ask a
//!    restarted pipeline to continue at this trainer's next batch.
//! 3. [`inputs`]: [`StepInputs`](inputs::StepInputs) turns a batch's sections into the
//!    step's tensors, with the losses' host-side [`LossPlan`](loss::LossPlan).
//! 4. [`model`]: the trainable [`SuperFlowModel`](model::SuperFlowModel), the sparse
//!    residual UNet of [`unet`] ([`SparseUNet`](unet::SparseUNet), driven by the kernel
//!    maps in the batch) and a 2D projection head on top of the frozen DINOv2 ViT of [`vit`]
//!    ([`DinoVit`](vit::DinoVit)).
//! 5. [`loss`]: [`SuperFlowLoss`](loss::SuperFlowLoss), the spatial, temporal and
//!    dense-to-sparse contrastive terms over superpoints and superpixels.
//! 6. [`train`]: a [`Trainer`](train::Trainer) runs one step (ViT, UNet, losses, backward,
//!    AdamW with the one-cycle [`lr_schedule`]) and carries the run's state.
//! 7. [`checkpoint`] saves and restores that state atomically, with the stream position to
//!    resume at; [`metrics`] writes one JSON line per step and plots the loss curves.
//!
//! 8. [`run`]: a training run as the `superflow-trainer` binary runs it — start (fresh,
//!    `--resume`, or a data-parallel job over MPI, `ddp`), the step loop, checkpoints on a
//!    schedule and on SIGTERM, the summary; why it fails is a [`RunError`](run::RunError).
//!
//! [`config`] is `trainer.toml` ([`TrainerConfig`](config::TrainerConfig)) with the
//! command line's [`Overrides`](config::Overrides); [`device`] turns a backend name into
//! a device; [`init`] draws the seeded initial weights; [`check`] compares backends on one
//! batch; [`probe`] scores a backbone downstream (its pipeline-fed half behind the `probe`
//! feature, its error [`probe_error`]); [`error`] holds [`TrainerError`](error::TrainerError),
//! the library's error.
//! The binary (`src/bin/superflow-trainer/`) only parses flags and dispatches.
//!
//! ```no_run
//! use std::time::Duration;
//! use superflow_trainer::config::TrainerConfig;
//! use superflow_trainer::stream::{Action, StreamPosition, StreamTracker};
//! use superflow_trainer::subscribe::{Subscription, Target};
//! use superflow_trainer::train::Trainer;
//!
//! let iox = superflow_schemas::service::iceoryx2_config(None)?;
//! let subscription = Subscription::open("default", Target::Rank(0), &iox, 2)?;
//! let mut trainer = Trainer::new(TrainerConfig::default(), &burn::tensor::Device::flex())?;
//! let mut stream = StreamTracker::new(None);
//! while let Some(batch) = subscription.receive(Duration::from_secs(30))? {
//!     let at = StreamPosition::new(batch.header().epoch, batch.header().step);
//!     if stream.classify(batch.origin(), at) != Action::Train {
//!         continue; // the binary also asks a restarted pipeline to resume (see `stream`)
//!     }
//!     let outcome = trainer.step(&batch.view()?)?;
//!     stream.trained(at);
//!     println!("{at}: loss {:.4}", outcome.losses.total);
//! }
//! # Ok::<(), Box<dyn std::error::Error>>(())
//! ```

pub mod check;
pub mod checkpoint;
pub mod config;
#[cfg(feature = "mpi")]
pub mod ddp;
pub mod device;
pub mod error;
pub mod features;
pub mod init;
pub mod inputs;
pub mod loss;
pub mod lr_schedule;
pub mod metrics;
pub mod model;
pub mod probe;
pub mod probe_error;
pub mod rows;
pub mod run;
pub mod stream;
pub mod subscribe;
#[cfg(feature = "probe")]
pub mod sweep_input;
pub mod sync;
pub mod train;
pub mod unet;
pub mod vit;
