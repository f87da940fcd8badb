//! `[service]` of `pipeline.toml`: the stream's mode, ranks and hosts, batch size,
//! prefetch, epochs, the epoch's order, subscriber waits and linger, with their ranges.

use crate::sample::EpochOrder;
use serde::{Deserialize, Serialize};
use superflow_common::InvalidSetting;
use superflow_schemas::service::qos;

/// Broadcast (every subscriber sees every batch) or shard (each rank its share):
/// `[service] mode` and `--mode`.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Default, Serialize, Deserialize, clap::ValueEnum)]
#[serde(rename_all = "snake_case")]
pub enum Mode {
    /// One stream on `superflow/<run>/batches`.
    #[default]
    Broadcast,
    /// `world_size` streams on `superflow/<run>/rank/<r>`.
    Shard,
}

/// How an epoch's samples are ordered: `[service] order` and `--order`.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Default, Serialize, Deserialize, clap::ValueEnum)]
#[serde(rename_all = "snake_case")]
pub enum Order {
    /// Every sample of the epoch shuffled.
    #[default]
    Global,
    /// Blocks of `block_length` consecutive keyframes of one drive, shuffled, served
    /// `open_blocks` side by side: a frame shared by neighbouring keyframes is built
    /// once.
    Blocks,
}

/// `[service]` of `pipeline.toml`.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(default, deny_unknown_fields)]
pub struct ServiceConfig {
    /// Broadcast or shard.
    pub mode: Mode,
    /// Ranks in shard mode (on this host).
    pub world_size: u32,
    /// This host's rank among `host_count` hosts (multi-host sharding).
    pub host_rank: u32,
    /// Hosts sharing each epoch; each runs its own pipeline with the same drives and
    /// configuration, and gets a disjoint share of every epoch's keyframes.
    pub host_count: u32,
    /// Samples per batch (4, the paper's per-GPU batch).
    pub batch_size: u32,
    /// Batches built ahead of the one being published.
    pub prefetch: u32,
    /// Epochs to stream; 0 streams forever.
    pub epochs: u64,
    /// How each epoch's samples are ordered.
    pub order: Order,
    /// Under `order = "blocks"`: keyframes a block, at most.
    pub block_length: u32,
    /// Under `order = "blocks"`: blocks served side by side (the same on every host of
    /// a job, and across an elastic resume: it is part of the order).
    pub open_blocks: u32,
    /// How often a publisher waiting on a full subscriber checks whether it died, ms.
    pub dead_node_check_ms: u64,
    /// Subscribers each stream waits for before its first batch (a batch published to
    /// nobody would be lost); afterwards it waits whenever none is attached.
    pub min_subscribers: u32,
    /// After the last epoch: keep serving (resume requests) until every subscriber has
    /// left, at most this long, seconds.
    pub linger_secs: u64,
}

impl Default for ServiceConfig {
    fn default() -> Self {
        Self {
            mode: Mode::Broadcast,
            world_size: 1,
            host_rank: 0,
            host_count: 1,
            batch_size: 4,
            prefetch: 2,
            epochs: 0,
            order: Order::Global,
            block_length: 8,
            open_blocks: 16,
            dead_node_check_ms: 500,
            min_subscribers: 1,
            linger_secs: 600,
        }
    }
}

impl ServiceConfig {
    /// Checks ranges.
    pub fn validate(&self) -> Result<(), InvalidSetting> {
        let within = |setting: &str, value: u32, range: std::ops::RangeInclusive<u32>| {
            if range.contains(&value) {
                Ok(())
            } else {
                let rule = format!("must be {}..={}", range.start(), range.end());
                Err(InvalidSetting::new(setting, value, rule))
            }
        };
        within("service.world_size", self.world_size, 1..=1024)?;
        within("service.host_count", self.host_count, 1..=4096)?;
        if self.host_rank >= self.host_count {
            return Err(InvalidSetting::new(
                "service.host_rank",
                self.host_rank,
                format!("must be below service.host_count = {}", self.host_count),
            ));
        }
        if self.mode == Mode::Broadcast && self.world_size != 1 {
            return Err(InvalidSetting::new(
                "service.world_size",
                self.world_size,
                "> 1 needs mode = \"shard\"",
            ));
        }
        within("service.batch_size", self.batch_size, 1..=256)?;
        within("service.prefetch", self.prefetch, 1..=64)?;
        if self.min_subscribers as usize > qos::MAX_SUBSCRIBERS {
            return Err(InvalidSetting::new(
                "service.min_subscribers",
                self.min_subscribers,
                format!(
                    "exceeds the {} subscribers a service admits",
                    qos::MAX_SUBSCRIBERS
                ),
            ));
        }
        within("service.block_length", self.block_length, 1..=4096)?;
        within("service.open_blocks", self.open_blocks, 1..=4096)?;
        if self.order == Order::Blocks {
            // Rank r's batch is positions r, r + R, r + 2R, ... of a global step: they
            // fall in distinct open blocks when open / gcd(open, R) ≥ batch.
            let ranks = self.streams() * self.host_count;
            let open = self.open_blocks;
            let apart = open / gcd(open, ranks);
            if apart < self.batch_size {
                let least = ranks * self.batch_size;
                return Err(InvalidSetting::new(
                    "service.open_blocks",
                    open,
                    format!(
                        "gives a batch of {} on each of {ranks} ranks only {apart} blocks to \
                         draw from; use {least} (or another multiple of {ranks} of at least \
                         {least})",
                        self.batch_size
                    ),
                ));
            }
        }
        if self.dead_node_check_ms == 0 {
            return Err(InvalidSetting::new(
                "service.dead_node_check_ms",
                self.dead_node_check_ms,
                "must be > 0",
            ));
        }
        Ok(())
    }

    /// The order of the epochs' samples.
    pub fn epoch_order(&self) -> EpochOrder {
        match self.order {
            Order::Global => EpochOrder::Global,
            Order::Blocks => EpochOrder::Blocks {
                length: self.block_length,
                open: self.open_blocks,
            },
        }
    }

    /// How far apart in the run's order the samples built at once usually are: the
    /// streams of a host are built in turn, a batch each, so two global batches cover
    /// them (streams that drift further apart lose some reuse of shared frames, never
    /// bytes).
    pub fn positions_in_flight(&self) -> u64 {
        2 * u64::from(self.batch_size) * u64::from(self.streams() * self.host_count)
    }

    /// Streams of this host: 1 in broadcast mode, `world_size` in shard mode.
    pub(super) fn streams(&self) -> u32 {
        match self.mode {
            Mode::Broadcast => 1,
            Mode::Shard => self.world_size,
        }
    }
}

/// Greatest common divisor (1 for `gcd(0, 0)`).
fn gcd(mut a: u32, mut b: u32) -> u32 {
    while b != 0 {
        (a, b) = (b, a % b);
    }
    a.max(1)
}
