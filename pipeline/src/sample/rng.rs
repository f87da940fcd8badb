//! The random draws of a sample. Every draw comes from a stream keyed by
//! `(seed, epoch, index, purpose)`, so a sample is the same whatever the thread count,
//! the order samples are built in, or a process restart. SplitMix64: tiny, stable
//! across versions (a dependency's generator could change its streams on upgrade).

/// What a stream is for; each purpose gets an independent stream.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum Purpose {
    /// The epoch's shuffle of keyframes.
    Shuffle,
    /// Which cameras a sample uses.
    Cameras,
    /// Horizontal flip of image `slot` of frame `frame`.
    ImageFlip {
        /// Frame position in the sample.
        frame: u32,
        /// Camera slot.
        slot: u32,
    },
    /// 3D augmentation of cloud `cloud` (frames first, then the dense cloud).
    Augment {
        /// Cloud position in the sample.
        cloud: u32,
    },
    /// Which keyframes of dataset group `group` get the fractional part of its repeat
    /// in an epoch (drawn with index 0).
    GroupShare {
        /// The group's position in the dataset.
        group: u32,
    },
    /// Where the first block of run `run` of an epoch's entries ends, under the
    /// `blocks` order (drawn with index 0).
    BlockPhase {
        /// The run's position among the epoch's runs.
        run: u32,
    },
}

impl Purpose {
    fn code(self) -> u64 {
        match self {
            Purpose::Shuffle => 1,
            Purpose::Cameras => 2,
            Purpose::ImageFlip { frame, slot } => {
                3 | (u64::from(frame) << 8) | (u64::from(slot) << 24)
            }
            Purpose::Augment { cloud } => 4 | (u64::from(cloud) << 8),
            Purpose::GroupShare { group } => 5 | (u64::from(group) << 8),
            Purpose::BlockPhase { run } => 6 | (u64::from(run) << 8),
        }
    }
}

fn mix(mut z: u64) -> u64 {
    z = (z ^ (z >> 30)).wrapping_mul(0xBF58_476D_1CE4_E5B9);
    z = (z ^ (z >> 27)).wrapping_mul(0x94D0_49BB_1331_11EB);
    z ^ (z >> 31)
}

/// A SplitMix64 stream.
#[derive(Debug, Clone)]
pub struct SampleRng(u64);

impl SampleRng {
    /// The stream of `purpose` for sample `index` of `epoch` under `seed`.
    pub fn new(seed: u64, epoch: u64, index: u64, purpose: Purpose) -> Self {
        let mut s = mix(seed ^ 0x5EED_5EED_5EED_5EED);
        for part in [epoch, index, purpose.code()] {
            s = mix(s ^ part.wrapping_mul(0x9E37_79B9_7F4A_7C15));
        }
        Self(s)
    }

    /// The next 64 bits.
    pub fn next_u64(&mut self) -> u64 {
        self.0 = self.0.wrapping_add(0x9E37_79B9_7F4A_7C15);
        mix(self.0)
    }

    /// Uniform in `[0, 1)` with 53 bits.
    pub fn unit(&mut self) -> f64 {
        (self.next_u64() >> 11) as f64 * (1.0 / (1u64 << 53) as f64)
    }

    /// Uniform in `[lo, hi]`.
    pub fn uniform(&mut self, lo: f64, hi: f64) -> f64 {
        lo + (hi - lo) * self.unit()
    }

    /// True with probability `p`.
    pub fn bernoulli(&mut self, p: f64) -> bool {
        self.unit() < p
    }

    /// Uniform in `0..n` (`n > 0`), without modulo bias.
    pub fn below(&mut self, n: u64) -> u64 {
        let zone = u64::MAX - u64::MAX % n;
        loop {
            let x = self.next_u64();
            if x < zone {
                return x % n;
            }
        }
    }

    /// Fisher–Yates shuffle.
    pub fn shuffle<T>(&mut self, items: &mut [T]) {
        for i in (1..items.len()).rev() {
            let j = self.below(i as u64 + 1) as usize;
            items.swap(i, j);
        }
    }

    /// `k` distinct indices of `0..n` in increasing order (`k <= n`).
    pub fn choose(&mut self, n: usize, k: usize) -> Vec<usize> {
        let mut all: Vec<usize> = (0..n).collect();
        self.shuffle(&mut all);
        all.truncate(k.min(n));
        all.sort_unstable();
        all
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn streams_are_keyed_and_repeatable() {
        let draw = |seed, epoch, index, p| {
            let mut r = SampleRng::new(seed, epoch, index, p);
            (0..4).map(|_| r.next_u64()).collect::<Vec<_>>()
        };
        let a = draw(1, 2, 3, Purpose::Cameras);
        assert_eq!(a, draw(1, 2, 3, Purpose::Cameras));
        assert_ne!(a, draw(1, 2, 4, Purpose::Cameras));
        assert_ne!(a, draw(1, 3, 3, Purpose::Cameras));
        assert_ne!(a, draw(2, 2, 3, Purpose::Cameras));
        assert_ne!(a, draw(1, 2, 3, Purpose::Augment { cloud: 0 }));
        assert_ne!(
            draw(1, 2, 3, Purpose::ImageFlip { frame: 0, slot: 1 }),
            draw(1, 2, 3, Purpose::ImageFlip { frame: 1, slot: 0 })
        );
    }

    #[test]
    fn draws_are_uniform_enough() {
        let mut r = SampleRng::new(7, 0, 0, Purpose::Shuffle);
        let n = 60_000;
        let mut counts = [0u32; 6];
        let mut sum = 0.0;
        for _ in 0..n {
            counts[r.below(6) as usize] += 1;
            sum += r.unit();
        }
        for c in counts {
            assert!((c as f64 - n as f64 / 6.0).abs() < 400.0, "{counts:?}");
        }
        assert!((sum / n as f64 - 0.5).abs() < 0.01);
        let picked = r.choose(6, 3);
        assert_eq!(picked.len(), 3);
        assert!(picked.windows(2).all(|w| w[0] < w[1]) && picked[2] < 6);
    }
}
