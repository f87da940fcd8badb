//! Per-point de-skew of raw sweeps: every point moved from the LiDAR frame at its own
//! firing instant into the LiDAR frame at the sweep's stamp,
//! `p_stamp = lidar_from_map(stamp) · map_from_lidar(stamp + t_i) · p_i`.
//!
//! A transform lookup costs ~0.45 µs (the chain of frames, a search and an interpolation
//! per edge), and the sweeps of Velodyne and Hesai drivers give every point its own
//! firing time (each laser fires at its own instant): one lookup per point would cost
//! ~15 ms a sweep of 33 k points. So the transform is looked up exactly at knots — the first and
//! the last firing, every stamp of a transform sample in between (where the interpolated
//! poses change course), and as many more as keep knots at most [`KNOT_SPACING_SECS`]
//! apart — and a point takes the linear blend of the 3×4 matrices of the knots either
//! side of its time. Between two knots every edge of the chain stays within one
//! interpolation segment (linear translation, slerp at a constant rate), so the point's
//! path is smooth there and the blend is off by at most `h²/8 · |p̈|` for knots `h`
//! apart: with `h` = 0.25 ms, turning at 1 rad/s and moving at 15 m/s, 1 µm at 100 m
//! (`ω² r + 2 ω v`), well below an `f32`'s spacing there (7.6 µm). Tested against one
//! exact lookup per point.
//!
//! Times spanning more than [`MAX_GRID_SPAN_SECS`], or not finite, are not a sweep's: they
//! take the exact lookup per distinct time.

use crate::drive::{TfError, TransformTree};
use nalgebra::{Isometry3, Point3};
use superflow_schemas::Stamp;
use superflow_schemas::sensor::PointCloud;

/// Largest gap between two knots, seconds.
pub const KNOT_SPACING_SECS: f64 = 0.25e-3;

/// Widest span of times the knots cover (a sweep spans 50–100 ms), seconds.
pub const MAX_GRID_SPAN_SECS: f64 = 1.0;

/// Moves every point of a raw sweep (per-point time, each point in the LiDAR frame at
/// its own firing instant) into the LiDAR frame at the sweep's stamp (see the module).
/// A cloud without per-point time is returned unchanged.
pub fn deskew(
    cloud: &PointCloud,
    tf: &TransformTree,
    map_frame: &str,
) -> Result<PointCloud, TfError> {
    let mut out = cloud.clone();
    deskew_in_place(&mut out, tf, map_frame)?;
    Ok(out)
}

/// [`deskew`] without the copy: the points of `cloud` are moved and its times zeroed.
pub fn deskew_in_place(
    cloud: &mut PointCloud,
    tf: &TransformTree,
    map_frame: &str,
) -> Result<(), TfError> {
    let Some(times) = cloud.time_offset_secs.as_mut() else {
        return Ok(());
    };
    let frame = cloud.frame_id.as_str();
    let stamp = cloud.stamp;
    let lidar_from_map = tf.lookup(map_frame, frame, stamp)?.inverse();
    let stamp_from_firing = |offset_secs: f64| -> Result<Isometry3<f64>, TfError> {
        Ok(lidar_from_map * tf.lookup(map_frame, frame, after(stamp, offset_secs))?)
    };
    match time_span(times) {
        Some((first, last)) => {
            let knots = knots(tf, map_frame, frame, stamp, first, last)?;
            Blend::new(&knots, stamp_from_firing)?.apply(&mut cloud.xyz, times);
        }
        None => exact(&mut cloud.xyz, times, stamp_from_firing)?,
    }
    times.fill(0.0);
    Ok(())
}

/// The instant `secs` after `stamp` (to the nanosecond; saturating, and a time that is
/// not a number counts as 0, so that an absurd time gets a lookup error, not an overflow).
fn after(stamp: Stamp, secs: f64) -> Stamp {
    Stamp::from_nanos(stamp.nanos().saturating_add((secs * 1e9).round() as i64))
}

/// The first and last time, when every time is finite and they span at most
/// [`MAX_GRID_SPAN_SECS`].
fn time_span(times: &[f32]) -> Option<(f64, f64)> {
    let (mut first, mut last) = (f32::INFINITY, f32::NEG_INFINITY);
    let mut finite = true;
    for &t in times {
        finite &= t.is_finite();
        first = first.min(t);
        last = last.max(t);
    }
    let (first, last) = (f64::from(first), f64::from(last));
    (finite && !times.is_empty() && last - first <= MAX_GRID_SPAN_SECS).then_some((first, last))
}

/// The knots for times `first..=last` after `stamp` (seconds): both ends, the samples of
/// the edges between `map_frame` and `frame` in between, and even subdivisions of every
/// gap wider than [`KNOT_SPACING_SECS`]; ascending, distinct.
fn knots(
    tf: &TransformTree,
    map_frame: &str,
    frame: &str,
    stamp: Stamp,
    first: f64,
    last: f64,
) -> Result<Vec<f64>, TfError> {
    let mut fixed = vec![first];
    fixed.extend(
        tf.sample_stamps(map_frame, frame, after(stamp, first), after(stamp, last))?
            .into_iter()
            .map(|s| s.secs_since(stamp))
            .filter(|&s| first < s && s < last),
    );
    fixed.push(last);
    fixed.sort_by(f64::total_cmp);
    fixed.dedup();
    let mut knots = vec![first];
    for pair in fixed.windows(2) {
        let (a, b) = (pair[0], pair[1]);
        let parts = ((b - a) / KNOT_SPACING_SECS).ceil().max(1.0) as usize;
        knots.extend((1..parts).map(|k| a + (b - a) * k as f64 / parts as f64));
        knots.push(b);
    }
    Ok(knots)
}

/// `stamp_from_firing` at the knots, as 3×4 matrices, and a uniform index into them.
struct Blend {
    first: f64,
    /// Per knot interval: its start, 1 / its length, the start's matrix and the change
    /// to the end's (row-major 3×4). One entry, with no change, when all times are equal.
    intervals: Vec<Interval>,
    /// Index of the interval holding `first + b · KNOT_SPACING_SECS`, for every `b`.
    bins: Vec<u32>,
}

struct Interval {
    start: f64,
    inv_len: f64,
    base: [f64; 12],
    delta: [f64; 12],
}

/// `iso` as a row-major 3×4 matrix.
fn matrix(iso: &Isometry3<f64>) -> [f64; 12] {
    let m = iso.to_homogeneous();
    std::array::from_fn(|i| m[(i / 4, i % 4)])
}

impl Blend {
    fn new(
        knots: &[f64],
        stamp_from_firing: impl Fn(f64) -> Result<Isometry3<f64>, TfError>,
    ) -> Result<Self, TfError> {
        let matrices = knots
            .iter()
            .map(|&t| stamp_from_firing(t).map(|iso| matrix(&iso)))
            .collect::<Result<Vec<_>, _>>()?;
        let mut intervals: Vec<Interval> = knots
            .windows(2)
            .zip(matrices.windows(2))
            .map(|(t, m)| Interval {
                start: t[0],
                inv_len: 1.0 / (t[1] - t[0]),
                base: m[0],
                delta: std::array::from_fn(|i| m[1][i] - m[0][i]),
            })
            .collect();
        if intervals.is_empty() {
            intervals.push(Interval {
                start: knots[0],
                inv_len: 0.0,
                base: matrices[0],
                delta: [0.0; 12],
            });
        }
        let first = knots[0];
        let span = knots[knots.len() - 1] - first;
        let bins = (span / KNOT_SPACING_SECS).ceil() as usize + 1;
        let mut at = 0usize;
        let bins = (0..bins)
            .map(|b| {
                let t = first + b as f64 * KNOT_SPACING_SECS;
                while at + 1 < intervals.len() && intervals[at + 1].start <= t {
                    at += 1;
                }
                at as u32
            })
            .collect();
        Ok(Self {
            first,
            intervals,
            bins,
        })
    }

    /// The interval holding time `t` (within the knots).
    fn interval_of(&self, t: f64) -> usize {
        let bin =
            (((t - self.first) * (1.0 / KNOT_SPACING_SECS)) as usize).min(self.bins.len() - 1);
        let mut i = self.bins[bin] as usize;
        while i + 1 < self.intervals.len() && self.intervals[i + 1].start <= t {
            i += 1;
        }
        i
    }

    /// Moves each point by the blend at its time (every time within the knots), a run of
    /// points in one interval at a time (consecutive points are mostly close in time).
    fn apply(&self, xyz: &mut [[f32; 3]], times: &[f32]) {
        let mut k = 0;
        while k < xyz.len() {
            let i = self.interval_of(f64::from(times[k]));
            let interval = &self.intervals[i];
            let end_time = self
                .intervals
                .get(i + 1)
                .map_or(f64::INFINITY, |next| next.start);
            let run = times[k..]
                .iter()
                .position(|&t| !(interval.start..end_time).contains(&f64::from(t)))
                .map_or(xyz.len(), |n| k + n.max(1));
            let (base, delta) = (&interval.base, &interval.delta);
            for (p, &t) in xyz[k..run].iter_mut().zip(&times[k..run]) {
                let w = (f64::from(t) - interval.start) * interval.inv_len;
                let [x, y, z] = p.map(f64::from);
                *p = std::array::from_fn(|r| {
                    let row = |m: &[f64; 12]| {
                        m[4 * r] * x + m[4 * r + 1] * y + m[4 * r + 2] * z + m[4 * r + 3]
                    };
                    (row(base) + w * row(delta)) as f32
                });
            }
            k = run;
        }
    }
}

/// One exact lookup per run of equal times.
fn exact(
    xyz: &mut [[f32; 3]],
    times: &[f32],
    stamp_from_firing: impl Fn(f64) -> Result<Isometry3<f64>, TfError>,
) -> Result<(), TfError> {
    let mut cached: Option<(f32, Isometry3<f64>)> = None;
    for (p, &t) in xyz.iter_mut().zip(times) {
        let iso = match cached {
            Some((ct, iso)) if ct == t => iso,
            _ => {
                let iso = stamp_from_firing(f64::from(t))?;
                cached = Some((t, iso));
                iso
            }
        };
        let q = iso * Point3::new(f64::from(p[0]), f64::from(p[1]), f64::from(p[2]));
        *p = [q.x as f32, q.y as f32, q.z as f32];
    }
    Ok(())
}

#[cfg(test)]
mod tests {
    use super::*;
    use nalgebra::{Translation3, UnitQuaternion, Vector3};
    use superflow_schemas::sensor::StampedTransform;

    const START: i64 = 1_700_000_000_000_000_000;

    fn edge(nanos: i64, parent: &str, child: &str, iso: Isometry3<f64>) -> StampedTransform {
        StampedTransform {
            stamp: Stamp::from_nanos(START + nanos),
            parent_frame: parent.into(),
            child_frame: child.into(),
            parent_from_child: iso,
            is_static: false,
        }
    }

    /// A vehicle on a hard turn: odometry at 50 Hz, yaw rate rising from 0.6 to 1.2 rad/s
    /// and speed from 12 to 18 m/s over the first second (2 s in all); `map → odom` drifting at 10 Hz; the
    /// LiDAR mounted 1.8 m up, tilted.
    fn turning_tree() -> TransformTree {
        let mut tree = TransformTree::new(0);
        let (mut x, mut y, mut yaw) = (0.0f64, 0.0f64, 0.0f64);
        let dt = 0.02;
        for k in 0..=100 {
            let t = k as f64 * dt;
            let pose = Isometry3::from_parts(
                Translation3::new(x, y, 0.02 * t.sin()),
                UnitQuaternion::from_euler_angles(0.01 * t, -0.02 * t, yaw),
            );
            tree.insert(edge(k * 20_000_000, "odom", "base_link", pose))
                .unwrap();
            let (rate, speed) = (0.6 + 0.6 * t.min(1.0), 12.0 + 6.0 * t.min(1.0));
            x += speed * yaw.cos() * dt;
            y += speed * yaw.sin() * dt;
            yaw += rate * dt;
        }
        for k in 0..=20 {
            let t = k as f64 * 0.1;
            let drift = Isometry3::new(
                Vector3::new(0.3 * t, -0.2 * t, 0.0),
                Vector3::z() * 0.01 * t,
            );
            tree.insert(edge(k * 100_000_000, "map", "odom", drift))
                .unwrap();
        }
        let mut mount = edge(
            0,
            "base_link",
            "lidar",
            Isometry3::from_parts(
                Translation3::new(0.9, 0.0, 1.8),
                UnitQuaternion::from_euler_angles(0.02, 0.01, -std::f64::consts::FRAC_PI_2),
            ),
        );
        mount.is_static = true;
        tree.insert(mount).unwrap();
        tree
    }

    /// `n` points out to 100 m with times in `0..span` seconds after `START + at`, in no
    /// particular order (as a ring-major organized cloud has them).
    fn cloud(n: usize, at: i64, span: f32) -> PointCloud {
        let mut rng = crate::test_rng::TestRng(0x9e37_79b9_7f4a_7c15);
        let mut uniform = move || rng.uniform();
        let xyz = (0..n)
            .map(|_| {
                let (range, azimuth, elevation) = (
                    1.0 + 99.0 * uniform(),
                    std::f64::consts::TAU * uniform(),
                    -0.4 + 0.5 * uniform(),
                );
                [
                    (range * elevation.cos() * azimuth.cos()) as f32,
                    (range * elevation.cos() * azimuth.sin()) as f32,
                    (range * elevation.sin()) as f32,
                ]
            })
            .collect();
        let times = (0..n).map(|_| span * uniform() as f32).collect();
        PointCloud {
            stamp: Stamp::from_nanos(START + at),
            frame_id: "lidar".into(),
            xyz,
            intensity: vec![0.0; n],
            ring: None,
            time_offset_secs: Some(times),
            label: None,
        }
    }

    /// Each point moved by its own exact lookup, in `f64`.
    fn exact_f64(cloud: &PointCloud, tree: &TransformTree) -> Vec<[f64; 3]> {
        let lidar_from_map = tree.lookup("map", "lidar", cloud.stamp).unwrap().inverse();
        let times = cloud.time_offset_secs.as_ref().unwrap();
        cloud
            .xyz
            .iter()
            .zip(times)
            .map(|(p, &t)| {
                let firing = after(cloud.stamp, f64::from(t));
                let iso = lidar_from_map * tree.lookup("map", "lidar", firing).unwrap();
                let q = iso * Point3::new(f64::from(p[0]), f64::from(p[1]), f64::from(p[2]));
                [q.x, q.y, q.z]
            })
            .collect()
    }

    /// The largest distance from the exact positions, less half the `f32` spacing at each
    /// coordinate (what storing the exact result as `f32` may lose anyway).
    fn worst_beyond_rounding(got: &[[f32; 3]], want: &[[f64; 3]]) -> f64 {
        got.iter()
            .zip(want)
            .map(|(g, w)| {
                let excess = |k: usize| {
                    let half_ulp = f64::from(f32::EPSILON) * w[k].abs().max(1e-30) / 2.0;
                    ((f64::from(g[k]) - w[k]).abs() - half_ulp).max(0.0)
                };
                (excess(0).powi(2) + excess(1).powi(2) + excess(2).powi(2)).sqrt()
            })
            .fold(0.0, f64::max)
    }

    #[test]
    fn blended_points_are_within_two_micrometres_of_exact_lookups() {
        let tree = turning_tree();
        // A 100 ms sweep over odometry samples and a map → odom sample (at 300 ms), times
        // distinct per point.
        let raw = cloud(40_000, 230_000_000, 0.1);
        let want = exact_f64(&raw, &tree);
        let fixed = deskew(&raw, &tree, "map").unwrap();
        assert!(
            fixed
                .time_offset_secs
                .as_ref()
                .unwrap()
                .iter()
                .all(|&t| t == 0.0)
        );
        let worst = worst_beyond_rounding(&fixed.xyz, &want);
        eprintln!("blend: {worst:e} m beyond f32 rounding");
        assert!(worst < 2e-6, "blend off by {worst} m beyond f32 rounding");
        // The motion is real: without de-skew the points are off by metres.
        let moved = raw.xyz.iter().zip(&want).map(|(p, w)| {
            let d = |k: usize| f64::from(p[k]) - w[k];
            (d(0).powi(2) + d(1).powi(2) + d(2).powi(2)).sqrt()
        });
        assert!(moved.fold(0.0, f64::max) > 1.0);
    }

    #[test]
    fn equal_times_and_wide_spans_are_exact() {
        let tree = turning_tree();
        // All points at one instant: one knot, one transform.
        let mut same = cloud(1_000, 400_000_000, 0.0);
        same.time_offset_secs = Some(vec![0.031; 1_000]);
        let worst = worst_beyond_rounding(
            &deskew(&same, &tree, "map").unwrap().xyz,
            &exact_f64(&same, &tree),
        );
        assert!(worst < 1e-9, "{worst}");
        // Times over more than a second are not a sweep's: one lookup per time.
        let wide = cloud(2_000, 0, 1.5);
        let worst = worst_beyond_rounding(
            &deskew(&wide, &tree, "map").unwrap().xyz,
            &exact_f64(&wide, &tree),
        );
        assert!(worst < 1e-9, "{worst}");
        // One point.
        let one = cloud(1, 500_000_000, 0.05);
        let worst = worst_beyond_rounding(
            &deskew(&one, &tree, "map").unwrap().xyz,
            &exact_f64(&one, &tree),
        );
        assert!(worst < 1e-9, "{worst}");
    }

    #[test]
    fn times_beyond_the_poses_are_lookup_errors() {
        let tree = turning_tree();
        let mut late = cloud(100, 1_900_000_000, 0.05);
        late.time_offset_secs.as_mut().unwrap()[7] = 0.3;
        assert!(matches!(
            deskew(&late, &tree, "map"),
            Err(TfError::Extrapolation { .. })
        ));
        // An infinite time saturates into a lookup error instead of overflowing the stamp.
        late.time_offset_secs.as_mut().unwrap()[7] = f32::INFINITY;
        assert!(matches!(
            deskew(&late, &tree, "map"),
            Err(TfError::Extrapolation { .. })
        ));
        // Without per-point time the cloud is unchanged.
        late.time_offset_secs = None;
        assert_eq!(deskew(&late, &tree, "map").unwrap().xyz, late.xyz);
    }
}
