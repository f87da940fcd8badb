//! Which plan a pipeline serves, in a few numbers every host of a job can compare: the
//! seed, the dataset's keyframes and a digest of everything that defines the samples
//! ([`PlanId::of`]). Hosts of one job each run a pipeline over their own copy of the
//! drives and deal themselves disjoint shares of the same seeded epochs; a host whose
//! drives, seed or recipe differ would serve shares that overlap the others' or leave
//! gaps, silently. The schedule service hands these numbers to every subscriber, and a
//! data-parallel trainer refuses to train when its ranks' pipelines disagree.

use crate::sample::SampleBuilder;
use xxhash_rust::xxh3::Xxh3;

/// Bumped when what the digest covers changes: digests of different versions never
/// compare equal by accident.
const DIGEST_TAG: &[u8] = b"superflow-plan-digest-1";

/// The plan a pipeline serves (the plan fields of `ScheduleReply`).
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub struct PlanId {
    /// The run's seed.
    pub seed: u64,
    /// Distinct keyframes of the whole dataset (every host's share, before the dataset
    /// groups' repeats).
    pub keyframes: u64,
    /// xxh3-64 over little-endian bytes of the seed, the sample recipe, the epoch order, the dataset
    /// groups (name, repeat, drive count) and per drive its camera count, keyframe count
    /// and the stamps of each keyframe's sweeps. File paths are left out: each host
    /// mounts its drives where it likes.
    pub digest: u64,
}

impl PlanId {
    /// The plan `builder` serves.
    pub fn of(builder: &SampleBuilder<'_>) -> Self {
        let config = builder.config();
        let dataset = builder.dataset();
        let plan = builder.plan();
        let mut h = Digest(Xxh3::new());
        h.bytes(DIGEST_TAG);
        h.u64(config.seed);
        // The recipe as its JSON: every setting that changes a sample, and no path. A
        // value that cannot be written (none can) still digests as the empty text, the
        // same on every host.
        h.bytes(serde_json::to_string(config).unwrap_or_default().as_bytes());
        // The epoch's order: it says which keyframe each position names.
        h.bytes(
            serde_json::to_string(&builder.mix().order)
                .unwrap_or_default()
                .as_bytes(),
        );
        h.u64(dataset.groups.len() as u64);
        for group in &dataset.groups {
            h.bytes(group.name.as_bytes());
            h.u64(group.repeat.to_bits());
            h.u64(group.drives.len() as u64);
        }
        h.u64(dataset.drives.len() as u64);
        // The plan lists keyframes in drive order: one pass, drive by drive.
        let mut keyframes = plan.keyframes.iter().peekable();
        for (index, drive) in dataset.drives.iter().enumerate() {
            h.u64(drive.cameras.len() as u64);
            let sweeps = drive.lidar.as_ref().map_or(&[][..], |l| &l.sweeps[..]);
            let stamp = |sweep: u32| {
                sweeps
                    .get(sweep as usize)
                    .map_or(i64::MIN, |s| s.stamp.nanos())
            };
            let mut count = 0u64;
            let mut stamps = Digest(Xxh3::new());
            while let Some(key) = keyframes.next_if(|k| k.drive as usize == index) {
                count += 1;
                stamps.i64(stamp(key.sweep));
                stamps.u64(key.frame_sweeps.len() as u64);
                for &sweep in &key.frame_sweeps {
                    stamps.i64(stamp(sweep));
                }
            }
            h.u64(count);
            h.u64(stamps.0.digest());
        }
        Self {
            seed: config.seed,
            keyframes: plan.keyframes.len() as u64,
            digest: h.0.digest(),
        }
    }
}

/// Little-endian, length-prefixed feeding of an xxh3 state: the same bytes on every
/// host, and no two sequences of fields give the same stream.
struct Digest(Xxh3);

impl Digest {
    fn u64(&mut self, value: u64) {
        self.0.update(&value.to_le_bytes());
    }

    fn i64(&mut self, value: i64) {
        self.0.update(&value.to_le_bytes());
    }

    fn bytes(&mut self, bytes: &[u8]) {
        self.u64(bytes.len() as u64);
        self.0.update(bytes);
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::drive::{Dataset, IngestConfig};
    use crate::sample::SampleConfig;
    use std::path::PathBuf;

    /// Copies of the sample drives in `<tmp>/<tag>/`: the same recordings at another
    /// path, as another host mounts them.
    fn copies(tag: &str) -> Vec<PathBuf> {
        let dir = scratch(tag);
        std::fs::create_dir_all(&dir).unwrap_or_else(|e| panic!("{e}"));
        ["street_foxglove", "street_ros2"]
            .iter()
            .map(|name| {
                let from = superflow_recordings::sample_drive_path(name);
                let to = dir.join(format!("{name}.mcap"));
                std::fs::copy(&from, &to).unwrap_or_else(|e| panic!("{}: {e}", from.display()));
                to
            })
            .collect()
    }

    fn scratch(tag: &str) -> PathBuf {
        std::env::temp_dir().join(format!("superflow-plan-id-{tag}-{}", std::process::id()))
    }

    fn open(paths: &[PathBuf]) -> Dataset {
        let config = IngestConfig {
            index_cache: Some(PathBuf::from("off")),
            ..IngestConfig::default()
        };
        Dataset::open(paths, &config).unwrap_or_else(|e| panic!("{e}"))
    }

    fn plan_id(dataset: &Dataset, seed: u64) -> PlanId {
        let config = SampleConfig {
            seed,
            ..SampleConfig::default()
        };
        PlanId::of(&SampleBuilder::new(dataset, config).unwrap_or_else(|e| panic!("{e}")))
    }

    #[test]
    fn the_digest_follows_the_plan_not_where_the_drives_are() {
        let (a, b) = (open(&copies("host0")), open(&copies("host1")));
        assert_ne!(a.drives[0].file_list(), b.drives[0].file_list());
        let (first, second) = (plan_id(&a, 3), plan_id(&b, 3));
        assert_eq!(first, second, "two hosts with copies of the same drives");
        assert!(first.keyframes > 0);
        assert_eq!(first.seed, 3);
        // Another seed: another plan.
        let reseeded = plan_id(&a, 4);
        assert_ne!(reseeded.digest, first.digest);
        assert_eq!(reseeded.keyframes, first.keyframes);
        // Another recipe setting that changes samples.
        let config = SampleConfig {
            seed: 3,
            cameras: 1,
            ..SampleConfig::default()
        };
        let builder = SampleBuilder::new(&a, config).unwrap_or_else(|e| panic!("{e}"));
        assert_ne!(PlanId::of(&builder).digest, first.digest);
        // Fewer drives: fewer keyframes, another digest.
        let one = open(&copies("host2")[..1]);
        let fewer = plan_id(&one, 3);
        assert!(fewer.keyframes < first.keyframes);
        assert_ne!(fewer.digest, first.digest);
        for tag in ["host0", "host1", "host2"] {
            let _ = std::fs::remove_dir_all(scratch(tag));
        }
    }
}
