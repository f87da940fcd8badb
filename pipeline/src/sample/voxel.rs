//! Voxelization: points → unique integer cells, one representative point per cell, and
//! the map from every point to its cell.

use super::cellkey::{Keyed, count_runs, sort_cells};
use serde::{Deserialize, Serialize};
use superflow_common::InvalidSetting;

/// How points are binned.
#[derive(Debug, Clone, Copy, PartialEq, Serialize, Deserialize)]
#[serde(tag = "kind", rename_all = "snake_case")]
pub enum VoxelGrid {
    /// Cells of `rho_m` in range, `phi_deg` in azimuth and `z_m` in height (the paper's
    /// default: 0.1 m, 1°, 0.1 m). Azimuth is `atan2(y, x)` in degrees, in `[-180, 180)`;
    /// it does not wrap (cells at −180° and 179° are not neighbours), as in the official
    /// code.
    Cylindrical {
        /// Range bin, metres.
        rho_m: f32,
        /// Azimuth bin, degrees.
        phi_deg: f32,
        /// Height bin, metres.
        z_m: f32,
    },
    /// Cubic-ish cells of the given size along x, y, z, metres.
    Cartesian {
        /// Cell size, metres.
        size_m: [f32; 3],
    },
}

impl Default for VoxelGrid {
    fn default() -> Self {
        VoxelGrid::Cylindrical {
            rho_m: 0.1,
            phi_deg: 1.0,
            z_m: 0.1,
        }
    }
}

/// `v.floor() as i32` without a call to libm's `floorf` (x86-64 without SSE4.1 has no
/// floor instruction): truncate, then step down for negative non-integers. Saturates
/// like the cast.
#[inline]
pub(super) fn floor_i32(v: f32) -> i32 {
    let t = v as i32;
    t.saturating_sub(i32::from(v < t as f32))
}

impl VoxelGrid {
    /// The cell of one point.
    pub fn cell(&self, p: [f32; 3]) -> [i32; 3] {
        let [x, y, z] = p;
        match *self {
            VoxelGrid::Cylindrical {
                rho_m,
                phi_deg,
                z_m,
            } => {
                let rho = x.hypot(y);
                let phi = y.atan2(x).to_degrees();
                // atan2 returns 180 for (-x, +0): fold it onto -180 so phi is in [-180, 180).
                let phi = if phi >= 180.0 { phi - 360.0 } else { phi };
                [
                    floor_i32(rho / rho_m),
                    floor_i32(phi / phi_deg),
                    floor_i32(z / z_m),
                ]
            }
            VoxelGrid::Cartesian { size_m } => [
                floor_i32(x / size_m[0]),
                floor_i32(y / size_m[1]),
                floor_i32(z / size_m[2]),
            ],
        }
    }

    /// The cells of all of `xyz`: the same as [`cell`](Self::cell) point by point, faster
    /// for cylindrical grids (see `cylinder.rs`).
    pub fn cells(&self, xyz: &[[f32; 3]]) -> Vec<[i32; 3]> {
        match *self {
            VoxelGrid::Cylindrical {
                rho_m,
                phi_deg,
                z_m,
            } => super::cylinder::cylindrical_cells(xyz, [rho_m, phi_deg, z_m], &|p| self.cell(p)),
            VoxelGrid::Cartesian { .. } => xyz.iter().map(|p| self.cell(*p)).collect(),
        }
    }

    /// Checks that the cell sizes are finite and positive; the error names the size as
    /// `voxel.<field>` (the caller adds its own prefix, e.g. `sample.`).
    pub fn validate(&self) -> Result<(), InvalidSetting> {
        let bad = |s: &f32| !(s.is_finite() && *s > 0.0);
        let rule = "must be finite and positive";
        match *self {
            VoxelGrid::Cylindrical {
                rho_m,
                phi_deg,
                z_m,
            } => {
                for (name, size) in [("rho_m", rho_m), ("phi_deg", phi_deg), ("z_m", z_m)] {
                    if bad(&size) {
                        return Err(InvalidSetting::new(format!("voxel.{name}"), size, rule));
                    }
                }
                Ok(())
            }
            VoxelGrid::Cartesian { size_m } if size_m.iter().any(bad) => Err(InvalidSetting::new(
                "voxel.size_m",
                format!("{size_m:?}"),
                rule,
            )),
            VoxelGrid::Cartesian { .. } => Ok(()),
        }
    }
}

/// The voxels of one cloud.
#[derive(Debug, Clone, PartialEq, Eq)]
pub struct Voxelized {
    /// Unique cells, sorted lexicographically by `(x, y, z)` (neighbours in space are
    /// near in memory, and the sparse-convolution maps are found by merging).
    pub coords: Vec<[i32; 3]>,
    /// For each cell, the index of its representative point (the first point in it).
    pub representative: Vec<u32>,
    /// For each point, the index of its cell in `coords`.
    pub point_to_voxel: Vec<u32>,
}

/// Bins `xyz` (finite points) into `grid`. Deterministic: cells are sorted, and the
/// first point of each cell (lowest index) represents it.
pub fn voxelize(xyz: &[[f32; 3]], grid: &VoxelGrid) -> Voxelized {
    voxelize_keyed(xyz, grid).0
}

/// [`voxelize`], and the voxels' packed keys when the cells have a packing (for the
/// first level's neighbour map: see `kernel_maps::build_levels_keyed`).
pub(crate) fn voxelize_keyed(xyz: &[[f32; 3]], grid: &VoxelGrid) -> (Voxelized, Option<Keyed>) {
    let cells = grid.cells(xyz);
    // Equal cells end up next to each other, in point order.
    let (order, keyed) = sort_cells(&cells);
    let same = |s: usize, t: usize| match &keyed {
        Some((_, keys)) => keys[s] == keys[t],
        None => cells[order[s] as usize] == cells[order[t] as usize],
    };
    // Without a packing (cells thousands of kilometres apart) the vectors grow instead.
    let unique = keyed.as_ref().map_or(0, |(_, keys)| count_runs(keys));
    let mut coords = Vec::with_capacity(unique);
    let mut representative = Vec::with_capacity(unique);
    let mut voxel_keys = Vec::with_capacity(unique);
    let mut point_to_voxel = vec![0u32; xyz.len()];
    for (s, &point) in order.iter().enumerate() {
        if s == 0 || !same(s - 1, s) {
            coords.push(cells[point as usize]);
            representative.push(point);
            if let Some((_, keys)) = &keyed {
                voxel_keys.push(keys[s]);
            }
        }
        point_to_voxel[point as usize] = (coords.len() - 1) as u32;
    }
    let voxel_keys = keyed.map(|(packing, _)| (packing, voxel_keys));
    let voxels = Voxelized {
        coords,
        representative,
        point_to_voxel,
    };
    (voxels, voxel_keys)
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn floor_without_libm_is_floor() {
        for v in [
            0.0f32,
            -0.0,
            0.5,
            -0.5,
            1.0,
            -1.0,
            2.999_999_8,
            -2.999_999_8,
            1e-30,
            -1e-30,
            16_777_217.0,
            -16_777_217.0,
            3e9,
            -3e9,
            f32::MAX,
            f32::MIN,
            f32::NAN,
        ] {
            assert_eq!(floor_i32(v), v.floor() as i32, "{v}");
        }
        let mut state = 0x9E37_79B9u32;
        for _ in 0..100_000 {
            state = state.wrapping_mul(1_664_525).wrapping_add(1_013_904_223);
            let v = f32::from_bits(state);
            if v.is_finite() {
                assert_eq!(floor_i32(v), v.floor() as i32, "{v}");
            }
            let w = (state as i32) as f32 / 1000.0;
            assert_eq!(floor_i32(w), w.floor() as i32, "{w}");
        }
    }

    #[test]
    fn cylindrical_cells_match_hand_computed_values() {
        let grid = VoxelGrid::default();
        // rho = sqrt(2) = 1.414 -> 14; phi = 45 deg -> 45; z = 0.25 -> 2.
        assert_eq!(grid.cell([1.0, 1.0, 0.25]), [14, 45, 2]);
        // Behind and to the right: phi = -135 deg; z = -1.55 -> -16.
        assert_eq!(grid.cell([-1.0, -1.0, -1.55]), [14, -135, -16]);
        // Straight behind: phi folds onto -180.
        assert_eq!(grid.cell([-5.0, 0.0, 0.0])[1], -180);
        let cart = VoxelGrid::Cartesian {
            size_m: [0.5, 0.5, 0.25],
        };
        assert_eq!(cart.cell([1.2, -0.1, 0.3]), [2, -1, 1]);
        assert!(
            VoxelGrid::Cartesian {
                size_m: [0.0, 1.0, 1.0]
            }
            .validate()
            .is_err()
        );
    }

    #[test]
    fn voxels_are_unique_with_first_point_representatives() {
        let points = [
            [1.0, 1.0, 0.25],
            [1.0, 1.0, 0.27], // same cell as point 0
            [5.0, 0.0, 0.0],
            [1.0, 1.0, 0.25], // duplicate of point 0
            [-3.0, 2.0, 1.0],
        ];
        let v = voxelize(&points, &VoxelGrid::default());
        // Cells in (rho, phi, z) order: [14, 45, 2] (points 0, 1, 3), [36, 146, 10]
        // (point 4), [50, 0, 0] (point 2); each represented by its first point.
        assert_eq!(v.coords, [[14, 45, 2], [36, 146, 10], [50, 0, 0]]);
        assert_eq!(v.representative, [0, 4, 2]);
        assert_eq!(v.point_to_voxel, [0, 0, 2, 0, 1]);
        for (i, p) in points.iter().enumerate() {
            assert_eq!(
                v.coords[v.point_to_voxel[i] as usize],
                VoxelGrid::default().cell(*p)
            );
        }
    }
}
