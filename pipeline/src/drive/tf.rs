//! The transform tree with time: static and stamped edges, lookups of `a_from_b` at any
//! instant by interpolation (linear translation, slerp rotation), extrapolation only
//! within a tolerance.

use nalgebra::{Isometry3, Translation3, UnitQuaternion};
use std::collections::HashMap;
use superflow_schemas::Stamp;
use superflow_schemas::sensor::StampedTransform;

/// Why a transform cannot be looked up or inserted.
#[derive(Debug, Clone, PartialEq, thiserror::Error)]
pub enum TfError {
    /// No transform mentions the frame.
    #[error("frame `{frame}` is not in the transform tree (known: {known})")]
    UnknownFrame {
        /// The frame asked for.
        frame: String,
        /// Frames that exist, comma-separated.
        known: String,
    },
    /// Both frames exist but are in different trees.
    #[error("frames `{target}` and `{source_frame}` are not connected by any chain of transforms")]
    NotConnected {
        /// Target frame.
        target: String,
        /// Source frame.
        source_frame: String,
    },
    /// The instant lies outside the stamped samples of an edge by more than the tolerance.
    #[error(
        "transform {parent} -> {child} at {stamp}: would extrapolate {gap_ms:.1} ms beyond the samples ({first} .. {last}), tolerance {tolerance_ms:.1} ms"
    )]
    Extrapolation {
        /// Parent frame of the edge.
        parent: String,
        /// Child frame of the edge.
        child: String,
        /// The instant asked for.
        stamp: Stamp,
        /// First sample.
        first: Stamp,
        /// Last sample.
        last: Stamp,
        /// Distance to the nearest sample.
        gap_ms: f64,
        /// The configured tolerance.
        tolerance_ms: f64,
    },
    /// A frame given two different parents.
    #[error("frame `{child}` has parent `{existing}` but a transform gives it parent `{new}`")]
    Reparented {
        /// The child frame.
        child: String,
        /// Its parent so far.
        existing: String,
        /// The conflicting parent.
        new: String,
    },
    /// The parent chain loops.
    #[error("the transform tree has a cycle through `{frame}`")]
    Cycle {
        /// A frame on the cycle.
        frame: String,
    },
}

#[derive(Debug, Clone, PartialEq)]
struct Edge {
    parent: String,
    fixed: Option<Isometry3<f64>>,
    samples: Vec<(Stamp, Isometry3<f64>)>,
}

/// Every transform of a drive, by child frame.
#[derive(Debug, Clone, PartialEq)]
pub struct TransformTree {
    edges: HashMap<String, Edge>,
    tolerance_nanos: i64,
}

const MAX_DEPTH: usize = 64;

fn interpolate(a: &Isometry3<f64>, b: &Isometry3<f64>, alpha: f64) -> Isometry3<f64> {
    let translation = a.translation.vector.lerp(&b.translation.vector, alpha);
    let mut qb = b.rotation;
    if a.rotation.coords.dot(&qb.coords) < 0.0 {
        qb = UnitQuaternion::new_unchecked(-qb.into_inner());
    }
    let rotation = a
        .rotation
        .try_slerp(&qb, alpha, 1e-12)
        .unwrap_or(a.rotation);
    Isometry3::from_parts(Translation3::from(translation), rotation)
}

impl TransformTree {
    /// An empty tree that extrapolates at most `tolerance_nanos` past an edge's samples.
    pub fn new(tolerance_nanos: i64) -> Self {
        Self {
            edges: HashMap::new(),
            tolerance_nanos,
        }
    }

    /// Adds a transform. Static transforms replace the edge's fixed value; stamped ones
    /// are kept in time order (insertion order does not matter).
    pub fn insert(&mut self, transform: StampedTransform) -> Result<(), TfError> {
        let edge = self
            .edges
            .entry(transform.child_frame.clone())
            .or_insert_with(|| Edge {
                parent: transform.parent_frame.clone(),
                fixed: None,
                samples: Vec::new(),
            });
        if edge.parent != transform.parent_frame {
            return Err(TfError::Reparented {
                child: transform.child_frame,
                existing: edge.parent.clone(),
                new: transform.parent_frame,
            });
        }
        if transform.is_static {
            edge.fixed = Some(transform.parent_from_child);
        } else {
            let at = edge.samples.partition_point(|(s, _)| *s <= transform.stamp);
            if at > 0 && edge.samples[at - 1].0 == transform.stamp {
                edge.samples[at - 1].1 = transform.parent_from_child;
            } else {
                edge.samples
                    .insert(at, (transform.stamp, transform.parent_from_child));
            }
        }
        Ok(())
    }

    /// Turns stamped edges whose every sample is the same transform (within 1 µm and
    /// 1 µrad) into static ones. The nuScenes converter re-publishes each sensor's
    /// extrinsics on `/tf` at every keyframe instead of once on `/tf_static`; frozen, they
    /// hold at any instant. Returns the `(parent, child)` pairs frozen, sorted.
    pub fn freeze_constant_edges(&mut self) -> Vec<(String, String)> {
        let mut frozen = Vec::new();
        for (child, edge) in &mut self.edges {
            let Some((_, first)) = edge.samples.first() else {
                continue;
            };
            let constant = edge.samples.iter().all(|(_, iso)| {
                (iso.translation.vector - first.translation.vector).norm() < 1e-6
                    && iso.rotation.angle_to(&first.rotation) < 1e-6
            });
            if edge.fixed.is_none() && constant && edge.samples.len() > 1 {
                edge.fixed = Some(*first);
                frozen.push((edge.parent.clone(), child.clone()));
            }
        }
        frozen.sort();
        frozen
    }

    /// The root of `frame`'s chain (the frame itself if it has no parent).
    pub fn root_of(&self, frame: &str) -> Result<String, TfError> {
        self.known(frame)?;
        let chain = self.chain(frame)?;
        Ok(chain.last().map_or(frame, |f| f).to_string())
    }

    /// Whether any transform mentions `frame`.
    pub fn contains(&self, frame: &str) -> bool {
        self.known(frame).is_ok()
    }

    /// Every frame mentioned, sorted.
    pub fn frames(&self) -> Vec<String> {
        let mut frames: Vec<String> = self
            .edges
            .iter()
            .flat_map(|(child, e)| [child.clone(), e.parent.clone()])
            .collect();
        frames.sort();
        frames.dedup();
        frames
    }

    /// `(parent, child, is_static, samples)` of every edge, sorted by child.
    pub fn edges(&self) -> Vec<(String, String, bool, usize)> {
        let mut edges: Vec<_> = self
            .edges
            .iter()
            .map(|(child, e)| {
                (
                    e.parent.clone(),
                    child.clone(),
                    e.fixed.is_some(),
                    e.samples.len(),
                )
            })
            .collect();
        edges.sort_by(|a, b| a.1.cmp(&b.1));
        edges
    }

    fn edge_at(&self, child: &str, edge: &Edge, stamp: Stamp) -> Result<Isometry3<f64>, TfError> {
        if let Some(fixed) = edge.fixed {
            return Ok(fixed);
        }
        let samples = &edge.samples;
        let (first, last) = match (samples.first(), samples.last()) {
            (Some(first), Some(last)) => (first, last),
            _ => unreachable!("an edge without a fixed value has samples"),
        };
        let gap = if stamp < first.0 {
            first.0.nanos_since(stamp)
        } else if stamp > last.0 {
            stamp.nanos_since(last.0)
        } else {
            let at = samples.partition_point(|(s, _)| *s <= stamp);
            let (s0, a) = &samples[at - 1];
            if *s0 == stamp || at == samples.len() {
                return Ok(*a);
            }
            let (s1, b) = &samples[at];
            let alpha = stamp.nanos_since(*s0) as f64 / s1.nanos_since(*s0) as f64;
            return Ok(interpolate(a, b, alpha));
        };
        if gap <= self.tolerance_nanos {
            return Ok(if stamp < first.0 { first.1 } else { last.1 });
        }
        Err(TfError::Extrapolation {
            parent: edge.parent.clone(),
            child: child.to_string(),
            stamp,
            first: first.0,
            last: last.0,
            gap_ms: gap as f64 * 1e-6,
            tolerance_ms: self.tolerance_nanos as f64 * 1e-6,
        })
    }

    /// The chain from `frame` up to its root: frames in order, starting with `frame`.
    fn chain<'a>(&'a self, frame: &'a str) -> Result<Vec<&'a str>, TfError> {
        let mut chain = vec![frame];
        let mut current = frame;
        while let Some((_, edge)) = self.edges.get_key_value(current) {
            current = edge.parent.as_str();
            chain.push(current);
            if chain.len() > MAX_DEPTH {
                return Err(TfError::Cycle {
                    frame: frame.to_string(),
                });
            }
        }
        Ok(chain)
    }

    fn known(&self, frame: &str) -> Result<(), TfError> {
        if self.edges.contains_key(frame) || self.edges.values().any(|e| e.parent == frame) {
            Ok(())
        } else {
            Err(TfError::UnknownFrame {
                frame: frame.to_string(),
                known: self.frames().join(", "),
            })
        }
    }

    /// `root_from_frame` along the first `steps` edges of `chain`.
    fn compose(
        &self,
        chain: &[&str],
        steps: usize,
        stamp: Stamp,
    ) -> Result<Isometry3<f64>, TfError> {
        let mut ancestor_from_frame = Isometry3::identity();
        for child in &chain[..steps] {
            let edge = &self.edges[*child];
            ancestor_from_frame = self.edge_at(child, edge, stamp)? * ancestor_from_frame;
        }
        Ok(ancestor_from_frame)
    }

    /// The stamps strictly between `from` and `to` of the samples of every stamped edge
    /// on the path between `target` and `source`, ascending (with repeats): between two
    /// of them, [`lookup`](Self::lookup) interpolates each edge within one segment.
    pub fn sample_stamps(
        &self,
        target: &str,
        source: &str,
        from: Stamp,
        to: Stamp,
    ) -> Result<Vec<Stamp>, TfError> {
        let (up_source, i, up_target, j) = self.path(target, source)?;
        let mut stamps: Vec<Stamp> = up_source[..i]
            .iter()
            .chain(&up_target[..j])
            .map(|child| &self.edges[*child])
            .filter(|edge| edge.fixed.is_none())
            .flat_map(|edge| {
                let samples = &edge.samples;
                let begin = samples.partition_point(|(s, _)| *s <= from);
                let end = samples.partition_point(|(s, _)| *s < to);
                samples[begin..end.max(begin)].iter().map(|(s, _)| *s)
            })
            .collect();
        stamps.sort_unstable();
        Ok(stamps)
    }

    /// Both frames' chains up to the root, and how many edges of each lead to the first
    /// frame they share.
    #[allow(clippy::type_complexity)]
    fn path<'a>(
        &'a self,
        target: &'a str,
        source: &'a str,
    ) -> Result<(Vec<&'a str>, usize, Vec<&'a str>, usize), TfError> {
        self.known(target)?;
        self.known(source)?;
        let up_source = self.chain(source)?;
        let up_target = self.chain(target)?;
        let (i, j) = up_source
            .iter()
            .enumerate()
            .find_map(|(i, f)| up_target.iter().position(|g| g == f).map(|j| (i, j)))
            .ok_or_else(|| TfError::NotConnected {
                target: target.to_string(),
                source_frame: source.to_string(),
            })?;
        Ok((up_source, i, up_target, j))
    }

    /// `target_from_source` at `stamp`: maps points in `source` to points in `target`.
    pub fn lookup(
        &self,
        target: &str,
        source: &str,
        stamp: Stamp,
    ) -> Result<Isometry3<f64>, TfError> {
        let (up_source, i, up_target, j) = self.path(target, source)?;
        let common_from_source = self.compose(&up_source, i, stamp)?;
        let common_from_target = self.compose(&up_target, j, stamp)?;
        Ok(common_from_target.inverse() * common_from_source)
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use nalgebra::{Point3, Vector3};

    fn tf(
        stamp: i64,
        parent: &str,
        child: &str,
        x: f64,
        yaw: f64,
        is_static: bool,
    ) -> StampedTransform {
        StampedTransform {
            stamp: Stamp::from_nanos(stamp),
            parent_frame: parent.into(),
            child_frame: child.into(),
            parent_from_child: Isometry3::new(Vector3::new(x, 0.0, 0.0), Vector3::z() * yaw),
            is_static,
        }
    }

    #[test]
    fn interpolates_translation_linearly_and_rotation_by_slerp() {
        let mut tree = TransformTree::new(0);
        tree.insert(tf(2_000, "map", "base_link", 2.0, 0.4, false))
            .unwrap();
        tree.insert(tf(1_000, "map", "base_link", 1.0, 0.0, false))
            .unwrap(); // out of order
        let mid = tree
            .lookup("map", "base_link", Stamp::from_nanos(1_250))
            .unwrap();
        assert!((mid.translation.vector.x - 1.25).abs() < 1e-12);
        assert!((mid.rotation.angle() - 0.1).abs() < 1e-12);
        let exact = tree
            .lookup("map", "base_link", Stamp::from_nanos(2_000))
            .unwrap();
        assert!((exact.rotation.angle() - 0.4).abs() < 1e-12);
        let inverse = tree
            .lookup("base_link", "map", Stamp::from_nanos(1_250))
            .unwrap();
        assert!((inverse * mid).translation.vector.norm() < 1e-12);
    }

    #[test]
    fn sample_stamps_are_those_of_the_stamped_edges_on_the_path() {
        let mut tree = TransformTree::new(0);
        for k in 0..5 {
            tree.insert(tf(k * 100, "map", "odom", 0.0, 0.0, false))
                .unwrap();
            tree.insert(tf(k * 40 + 5, "odom", "base_link", 0.0, 0.0, false))
                .unwrap();
            tree.insert(tf(k * 10, "base_link", "cam", 0.0, 0.0, false))
                .unwrap();
        }
        tree.insert(tf(0, "base_link", "lidar", 0.5, 0.0, true))
            .unwrap();
        let stamps = |target, source, from, to| -> Vec<i64> {
            tree.sample_stamps(
                target,
                source,
                Stamp::from_nanos(from),
                Stamp::from_nanos(to),
            )
            .unwrap()
            .into_iter()
            .map(Stamp::nanos)
            .collect()
        };
        // map ← odom ← base_link ← lidar: the map and odom edges, strictly inside.
        assert_eq!(stamps("map", "lidar", 45, 200), [85, 100, 125, 165]);
        assert_eq!(stamps("lidar", "map", 45, 200), [85, 100, 125, 165]);
        // lidar → base_link ← cam: only the camera's edge; the static one has none.
        assert_eq!(stamps("lidar", "cam", 5, 30), [10, 20]);
        assert!(stamps("map", "lidar", 100, 100).is_empty());
        assert!(
            tree.sample_stamps("map", "nowhere", Stamp::from_nanos(0), Stamp::from_nanos(1))
                .is_err()
        );
    }

    #[test]
    fn composes_chains_through_a_common_ancestor() {
        let mut tree = TransformTree::new(0);
        tree.insert(tf(
            0,
            "map",
            "odom",
            10.0,
            std::f64::consts::FRAC_PI_2,
            true,
        ))
        .unwrap();
        tree.insert(tf(0, "odom", "base_link", 1.0, 0.0, false))
            .unwrap();
        tree.insert(tf(100, "odom", "base_link", 3.0, 0.0, false))
            .unwrap();
        tree.insert(tf(0, "base_link", "lidar", 0.5, 0.0, true))
            .unwrap();
        tree.insert(tf(0, "base_link", "cam", 0.0, std::f64::consts::PI, true))
            .unwrap();
        // lidar origin at t=50: odom (2.5, 0), map = (10, 0) + rot90 * (2.5, 0) = (10, 2.5).
        let map_from_lidar = tree.lookup("map", "lidar", Stamp::from_nanos(50)).unwrap();
        let p = map_from_lidar * Point3::origin();
        assert!((p - Point3::new(10.0, 2.5, 0.0)).norm() < 1e-12, "{p}");
        // Sibling frames: the lidar origin seen from the camera (rotated 180°): (-0.5, 0).
        let cam_from_lidar = tree.lookup("cam", "lidar", Stamp::from_nanos(50)).unwrap();
        let q = cam_from_lidar * Point3::origin();
        assert!((q - Point3::new(-0.5, 0.0, 0.0)).norm() < 1e-12, "{q}");
        assert_eq!(tree.frames(), ["base_link", "cam", "lidar", "map", "odom"]);
    }

    #[test]
    fn extrapolation_is_bounded_and_errors_name_the_edge() {
        let mut tree = TransformTree::new(5);
        tree.insert(tf(100, "map", "base_link", 1.0, 0.0, false))
            .unwrap();
        tree.insert(tf(200, "map", "base_link", 2.0, 0.0, false))
            .unwrap();
        assert!(
            tree.lookup("map", "base_link", Stamp::from_nanos(204))
                .is_ok()
        );
        let err = tree
            .lookup("map", "base_link", Stamp::from_nanos(300))
            .unwrap_err();
        assert!(matches!(err, TfError::Extrapolation { .. }));
        assert!(err.to_string().contains("map -> base_link"), "{err}");
        let err = tree
            .lookup("map", "camera", Stamp::from_nanos(150))
            .unwrap_err();
        assert!(err.to_string().contains("`camera`"), "{err}");
        tree.insert(tf(0, "world", "other", 1.0, 0.0, true))
            .unwrap();
        assert!(matches!(
            tree.lookup("map", "other", Stamp::from_nanos(150)),
            Err(TfError::NotConnected { .. })
        ));
        assert!(matches!(
            tree.insert(tf(0, "odom", "base_link", 0.0, 0.0, false)),
            Err(TfError::Reparented { .. })
        ));
    }

    #[test]
    fn constant_stamped_edges_are_frozen_into_static_ones() {
        let mut tree = TransformTree::new(0);
        for t in [100, 600, 1_100] {
            tree.insert(tf(t, "base_link", "CAM_FRONT", 1.5, 0.2, false))
                .unwrap();
            tree.insert(tf(t, "map", "base_link", t as f64, 0.0, false))
                .unwrap();
        }
        assert!(
            tree.lookup("base_link", "CAM_FRONT", Stamp::from_nanos(2_000))
                .is_err()
        );
        let frozen = tree.freeze_constant_edges();
        assert_eq!(frozen, [("base_link".to_string(), "CAM_FRONT".to_string())]);
        let late = tree
            .lookup("base_link", "CAM_FRONT", Stamp::from_nanos(2_000))
            .unwrap();
        assert!((late.translation.vector.x - 1.5).abs() < 1e-12);
        assert!(
            tree.lookup("map", "base_link", Stamp::from_nanos(2_000))
                .is_err()
        );
    }

    #[test]
    fn slerp_takes_the_short_way_around() {
        let mut tree = TransformTree::new(0);
        let mut a = tf(0, "map", "b", 0.0, 0.1, false);
        let b = tf(10, "map", "b", 0.0, 0.3, false);
        // Same rotation, opposite quaternion sign.
        a.parent_from_child.rotation =
            UnitQuaternion::new_unchecked(-a.parent_from_child.rotation.into_inner());
        tree.insert(a).unwrap();
        tree.insert(b).unwrap();
        let mid = tree.lookup("map", "b", Stamp::from_nanos(5)).unwrap();
        assert!((mid.rotation.angle() - 0.2).abs() < 1e-12);
    }
}
