//! What neighbouring samples share, built once: under the `blocks` order
//! ([`super::EpochOrder::Blocks`]) a keyframe's triplet shares two of its three frames
//! with the next keyframe of its block, built `open` positions later. The
//! [`FrameCache`] keeps each frame's de-skewed sweep and each camera's image resized to
//! the recipe's size, not flipped, with its class ids or sidecar superpixels alike, so
//! the samples that use a frame decompress, decode and resize it once; each sample
//! flips its own copy (the bytes of a cold build's one-pass resize-and-flip).
//!
//! An entry lives while a sample still to be built will ask for it: the builder works out
//! from the epoch's order the last position that uses each frame ([`LastUses`]), and the
//! entry goes when that sample takes it. What the samples of open blocks share with
//! their next keyframes is all that stays: for each open block, about two frames' sweeps
//! and the images of those frames that its samples have drawn so far (3 of 6 cameras a
//! sample, so 3 to 6 a frame). Entries whose last user failed, or lives on another
//! host, go once no sample within `keep` positions of the newest one has asked for them
//! (positions count across epochs).
//!
//! What comes out of the cache is what reading it afresh gives, byte for byte: nothing
//! in an entry depends on the sample that read it (the flip, a draw of the sample, comes
//! after).

use super::images::CameraRead;
use super::types::StageTimes;
use std::collections::HashMap;
use std::sync::atomic::{AtomicU64, Ordering};
use std::sync::{Arc, Mutex, OnceLock, PoisonError};
use superflow_schemas::sensor::PointCloud;

/// A sweep, decoded and de-skewed (in its LiDAR frame at its stamp).
#[derive(Debug, Clone)]
pub(super) struct SweepEntry {
    /// The points.
    pub cloud: Arc<PointCloud>,
    /// Non-finite points dropped when decoding.
    pub dropped: u64,
}

/// What an entry is.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Hash)]
pub(super) enum FrameKey {
    /// Sweep `sweep` of drive `drive`.
    Sweep { drive: u32, sweep: u32 },
    /// Camera `camera`'s image for sweep `sweep` of drive `drive`.
    Image { drive: u32, sweep: u32, camera: u32 },
}

/// The last run position of an epoch that asks for each frame.
pub(super) type LastUses = HashMap<FrameKey, u64>;

#[derive(Debug, Clone)]
enum Value {
    Sweep(Arc<SweepEntry>),
    Image(Arc<CameraRead>),
}

impl Value {
    fn bytes(&self) -> u64 {
        match self {
            Value::Sweep(s) => {
                let c = &s.cloud;
                let n = c.len() as u64;
                n * 16
                    + c.ring.as_ref().map_or(0, |_| n * 2)
                    + c.time_offset_secs.as_ref().map_or(0, |_| n * 4)
                    + c.label.as_ref().map_or(0, |_| n * 4)
            }
            Value::Image(i) => i.bytes(),
        }
    }
}

struct Slot {
    value: Value,
    /// The newest position that asked for it.
    used: u64,
}

#[derive(Default)]
struct Entries {
    map: HashMap<FrameKey, Slot>,
    /// The last uses of the epochs being built.
    last_uses: Vec<(u64, Arc<OnceLock<LastUses>>)>,
    /// The newest position seen.
    newest: u64,
    /// The position up to which entries were last swept for age.
    swept: u64,
    bytes: u64,
}

/// Counters of a [`FrameCache`] (hits, misses, what it holds).
#[derive(Debug, Default)]
pub struct FrameCacheStats {
    /// Lookups that found their entry.
    pub hits: AtomicU64,
    /// Lookups that built it.
    pub misses: AtomicU64,
    /// Bytes held now.
    pub bytes: AtomicU64,
    /// The most bytes held at once.
    pub peak_bytes: AtomicU64,
}

/// Frames shared by the samples of open blocks (see the module documentation).
pub struct FrameCache {
    entries: Mutex<Entries>,
    keep: u64,
    stats: FrameCacheStats,
}

impl std::fmt::Debug for FrameCache {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.debug_struct("FrameCache")
            .field("keep", &self.keep)
            .field("stats", &self.stats)
            .finish_non_exhaustive()
    }
}

impl FrameCache {
    /// A cache that keeps an entry while a sample within `keep` positions of the newest
    /// one asked for it.
    pub fn new(keep: u64) -> Self {
        Self {
            entries: Mutex::new(Entries::default()),
            keep: keep.max(1),
            stats: FrameCacheStats::default(),
        }
    }

    /// How many positions an entry outlives its last use.
    pub fn keep(&self) -> u64 {
        self.keep
    }

    /// Its counters.
    pub fn stats(&self) -> &FrameCacheStats {
        &self.stats
    }

    /// The last uses of `epoch`'s frames, worked out by `compute` once (the samples that
    /// ask meanwhile wait for it; epochs before `epoch − 1` are forgotten).
    pub(super) fn last_uses(
        &self,
        epoch: u64,
        compute: impl FnOnce() -> LastUses,
    ) -> Arc<OnceLock<LastUses>> {
        let cell = {
            let mut entries = self.lock();
            match entries.last_uses.iter().find(|(e, _)| *e == epoch) {
                Some((_, cell)) => cell.clone(),
                None => {
                    entries.last_uses.retain(|(e, _)| *e + 1 >= epoch);
                    let cell = Arc::new(OnceLock::new());
                    entries.last_uses.push((epoch, cell.clone()));
                    cell
                }
            }
        };
        cell.get_or_init(compute);
        cell
    }

    /// Sweep `sweep` of drive `drive` for the sample at run position `position`, built
    /// by `build` unless held; `last`: no later sample asks for it.
    pub(super) fn sweep<E>(
        &self,
        (drive, sweep): (u32, u32),
        (position, last): (u64, bool),
        build: impl FnOnce() -> Result<(SweepEntry, StageTimes), E>,
    ) -> Result<(Arc<SweepEntry>, StageTimes), E> {
        let key = FrameKey::Sweep { drive, sweep };
        let got = self.get_or(key, (position, last), || {
            build().map(|(s, t)| (Value::Sweep(Arc::new(s)), t))
        })?;
        match got {
            (Value::Sweep(s), t) => Ok((s, t)),
            (Value::Image(_), _) => unreachable!("a sweep key holds a sweep"),
        }
    }

    /// The image of camera `camera` for sweep `sweep` of drive `drive` as read, for the
    /// sample at run position `position`, read by `build` unless held; `last`: no later
    /// sample asks for it.
    pub(super) fn image<E>(
        &self,
        (drive, sweep, camera): (u32, u32, u32),
        (position, last): (u64, bool),
        build: impl FnOnce() -> Result<(CameraRead, StageTimes), E>,
    ) -> Result<(Arc<CameraRead>, StageTimes), E> {
        let key = FrameKey::Image {
            drive,
            sweep,
            camera,
        };
        let got = self.get_or(key, (position, last), || {
            build().map(|(i, t)| (Value::Image(Arc::new(i)), t))
        })?;
        match got {
            (Value::Image(i), t) => Ok((i, t)),
            (Value::Sweep(_), _) => unreachable!("an image key holds an image"),
        }
    }

    /// The entry of `key`, built outside the lock on a miss (two samples that miss the
    /// same entry at once both build it; the bytes are the same). The last use takes the
    /// entry out, or does not put it in.
    fn get_or<E>(
        &self,
        key: FrameKey,
        (position, last): (u64, bool),
        build: impl FnOnce() -> Result<(Value, StageTimes), E>,
    ) -> Result<(Value, StageTimes), E> {
        {
            let mut entries = self.lock();
            entries.newest = entries.newest.max(position);
            let found = if last {
                entries.map.remove(&key).map(|slot| {
                    entries.bytes -= slot.value.bytes();
                    slot.value
                })
            } else {
                entries.map.get_mut(&key).map(|slot| {
                    slot.used = slot.used.max(position);
                    slot.value.clone()
                })
            };
            if let Some(value) = found {
                self.stats.hits.fetch_add(1, Ordering::Relaxed);
                self.stats.bytes.store(entries.bytes, Ordering::Relaxed);
                return Ok((value, StageTimes::default()));
            }
        }
        self.stats.misses.fetch_add(1, Ordering::Relaxed);
        let (value, times) = build()?;
        let mut entries = self.lock();
        if !last {
            let bytes = value.bytes();
            let slot = Slot {
                value: value.clone(),
                used: position,
            };
            if let Some(previous) = entries.map.insert(key, slot) {
                entries.bytes -= previous.value.bytes();
            }
            entries.bytes += bytes;
        }
        self.drop_unused(&mut entries);
        self.stats.bytes.store(entries.bytes, Ordering::Relaxed);
        self.stats
            .peak_bytes
            .fetch_max(entries.bytes, Ordering::Relaxed);
        Ok((value, times))
    }

    /// Drops the entries no sample within `keep` positions of the newest asked for
    /// (looked for once every `keep / 4` positions: entries may outlive their use by
    /// that much).
    fn drop_unused(&self, entries: &mut Entries) {
        let step = (self.keep / 4).max(1);
        if entries.newest < entries.swept + step {
            return;
        }
        entries.swept = entries.newest;
        let Some(oldest) = entries.newest.checked_sub(self.keep) else {
            return;
        };
        let mut freed = 0;
        entries.map.retain(|_, slot| {
            let keep = slot.used >= oldest;
            if !keep {
                freed += slot.value.bytes();
            }
            keep
        });
        entries.bytes -= freed;
    }

    fn lock(&self) -> std::sync::MutexGuard<'_, Entries> {
        self.entries.lock().unwrap_or_else(PoisonError::into_inner)
    }
}

/// `data` (rows of `width` pixels of `C` values) as it is, or mirrored left to right, in
/// a new buffer.
pub(super) fn copy_mirrored<T: Copy + Default, const C: usize>(
    data: &[T],
    width: usize,
    mirrored: bool,
) -> Vec<T> {
    let stride = width * C;
    if !mirrored || stride == 0 {
        return data.to_vec();
    }
    let mut out = vec![T::default(); data.len()];
    for (to, from) in out.chunks_exact_mut(stride).zip(data.chunks_exact(stride)) {
        for (dst, src) in to.chunks_exact_mut(C).zip(from.chunks_exact(C).rev()) {
            dst.copy_from_slice(src);
        }
    }
    out
}

/// Class ids (rows of `width`) widened to `u32`, mirrored left to right when `mirrored`.
pub(super) fn widen_mirrored(ids: &[u8], width: usize, mirrored: bool) -> Vec<u32> {
    if !mirrored || width == 0 {
        return ids.iter().map(|&v| u32::from(v)).collect();
    }
    let mut out = Vec::with_capacity(ids.len());
    for row in ids.chunks_exact(width) {
        out.extend(row.iter().rev().map(|&v| u32::from(v)));
    }
    out
}

#[cfg(test)]
mod tests {
    use super::*;

    fn sweep(points: usize) -> SweepEntry {
        SweepEntry {
            cloud: Arc::new(PointCloud {
                xyz: vec![[0.0; 3]; points],
                intensity: vec![0.0; points],
                ..PointCloud::default()
            }),
            dropped: 0,
        }
    }

    #[test]
    fn an_entry_is_built_once_while_in_use_and_dropped_after() {
        let cache = FrameCache::new(8);
        let built = std::cell::Cell::new(0);
        let get = |sweep: u32, position: u64| {
            cache
                .sweep::<()>((0, sweep), (position, false), || {
                    built.set(built.get() + 1);
                    Ok((self::sweep(10), StageTimes::default()))
                })
                .unwrap()
        };
        get(1, 0);
        get(1, 5);
        get(1, 12);
        assert_eq!(built.get(), 1, "used within 8 positions each time");
        get(2, 30);
        get(2, 31);
        assert_eq!(built.get(), 2);
        // Sweep 1 was last used at 12: gone by 30 + 8.
        get(3, 40);
        get(1, 41);
        assert_eq!(built.get(), 4, "sweep 1 was dropped and built again");
        assert_eq!(cache.stats().hits.load(Ordering::Relaxed), 3);
        assert_eq!(cache.stats().misses.load(Ordering::Relaxed), 4);
        assert!(cache.stats().bytes.load(Ordering::Relaxed) <= 3 * 160);
    }

    #[test]
    fn a_failed_build_is_not_kept() {
        let cache = FrameCache::new(8);
        let e = cache.sweep((0, 0), (0, false), || {
            Err::<(SweepEntry, StageTimes), _>("bad")
        });
        assert_eq!(e.unwrap_err(), "bad");
        let ok = cache.sweep::<&str>((0, 0), (1, false), || Ok((sweep(3), StageTimes::default())));
        assert_eq!(ok.unwrap().0.cloud.len(), 3);
    }

    #[test]
    fn the_last_use_takes_the_entry_out() {
        let cache = FrameCache::new(100);
        let built = std::cell::Cell::new(0);
        let get = |position: u64, last: bool| {
            cache
                .sweep::<()>((3, 7), (position, last), || {
                    built.set(built.get() + 1);
                    Ok((sweep(10), StageTimes::default()))
                })
                .unwrap()
        };
        get(0, false);
        assert!(cache.stats().bytes.load(Ordering::Relaxed) > 0);
        get(1, true);
        assert_eq!(built.get(), 1);
        assert_eq!(cache.stats().bytes.load(Ordering::Relaxed), 0, "taken out");
        // A frame used once is built and not kept.
        get(2, true);
        assert_eq!(built.get(), 2);
        assert_eq!(cache.stats().bytes.load(Ordering::Relaxed), 0);
    }

    #[test]
    fn mirrored_copies_reverse_each_rows_pixels() {
        let rgb: Vec<u8> = (0..12).collect();
        assert_eq!(copy_mirrored::<u8, 3>(&rgb, 2, false), rgb);
        assert_eq!(
            copy_mirrored::<u8, 3>(&rgb, 2, true),
            [3, 4, 5, 0, 1, 2, 9, 10, 11, 6, 7, 8]
        );
        let mut flipped = rgb.clone();
        super::super::image_ops::flip_horizontal(&mut flipped, 2, 3);
        assert_eq!(copy_mirrored::<u8, 3>(&rgb, 2, true), flipped);
        let ids: Vec<u8> = (0..6).collect();
        assert_eq!(widen_mirrored(&ids, 3, false), [0, 1, 2, 3, 4, 5]);
        assert_eq!(widen_mirrored(&ids, 3, true), [2, 1, 0, 5, 4, 3]);
    }
}
