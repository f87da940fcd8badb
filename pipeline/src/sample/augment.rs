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
        let r =
            Rotation3::from_axis_angle(&Vector3::z_axis(), self.yaw_rad).into_inner() * self.scale;
        let (sx, sy) = (
            if self.flip_x { -1.0 } else { 1.0 },
            if self.flip_y { -1.0 } else { 1.0 },
        );
        for p in xyz {
            let v = r * Vector3::new(sx * f64::from(p[0]), sy * f64::from(p[1]), f64::from(p[2]));
            *p = [v.x as f32, v.y as f32, v.z as f32];
        }
    }
}
