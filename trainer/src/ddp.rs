//! Synchronous data parallelism over MPI (`superflow-trainer --ddp` under `mpirun`,
//! `srun --mpi=pmix` or the MPI Operator): the collectives a step needs, on the job's
//! world communicator, each guarded by a timeout.
//!
//! * [`Ddp::all_reduce_sum`]: the step's [`GradientBuffer`](crate::sync::GradientBuffer)
//!   summed over the ranks (one `MPI_Allreduce` of `f32`);
//! * [`Ddp::broadcast_bytes`]: rank 0's model (and, when resuming, optimizer and
//!   checkpoint state) to every rank, so that all start from the same parameters;
//! * [`Ddp::all_gather`]: a few numbers per rank (stream positions, stop flags).
//!
//! A rank that dies ends the job (MPI's contract: `mpirun` kills the others). A rank that
//! hangs would leave the others blocked in a collective forever, so every collective
//! runs under a watchdog: past the timeout it logs which collective of which step waited
//! too long and aborts the job (`MPI_Abort`, exit code [`ABORT_CODE`]).
//!
//! Ranks on one host are told apart by a shared-memory split of the world
//! ([`Ddp::local_rank`]): each subscribes to the shard stream of that number from its
//! host's pipeline (`superflow-pipeline --mode shard --world-size <ranks on the host>`).

use crate::error::TrainerError;
use mpi::Threading;
use mpi::collective::SystemOperation;
use mpi::environment::Universe;
use mpi::topology::{Communicator, SimpleCommunicator};
use mpi::traits::*;
use std::sync::{Arc, Mutex};
use std::time::{Duration, Instant};

/// Exit code of a job aborted by the collective watchdog.
pub const ABORT_CODE: i32 = superflow_common::exit::PEER_FAILED as i32;

/// The MPI job as this rank sees it.
pub struct Ddp {
    /// Finalizes MPI when dropped.
    _universe: Universe,
    world: SimpleCommunicator,
    rank: usize,
    size: usize,
    local_rank: usize,
    local_size: usize,
    watchdog: Watchdog,
}

impl std::fmt::Debug for Ddp {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.debug_struct("Ddp")
            .field("rank", &self.rank)
            .field("size", &self.size)
            .field("local_rank", &self.local_rank)
            .field("local_size", &self.local_size)
            .finish_non_exhaustive()
    }
}

impl Ddp {
    /// Joins the MPI job (a process started without a launcher is a job of one); every
    /// collective later gives up after `timeout`.
    pub fn init(timeout: Duration) -> Result<Self, TrainerError> {
        let (universe, threading) = mpi::initialize_with_threading(Threading::Multiple)
            .ok_or(TrainerError::MpiInitialized)?;
        let world = universe.world();
        let local = world.split_shared(world.rank());
        let ddp = Self {
            rank: world.rank() as usize,
            size: world.size() as usize,
            local_rank: local.rank() as usize,
            local_size: local.size() as usize,
            watchdog: Watchdog::start(timeout, threading == Threading::Multiple),
            world,
            _universe: universe,
        };
        tracing::info!(
            rank = ddp.rank,
            world_size = ddp.size,
            local_rank = ddp.local_rank,
            local_size = ddp.local_size,
            library = %mpi::environment::library_version().unwrap_or_default().lines().next().unwrap_or(""),
            "joined the MPI job"
        );
        Ok(ddp)
    }

    /// This rank (0-based) in the job.
    pub fn rank(&self) -> usize {
        self.rank
    }

    /// Ranks in the job.
    pub fn size(&self) -> usize {
        self.size
    }

    /// This rank among the ranks of its host (the shard stream it reads).
    pub fn local_rank(&self) -> usize {
        self.local_rank
    }

    /// Ranks on this host (the host pipeline's `--world-size`).
    pub fn local_size(&self) -> usize {
        self.local_size
    }

    /// Sums `values` elementwise over all ranks, in place (every rank passes the same
    /// length). `what` names the collective if it times out.
    pub fn all_reduce_sum(&self, values: &mut [f32], what: &str) {
        let _guard = self.watchdog.arm(what);
        let send = values.to_vec();
        self.world
            .all_reduce_into(&send[..], values, SystemOperation::sum());
    }

    /// Rank 0's `bytes` on every rank (the others pass anything; it is replaced).
    pub fn broadcast_bytes(&self, bytes: Vec<u8>, what: &str) -> Vec<u8> {
        let _guard = self.watchdog.arm(what);
        let root = self.world.process_at_rank(0);
        let mut len = bytes.len() as u64;
        root.broadcast_into(&mut len);
        let mut buffer = if self.rank == 0 {
            bytes
        } else {
            vec![0u8; len as usize]
        };
        // MPI counts are C ints: move large records in pieces.
        for piece in buffer.chunks_mut(1 << 30) {
            root.broadcast_into(piece);
        }
        buffer
    }

    /// Every rank's `values` (all ranks pass the same count), concatenated in rank order.
    pub fn all_gather(&self, values: &[u64], what: &str) -> Vec<u64> {
        let _guard = self.watchdog.arm(what);
        let mut all = vec![0u64; values.len() * self.size];
        self.world.all_gather_into(values, &mut all[..]);
        all
    }

    /// Waits until every rank got here.
    pub fn barrier(&self, what: &str) {
        let _guard = self.watchdog.arm(what);
        self.world.barrier();
    }
}

/// Aborts the job when a collective waits longer than the timeout (a hung peer).
#[derive(Debug, Clone)]
struct Watchdog {
    armed: Arc<Mutex<Option<(Instant, String)>>>,
}

/// Disarms the watchdog when the collective returns.
struct Armed<'a>(&'a Watchdog);

impl Drop for Armed<'_> {
    fn drop(&mut self) {
        if let Ok(mut armed) = self.0.armed.lock() {
            *armed = None;
        }
    }
}

impl Watchdog {
    fn start(timeout: Duration, can_abort_from_thread: bool) -> Self {
        let dog = Self {
            armed: Arc::new(Mutex::new(None)),
        };
        let watched = dog.armed.clone();
        let spawned = std::thread::Builder::new()
            .name("mpi-watchdog".into())
            .spawn(move || {
                loop {
                    std::thread::sleep(Duration::from_millis(250));
                    let expired = watched.lock().ok().and_then(|armed| {
                        armed
                            .as_ref()
                            .filter(|(since, _)| since.elapsed() > timeout)
                            .map(|(since, what)| (what.clone(), since.elapsed()))
                    });
                    if let Some((what, waited)) = expired {
                        let message = format!(
                            "{what}: no answer from the other ranks within {:.0} s (a peer hung or its data stream stalled); aborting the MPI job",
                            waited.as_secs_f64()
                        );
                        tracing::error!("{message}");
                        eprintln!("superflow-trainer: {message}");
                        if can_abort_from_thread {
                            SimpleCommunicator::world().abort(ABORT_CODE);
                        }
                        std::process::exit(ABORT_CODE);
                    }
                }
            });
        if let Err(e) = spawned {
            tracing::warn!(error = %e, "no collective watchdog: a hung peer will hang this rank");
        }
        dog
    }

    fn arm(&self, what: &str) -> Armed<'_> {
        if let Ok(mut armed) = self.armed.lock() {
            *armed = Some((Instant::now(), what.to_string()));
        }
        Armed(self)
    }
}
