//! [`Metrics`]: the counters of a running service, shared by the publisher, the
//! producer, the Prometheus endpoint ([`Metrics::prometheus`]) and the periodic log.

use std::sync::atomic::{AtomicU64, Ordering};

/// Counters of a running service, shared with the metrics endpoint and the log.
#[derive(Debug, Default)]
pub struct Metrics {
    /// Batches published, lost ones included.
    pub batches: AtomicU64,
    /// Batches published lost: every sample failed to build (`BATCH_LOST`, no sample).
    pub lost_batches: AtomicU64,
    /// Samples published.
    pub samples: AtomicU64,
    /// Bytes of payload published.
    pub bytes: AtomicU64,
    /// Time the publisher waited for a prepared batch (producer too slow), ns.
    pub wait_for_build_nanos: AtomicU64,
    /// Time spent in `send` (backpressure: subscribers full), ns.
    pub backpressure_nanos: AtomicU64,
    /// Time writing batches into shared memory, ns.
    pub write_nanos: AtomicU64,
    /// CPU time building samples, by stage, ns.
    pub stage_decode_nanos: AtomicU64,
    /// See [`crate::sample::StageTimes`].
    pub stage_sweeps_nanos: AtomicU64,
    /// See [`crate::sample::StageTimes`].
    pub stage_images_nanos: AtomicU64,
    /// See [`crate::sample::StageTimes`].
    pub stage_projection_nanos: AtomicU64,
    /// See [`crate::sample::StageTimes`].
    pub stage_superpixels_nanos: AtomicU64,
    /// See [`crate::sample::StageTimes`].
    pub stage_voxels_nanos: AtomicU64,
    /// Subscribers found dead and cleaned up.
    pub dead_subscribers: AtomicU64,
    /// Samples that could not be built (counted, logged, replaced by nothing: the batch
    /// is published short, or lost when none of its samples was built).
    pub failed_samples: AtomicU64,
    /// Resume requests accepted.
    pub resumes: AtomicU64,
    /// Messages skipped while indexing the drives.
    pub skipped_messages: AtomicU64,
    /// Shared frames (sweeps, images) found built, under the `blocks` order.
    pub frame_hits: AtomicU64,
    /// Shared frames built.
    pub frame_misses: AtomicU64,
    /// Bytes the shared frames hold now.
    pub frame_bytes: AtomicU64,
}

impl Metrics {
    /// Adds one sample's CPU time per stage.
    pub fn add_stages(&self, t: &crate::sample::StageTimes) {
        for (counter, nanos) in [
            (&self.stage_decode_nanos, t.decode),
            (&self.stage_sweeps_nanos, t.sweeps),
            (&self.stage_images_nanos, t.images),
            (&self.stage_projection_nanos, t.projection),
            (&self.stage_superpixels_nanos, t.superpixels),
            (&self.stage_voxels_nanos, t.voxels),
        ] {
            counter.fetch_add(nanos, Ordering::Relaxed);
        }
    }

    /// The counters in Prometheus text format.
    pub fn prometheus(&self) -> String {
        let counters: [(&str, &str, &AtomicU64); 16] = [
            (
                "superflow_batches_total",
                "Batches published, lost ones included",
                &self.batches,
            ),
            (
                "superflow_lost_batches_total",
                "Batches published lost: every sample failed to build",
                &self.lost_batches,
            ),
            (
                "superflow_samples_total",
                "Samples published",
                &self.samples,
            ),
            (
                "superflow_payload_bytes_total",
                "Payload bytes published",
                &self.bytes,
            ),
            (
                "superflow_wait_for_build_seconds_total",
                "Publisher waiting for the producer",
                &self.wait_for_build_nanos,
            ),
            (
                "superflow_backpressure_seconds_total",
                "Publisher waiting for full subscribers",
                &self.backpressure_nanos,
            ),
            (
                "superflow_write_seconds_total",
                "Writing batches into shared memory",
                &self.write_nanos,
            ),
            (
                "superflow_stage_decode_seconds_total",
                "CPU time decoding sweeps and images",
                &self.stage_decode_nanos,
            ),
            (
                "superflow_stage_sweeps_seconds_total",
                "CPU time de-skewing and aligning sweeps",
                &self.stage_sweeps_nanos,
            ),
            (
                "superflow_stage_images_seconds_total",
                "CPU time resizing images",
                &self.stage_images_nanos,
            ),
            (
                "superflow_stage_projection_seconds_total",
                "CPU time projecting points",
                &self.stage_projection_nanos,
            ),
            (
                "superflow_stage_superpixels_seconds_total",
                "CPU time on superpixels",
                &self.stage_superpixels_nanos,
            ),
            (
                "superflow_stage_voxels_seconds_total",
                "CPU time on voxels and maps",
                &self.stage_voxels_nanos,
            ),
            (
                "superflow_dead_subscribers_total",
                "Dead subscribers cleaned up",
                &self.dead_subscribers,
            ),
            (
                "superflow_failed_samples_total",
                "Samples that could not be built",
                &self.failed_samples,
            ),
            (
                "superflow_resumes_total",
                "Resume requests accepted",
                &self.resumes,
            ),
        ];
        let mut out = String::new();
        for (name, help, value) in counters {
            let v = value.load(Ordering::Relaxed);
            let (kind, shown) = if name.ends_with("_seconds_total") {
                ("counter", format!("{}", v as f64 / 1e9))
            } else {
                ("counter", v.to_string())
            };
            out.push_str(&format!(
                "# HELP {name} {help}\n# TYPE {name} {kind}\n{name} {shown}\n"
            ));
        }
        let (hits, misses, held) = (
            self.frame_hits.load(Ordering::Relaxed),
            self.frame_misses.load(Ordering::Relaxed),
            self.frame_bytes.load(Ordering::Relaxed),
        );
        out.push_str(&format!(
            "# HELP superflow_frame_hits_total Shared frames found built (order = blocks)\n# TYPE superflow_frame_hits_total counter\nsuperflow_frame_hits_total {hits}\n\
             # HELP superflow_frame_misses_total Shared frames built (order = blocks)\n# TYPE superflow_frame_misses_total counter\nsuperflow_frame_misses_total {misses}\n\
             # HELP superflow_frame_bytes Bytes held by shared frames\n# TYPE superflow_frame_bytes gauge\nsuperflow_frame_bytes {held}\n"
        ));
        let skipped = self.skipped_messages.load(Ordering::Relaxed);
        out.push_str(&format!(
            "# HELP superflow_skipped_messages Messages skipped while indexing\n# TYPE superflow_skipped_messages gauge\nsuperflow_skipped_messages {skipped}\n"
        ));
        // Object-store requests, bytes, retries by cause, latency and prefetch (empty
        // for a run over local drives only).
        out.push_str(&crate::source::remote::stats::prometheus());
        out
    }
}

/// Logs the main counters (every 10 s while serving, and once at the end).
pub(super) fn log_counters(metrics: &Metrics) {
    tracing::info!(
        batches = metrics.batches.load(Ordering::Relaxed),
        lost_batches = metrics.lost_batches.load(Ordering::Relaxed),
        samples = metrics.samples.load(Ordering::Relaxed),
        backpressure_secs = metrics.backpressure_nanos.load(Ordering::Relaxed) as f64 / 1e9,
        wait_for_build_secs = metrics.wait_for_build_nanos.load(Ordering::Relaxed) as f64 / 1e9,
        dead_subscribers = metrics.dead_subscribers.load(Ordering::Relaxed),
        failed_samples = metrics.failed_samples.load(Ordering::Relaxed),
        "counters"
    );
}
