//! The 3D augmentation of a cloud — a flip, a rotation about z and a scale — drawn from
//! the sample's keyed random stream and applied after the points are paired with pixels.

use super::recipe::SampleConfig;
use super::rng::SampleRng;
use nalgebra::{Rotation3, Vector3};
use serde::Serialize;

/// The 3D augmentation drawn for one cloud: `p' = scale · Rz(yaw) · flip · p`.
#[derive(Debug, Clone, Copy, PartialEq, Serialize)]
pub struct Augmentation {
    /// x → −x.
    pub flip_x: bool,
    /// y → −y.
    pub flip_y: bool,
    /// Rotation about z, radians.
    pub yaw_rad: f64,
    /// Scale factor.
    pub scale: f64,
}

impl Augmentation {
    /// No change.
    pub const IDENTITY: Augmentation = Augmentation {
        flip_x: false,
        flip_y: false,
        yaw_rad: 0.0,
        scale: 1.0,
    };

    pub(super) fn draw(config: &SampleConfig, rng: &mut SampleRng) -> Self {
        let a = &config.augment;
        if !a.enabled {
            return Self::IDENTITY;
        }
        Augmentation {
            flip_x: rng.bernoulli(a.flip_x_probability),
            flip_y: rng.bernoulli(a.flip_y_probability),
            yaw_rad: rng.uniform(0.0, a.rotation_max_rad),
            scale: rng.uniform(a.scale_min, a.scale_max),
        }
    }

    /// Applies the augmentation to points in place.
    pub fn apply(&self, xyz: &mut [[f32; 3]]) {
        if *self == Self::IDENTITY {
            return;
        }
        let map = self.point_map();
        for p in xyz {
            *p = map(*p);
        }
    }

    /// The augmented copy of `xyz` (what [`apply`](Self::apply) does to a clone, in one
    /// pass).
    pub fn applied(&self, xyz: &[[f32; 3]]) -> Vec<[f32; 3]> {
        if *self == Self::IDENTITY {
            return xyz.to_vec();
        }
        let map = self.point_map();
        xyz.iter().map(|p| map(*p)).collect()
    }

    /// The points back where they were before the augmentation (in their LiDAR frame):
    /// `p = flip · Rz(−yaw) · p' / scale`, in `f64`. Viewers place them with the cameras.
    pub fn unapplied(&self, xyz: &[[f32; 3]]) -> Vec<[f32; 3]> {
        if *self == Self::IDENTITY {
            return xyz.to_vec();
        }
        let r =
            Rotation3::from_axis_angle(&Vector3::z_axis(), -self.yaw_rad).into_inner() / self.scale;
        let (sx, sy) = (
            if self.flip_x { -1.0 } else { 1.0 },
            if self.flip_y { -1.0 } else { 1.0 },
        );
        xyz.iter()
            .map(|p| {
                let v = r * Vector3::new(f64::from(p[0]), f64::from(p[1]), f64::from(p[2]));
                [(sx * v.x) as f32, (sy * v.y) as f32, v.z as f32]
            })
            .collect()
    }

    /// The augmentation of one point: flips, then the scaled rotation, in `f64`.
    fn point_map(&self) -> impl Fn([f32; 3]) -> [f32; 3] {
        let r =
            Rotation3::from_axis_angle(&Vector3::z_axis(), self.yaw_rad).into_inner() * self.scale;
        let (sx, sy) = (
            if self.flip_x { -1.0 } else { 1.0 },
            if self.flip_y { -1.0 } else { 1.0 },
        );
        move |p| {
            let v = r * Vector3::new(sx * f64::from(p[0]), sy * f64::from(p[1]), f64::from(p[2]));
            [v.x as f32, v.y as f32, v.z as f32]
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn unapplying_gives_the_points_back() {
        let a = Augmentation {
            flip_x: true,
            flip_y: false,
            yaw_rad: 2.1,
            scale: 1.04,
        };
        let points = [[12.5f32, -3.25, 1.5], [-40.0, 22.0, -1.75], [0.0, 0.0, 0.0]];
        for (p, q) in points.iter().zip(a.unapplied(&a.applied(&points))) {
            for k in 0..3 {
                assert!((p[k] - q[k]).abs() < 1e-5, "{p:?} → {q:?}");
            }
        }
        assert_eq!(Augmentation::IDENTITY.unapplied(&points), points);
    }

    #[test]
    fn the_augmented_copy_is_the_copy_augmented_in_place() {
        let mut rng = crate::test_rng::TestRng(0x6a09_e667_f3bc_c908);
        let mut unit = move || (rng.next() >> 11) as f64 / (1u64 << 53) as f64;
        let points: Vec<[f32; 3]> = (0..1000)
            .map(|_| {
                [
                    (unit() - 0.5) * 200.0,
                    (unit() - 0.5) * 200.0,
                    unit() * 6.0 - 2.0,
                ]
            })
            .map(|p| p.map(|v| v as f32))
            .collect();
        for k in 0..16 {
            let a = Augmentation {
                flip_x: k & 1 == 1,
                flip_y: k & 2 == 2,
                yaw_rad: unit() * std::f64::consts::PI,
                scale: 0.95 + unit() * 0.1,
            };
            let mut in_place = points.clone();
            a.apply(&mut in_place);
            assert_eq!(a.applied(&points), in_place, "{a:?}");
            assert_ne!(in_place, points);
        }
        assert_eq!(Augmentation::IDENTITY.applied(&points), points);
        // A quarter turn, flipped in x and doubled: (1, 2, 3) -> (-1, 2, 3) -> (-2, -1, 3) · 2.
        let quarter = Augmentation {
            flip_x: true,
            flip_y: false,
            yaw_rad: std::f64::consts::FRAC_PI_2,
            scale: 2.0,
        };
        let [x, y, z] = quarter.applied(&[[1.0, 2.0, 3.0]])[0];
        assert!((x + 4.0).abs() < 1e-6 && (y + 2.0).abs() < 1e-6 && (z - 6.0).abs() < 1e-6);
    }
}
