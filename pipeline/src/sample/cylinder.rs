//! Cylindrical cells of a whole cloud, fast and identical to [`VoxelGrid::cell`].
//!
//! The per-point formula calls libm's `hypotf` and `atan2f`, which cost tens of
//! nanoseconds a point and are not vectorized. Here range and azimuth are first computed in `f32` lanes, eight
//! points to an AVX2 register — a square root and an arctangent polynomial — and floored
//! when the value lies clearly inside a cell; a value within a margin of a cell boundary
//! (or of the ±180° fold, or not finite, or huge) takes the exact per-point formula
//! instead. The margin covers both this pass's error (the polynomial's and every
//! rounding's) and the rounding of the `f32` formula, so the cells are the ones the
//! formula gives, bit for bit (tested on millions of points, boundaries included); one or
//! two points in a thousand take the exact path. The pass is in `f32` rather than `f64`
//! so that a register holds eight points instead of four.
//!
//! [`VoxelGrid::cell`]: super::voxel::VoxelGrid::cell

use std::f32::consts::{FRAC_PI_2, PI};

/// `atan(t) / t` as a polynomial in `t²` on `[0, 1]`: a least-squares fit at
/// Chebyshev nodes (weighted by `t`); `t·P(t²)` evaluated in `f32` is within 1.4e-7 rad
/// of `atan(t)`.
const ATAN_COEFFS: [f32; 8] = [
    0.999_999_46,
    -0.333_301_07,
    0.199_485_1,
    -0.139_158_03,
    0.096_562_564,
    -0.056_063_175,
    0.021_946_61,
    -0.004_073_309_2,
];

/// Bound on [`atan2`]'s error, radians: the fit, the quotient `t`, the polynomial's
/// roundings and the reductions by `π/2` and `π` in `f32` come to under 5e-7; four times
/// that.
const ATAN_ERROR: f32 = 2e-6;

/// Relative error of the value this pass computes (a few `f32` roundings: under 5e-7)
/// plus what the `f32` formula may carry (`hypotf`/`atan2f` within 2 ulp, the degree
/// constant, a product and a quotient each rounded: under 4e-7), with room.
const RELATIVE: f32 = 2e-6;

/// Cells of slack on top of the margins: the floor's own subtractions round for values
/// under one cell (by at most 6e-8), and ranges so small that `x² + y²` underflows
/// (under 1e-19 m) must not look clear.
const SLACK: f32 = 1e-5;

/// Beyond this many cells the exact formula decides (under 2²², where adding
/// [`ROUND_F32`] rounds to integers).
const LARGE: f32 = 4e6;

/// `atan2(y, x)` in radians within [`ATAN_ERROR`], branch-light.
#[inline(always)]
fn atan2(y: f32, x: f32) -> f32 {
    let (ax, ay) = (x.abs(), y.abs());
    let (lo, hi) = (ax.min(ay), ax.max(ay));
    let t = if hi > 0.0 { lo / hi } else { 0.0 };
    let s = t * t;
    let p = ATAN_COEFFS.iter().rev().fold(0.0, |acc, c| acc * s + c);
    let r = t * p;
    let r = if ay > ax { FRAC_PI_2 - r } else { r };
    let r = if x < 0.0 { PI - r } else { r };
    if y < 0.0 { -r } else { r }
}

/// `1.5·2²³`: adding it to an `f32` of magnitude under 2²² rounds it to an integer, held
/// in the low bits of the sum's mantissa (offset by 2²²).
const ROUND_F32: f32 = 12_582_912.0;

/// `floor(q)`, and whether every value within `margin` of `q` has that floor, in plain
/// float arithmetic so that a loop of it runs in vector lanes: `q.floor()` would call
/// libm (x86-64 has no floor instruction before SSE4.1) and `as` casts saturate, which
/// the compiler does lane by lane. `q` is rounded by adding and removing
/// [`ROUND_F32`], stepped down if that rounded up, and the integer read from the low
/// bits of the floor plus [`ROUND_F32`]. Only a clear `q` (under [`LARGE`], finite)
/// needs the right cell; any other gets the exact formula.
#[inline(always)]
fn clear_floor(q: f32, margin: f32) -> (i32, bool) {
    let f = floor_of(q);
    (
        cell_of(f),
        q.abs() < LARGE && q - f >= margin && f + 1.0 - q >= margin,
    )
}

/// `floor(v)` as a float, for an `f32` under 2²² (see [`clear_floor`]).
#[inline(always)]
fn floor_of(v: f32) -> f32 {
    let r = (v + ROUND_F32) - ROUND_F32;
    if r > v { r - 1.0 } else { r }
}

/// The integer `f` (a floor from [`floor_of`]), read from the low bits of `f` plus
/// [`ROUND_F32`].
#[inline(always)]
fn cell_of(f: f32) -> i32 {
    let bits = (f + ROUND_F32).to_bits() as i32;
    (bits & 0x7F_FFFF) - 0x40_0000
}

/// `floor(v)` as [`clear_floor`] finds it, for an `f32` under 2²², and whether `v` is
/// (finite and) that small.
#[inline(always)]
fn small_floor(v: f32) -> (i32, bool) {
    (cell_of(floor_of(v)), v.abs() < 4_194_304.0)
}

/// Points per batch of the arithmetic pass (kept in registers and L1).
const CHUNK: usize = 64;

/// The cylindrical cells of `xyz` (cell sizes `rho_m`, `phi_deg`, `z_m`); `exact` is
/// the per-point formula, used near boundaries.
///
/// Also compiled with AVX2 and with AVX-512 (eight and sixteen lanes), chosen at run
/// time: the same IEEE operations in the same order (no FMA), so the same cells.
#[allow(unsafe_code)]
pub(super) fn cylindrical_cells(
    xyz: &[[f32; 3]],
    sizes: [f32; 3],
    exact: &dyn Fn([f32; 3]) -> [i32; 3],
) -> Vec<[i32; 3]> {
    #[cfg(target_arch = "x86_64")]
    if super::simd::has_avx512() {
        // SAFETY: the CPU runs AVX-512 F and BW (checked just above), the only
        // requirement of calling a function compiled with them enabled.
        return unsafe { cylindrical_cells_avx512(xyz, sizes, exact) };
    }
    #[cfg(target_arch = "x86_64")]
    if crate::sample::simd::has_avx2() {
        // SAFETY: the CPU runs AVX2 (checked just above), the only requirement of calling
        // a function compiled with it enabled.
        return unsafe { cylindrical_cells_avx2(xyz, sizes, exact) };
    }
    cylindrical_cells_inline(xyz, sizes, exact)
}

/// [`cylindrical_cells`] compiled with AVX2 enabled.
#[cfg(target_arch = "x86_64")]
#[target_feature(enable = "avx2")]
fn cylindrical_cells_avx2(
    xyz: &[[f32; 3]],
    sizes: [f32; 3],
    exact: &dyn Fn([f32; 3]) -> [i32; 3],
) -> Vec<[i32; 3]> {
    cylindrical_cells_inline(xyz, sizes, exact)
}

/// [`cylindrical_cells`] compiled with AVX-512 enabled.
#[cfg(target_arch = "x86_64")]
#[target_feature(enable = "avx512f,avx512bw,avx2")]
fn cylindrical_cells_avx512(
    xyz: &[[f32; 3]],
    sizes: [f32; 3],
    exact: &dyn Fn([f32; 3]) -> [i32; 3],
) -> Vec<[i32; 3]> {
    cylindrical_cells_inline(xyz, sizes, exact)
}

#[inline(always)]
fn cylindrical_cells_inline(
    xyz: &[[f32; 3]],
    [rho_m, phi_deg, z_m]: [f32; 3],
    exact: &dyn Fn([f32; 3]) -> [i32; 3],
) -> Vec<[i32; 3]> {
    let per_rho = 1.0 / rho_m;
    let per_phi = 1f32.to_degrees() / phi_deg;
    let phi_error = ATAN_ERROR * per_phi + SLACK;
    // Cells of 180° and beyond: the fold's cells.
    let fold = 179.9f32.to_radians() * per_phi;
    let mut out = Vec::with_capacity(xyz.len());
    let mut near_boundary = Vec::new();
    let (mut rho, mut phi) = ([0f32; CHUNK], [0f32; CHUNK]);
    let mut cells = [[0i32; 3]; CHUNK];
    let mut clear = [false; CHUNK];
    for (c, chunk) in xyz.chunks(CHUNK).enumerate() {
        // Branch-free arithmetic, one point per lane: the compiler vectorizes both loops.
        for ((p, r), a) in chunk.iter().zip(&mut rho).zip(&mut phi) {
            let (x, y) = (p[0], p[1]);
            *r = (x * x + y * y).sqrt() * per_rho;
            *a = atan2(y, x) * per_phi;
        }
        for ((((p, &r), &a), cell), ok) in chunk
            .iter()
            .zip(&rho)
            .zip(&phi)
            .zip(&mut cells)
            .zip(&mut clear)
        {
            let (r_cell, r_clear) = clear_floor(r, r.abs() * RELATIVE + SLACK);
            let (a_cell, a_clear) = clear_floor(a, a.abs() * RELATIVE + phi_error);
            // The formula's own f32 quotient, floored: exact wherever it is small.
            let (z_cell, z_clear) = small_floor(p[2] / z_m);
            *cell = [r_cell, a_cell, z_cell];
            *ok = r_clear & a_clear & z_clear & (a.abs() < fold);
        }
        out.extend_from_slice(&cells[..chunk.len()]);
        // Points near a boundary get their cell after the pass (a reduction first: in
        // most chunks there is none).
        if clear[..chunk.len()].iter().fold(true, |all, &ok| all & ok) {
            continue;
        }
        for (j, ok) in clear[..chunk.len()].iter().enumerate() {
            if !ok {
                near_boundary.push(c * CHUNK + j);
            }
        }
    }
    for i in near_boundary {
        out[i] = exact(xyz[i]);
    }
    out
}

#[cfg(test)]
mod tests {
    use super::super::voxel::VoxelGrid;

    /// Every point's fast cell against the per-point formula, from the copy the CPU
    /// runs and from the baseline copy.
    fn assert_same(grid: &VoxelGrid, points: &[[f32; 3]]) {
        let fast = grid.cells(points);
        for (p, c) in points.iter().zip(&fast) {
            assert_eq!(*c, grid.cell(*p), "{p:?} in {grid:?}");
        }
        if let VoxelGrid::Cylindrical {
            rho_m,
            phi_deg,
            z_m,
        } = *grid
        {
            let exact = |p| grid.cell(p);
            let sizes = [rho_m, phi_deg, z_m];
            let baseline = super::cylindrical_cells_inline(points, sizes, &exact);
            assert_eq!(baseline, fast, "{grid:?}: baseline copy");
            #[cfg(target_arch = "x86_64")]
            #[allow(unsafe_code)]
            {
                if crate::sample::simd::has_avx2() {
                    // SAFETY: the CPU runs AVX2.
                    let avx2 = unsafe { super::cylindrical_cells_avx2(points, sizes, &exact) };
                    assert_eq!(avx2, fast, "{grid:?}: AVX2 copy");
                }
                if crate::sample::simd::has_avx512() {
                    // SAFETY: the CPU runs AVX-512 F and BW.
                    let avx512 = unsafe { super::cylindrical_cells_avx512(points, sizes, &exact) };
                    assert_eq!(avx512, fast, "{grid:?}: AVX-512 copy");
                }
            }
        }
    }

    #[test]
    fn floors_in_lanes_are_floor() {
        let mut state = 0x9E37_79B9u32;
        let mut values = vec![
            0.0f32,
            -0.0,
            0.5,
            -0.5,
            -1.0,
            2.999_999_8,
            -2.999_999_8,
            1e-30,
            -1e-30,
            4_194_303.5,
            -4_194_303.5,
            -4_194_303.7,
            4_194_303.9,
        ];
        for _ in 0..1_000_000 {
            state = state.wrapping_mul(1_664_525).wrapping_add(1_013_904_223);
            values.push(f32::from_bits(state));
            values.push((state as i32) as f32 / 1000.0);
        }
        for v in values {
            let (cell, small) = super::small_floor(v);
            assert_eq!(small, v.abs() < 4_194_304.0, "{v}");
            if small {
                assert_eq!(cell, v.floor() as i32, "{v}");
            }
            let q = v * 7.3;
            let (cell, clear) = super::clear_floor(q, 0.0);
            if clear {
                assert_eq!(cell, q.floor() as i32, "{q}");
            } else {
                assert!(q.is_nan() || q.abs() >= super::LARGE, "{q}");
            }
        }
    }

    #[test]
    fn arctangent_is_within_its_bound() {
        // Against the f64 arctangent of the same f32 inputs, all around and near the
        // octant edges (|x| = |y|) and the axes.
        let mut worst = 0f64;
        let mut check = |y: f32, x: f32| {
            let want = f64::from(y).atan2(f64::from(x));
            worst = worst.max((f64::from(super::atan2(y, x)) - want).abs());
        };
        for i in 0..400_000 {
            let a = -PI + 2.0 * PI * f64::from(i) / 400_000.0;
            check((a.sin() * 37.0) as f32, (a.cos() * 37.0) as f32);
        }
        for v in [1e-30f32, 1e-3, 0.7, 1.0, 5.0, 1e4] {
            for (sy, sx) in [(1.0, 1.0), (1.0, -1.0), (-1.0, 1.0), (-1.0, -1.0)] {
                for d in -4..=4 {
                    let w = f32::from_bits((v.to_bits() as i32 + d) as u32);
                    check(sy * v, sx * w);
                    check(sy * w, sx * v);
                    check(sy * v, 0.0);
                    check(0.0, sx * v);
                }
            }
        }
        assert!(worst < f64::from(super::ATAN_ERROR) / 4.0, "{worst}");
    }
    use std::f64::consts::PI;

    #[test]
    fn fast_cells_equal_the_formula_everywhere() {
        let grids = [
            VoxelGrid::default(),
            VoxelGrid::Cylindrical {
                rho_m: 0.05,
                phi_deg: 0.25,
                z_m: 0.2,
            },
            VoxelGrid::Cylindrical {
                rho_m: 0.3,
                phi_deg: 3.0,
                z_m: 0.1,
            },
        ];
        let mut state = 0x2545_F491_4F6C_DD1Du64;
        let mut next = move || {
            state ^= state << 13;
            state ^= state >> 7;
            state ^= state << 17;
            (state >> 11) as f64 / (1u64 << 53) as f64
        };
        let mut points: Vec<[f32; 3]> = Vec::new();
        // Random points from 1 cm to 200 m.
        for _ in 0..150_000 {
            let r = 200f64.powf(next() * 1.4 - 0.4);
            let a = (next() * 2.0 - 1.0) * PI;
            let z = (next() - 0.5) * 8.0;
            points.push([(r * a.cos()) as f32, (r * a.sin()) as f32, z as f32]);
        }
        // Points on and next to cell boundaries: ranges at multiples of 5 cm, azimuths
        // at multiples of 0.25°, and their f32 neighbours.
        for k in 1..4000 {
            let r = 0.05 * f64::from(k % 2000 + 1);
            let a = (0.25 * f64::from(k % 1440) - 180.0).to_radians();
            let (x, y) = ((r * a.cos()) as f32, (r * a.sin()) as f32);
            for (dx, dy) in [(0, 0), (1, 0), (-1, 0), (0, 1), (0, -1)] {
                let step = |v: f32, d: i32| f32::from_bits((v.to_bits() as i32 + d) as u32);
                points.push([step(x, dx), step(y, dy), 0.1 * (k % 7) as f32]);
            }
        }
        // Axes, signed zeros, the fold, far, non-finite.
        for p in [
            [0.0, 0.0, 0.0],
            [-0.0, 0.0, 0.0],
            [0.0, -0.0, 0.0],
            [-5.0, 0.0, 1.0],
            [-5.0, -0.0, 1.0],
            [-5.0, 1e-7, 1.0],
            [-5.0, -1e-7, 1.0],
            [5.0, 0.0, 0.0],
            [0.0, 5.0, 0.0],
            [0.0, -5.0, 0.0],
            [3e9, 1.0, 0.0],
            [-3e9, -3e9, 3e9],
            [f32::MAX, f32::MAX, 0.0],
            [f32::NAN, 1.0, 0.0],
            [1.0, f32::INFINITY, 0.0],
            [1.0, 1.0, f32::NEG_INFINITY],
        ] {
            points.push(p);
        }
        for grid in &grids {
            assert_same(grid, &points);
        }
    }
}
