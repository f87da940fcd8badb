//! What the scene is made of: upright boxes ([`SceneBox`]), some of them moving
//! ([`Motion`]), and what a ray that meets one reports ([`Hit`]).

use nalgebra::{Point3, Vector3};

/// How a box moves: constant velocity along x from `x0` at the drive's start.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct Motion {
    /// Speed along +x in m/s (negative: driving towards -x).
    pub speed_x: f64,
}

/// An upright box (yaw only) with a class and a base colour.
#[derive(Debug, Clone, PartialEq)]
pub struct SceneBox {
    /// Stable name, used for landmarks.
    pub name: String,
    /// Centre of the box at the drive's start (map frame).
    pub center: Point3<f64>,
    /// Half extents along the box's own x, y, z.
    pub half: Vector3<f64>,
    /// Heading about z, radians.
    pub yaw: f64,
    /// Semantic class.
    pub class: u8,
    /// Base colour (linear RGB in 0..1).
    pub color: [f64; 3],
    /// LiDAR reflectivity in 0..1.
    pub reflectivity: f64,
    /// `None` for static boxes.
    pub motion: Option<Motion>,
}

impl SceneBox {
    /// Centre at `t_secs` after the drive's start.
    pub fn center_at(&self, t_secs: f64) -> Point3<f64> {
        match self.motion {
            None => self.center,
            Some(m) => self.center + Vector3::new(m.speed_x * t_secs, 0.0, 0.0),
        }
    }

    /// Whether the box moves during the drive.
    pub fn is_moving(&self) -> bool {
        self.motion.is_some_and(|m| m.speed_x != 0.0)
    }

    /// The eight corners at `t_secs`, bottom ones first.
    pub fn corners_at(&self, t_secs: f64) -> [Point3<f64>; 8] {
        let c = self.center_at(t_secs);
        let (s, co) = self.yaw.sin_cos();
        let mut out = [Point3::origin(); 8];
        for (i, corner) in out.iter_mut().enumerate() {
            let lx = if i & 1 == 0 {
                -self.half.x
            } else {
                self.half.x
            };
            let ly = if i & 2 == 0 {
                -self.half.y
            } else {
                self.half.y
            };
            let lz = if i & 4 == 0 {
                -self.half.z
            } else {
                self.half.z
            };
            *corner = Point3::new(c.x + co * lx - s * ly, c.y + s * lx + co * ly, c.z + lz);
        }
        out
    }
}

/// What a ray hit.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct Hit {
    /// Distance along the (unit) ray.
    pub distance: f64,
    /// Hit point in the map frame.
    pub point: Point3<f64>,
    /// Outward surface normal (unit).
    pub normal: Vector3<f64>,
    /// Semantic class.
    pub class: u8,
    /// Surface colour at the hit (texture included).
    pub color: [f64; 3],
    /// LiDAR reflectivity at the hit.
    pub reflectivity: f64,
    /// Id of the box hit (its index in [`Scene::boxes`]); `None` for the ground.
    pub object: Option<u32>,
}

/// The street scene.
#[derive(Debug, Clone)]
pub struct Scene {
    /// Every box of the scene.
    pub boxes: Vec<SceneBox>,
}

impl Scene {
    /// The box of object id `id` (as [`Hit::object`] gives it), if there is one.
    pub fn object(&self, id: u32) -> Option<&SceneBox> {
        self.boxes.get(usize::try_from(id).ok()?)
    }

    /// Whether object `id` is a box that moves during the drive (`false` for an id
    /// without a box).
    pub fn is_moving(&self, id: u32) -> bool {
        self.object(id).is_some_and(SceneBox::is_moving)
    }
}
