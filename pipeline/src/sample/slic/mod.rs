//! SLIC superpixels (Achanta et al., 2012), the way SuperFlow and SLidR make them:
//! scikit-image's `slic(image, n_segments=150, compactness=6, sigma=3, start_label=0,
//! enforce_connectivity=True, min_size_factor=0.5, max_size_factor=3, convert2lab=True)`.
//!
//! The steps follow scikit-image (0.19 and later) so closely that the labels come out
//! identical to its on the test images (see `slic_matches_scikit_image_exactly`):
//!
//! 1. the image is stretched to `[0, 1]` by its global minimum and maximum (a no-op for an
//!    image that spans 0..255), converted to CIELAB (sRGB gamma, D65 white), and each Lab
//!    channel is smoothed by a Gaussian of `sigma` pixels (separable, truncated at 4 σ,
//!    `reflect` borders `d c b a | a b c d | d c b a`) — scikit-image smooths after the
//!    conversion, not before;
//! 2. cluster centres start on scikit-image's `regular_grid` of about `n_segments` cells
//!    (step `S ≈ √(W·H / n_segments)`, rounded); the first assignment is the nearest grid
//!    centre (scikit-image starts the centre colours at zero, which makes its first pass
//!    purely spatial);
//! 3. each later pass gives every pixel within `±2S` of a centre (scikit-image's window;
//!    the paper's is `±S`) to the centre minimising `D² = d_lab² + (d_xy / S)² · m²`, `m`
//!    the compactness, the lowest index on ties, and moves the centres to the means of
//!    their pixels; the passes stop early at a fixed point (no label changed), which gives
//!    the same result as running them all;
//! 4. connectivity is enforced as scikit-image does: a raster scan grows 4-connected
//!    components breadth-first (at most `3 ·` the mean segment size, larger ones are
//!    split), a component smaller than `min_size_factor ·` the mean segment size takes the
//!    label of the last already-labelled neighbour its search met, and the labels come out
//!    dense, numbered in raster order of first appearance.
//!
//! Everything is single-threaded, `f32` and deterministic, and the labels are those of
//! the straightforward computation; only the work is cut:
//!
//! * a pass goes tile by tile (16 × 16 pixels) and tries a centre on a tile, or on a row
//!   of it, only when a lower bound of its distance (from the spatial terms and the Lab
//!   bounding box of the pixels) does not exceed the best distances found so far, the
//!   tile's previous centres first; a tile whose pixels all had one centre is skipped
//!   when that centre provably stays the nearest (see `search`);
//! * the centre sums walk four rows side by side, and the centres after the last pass
//!   are not computed (see `centres`);
//! * connectivity is worked out on runs of equal labels, breadth-first only where the
//!   order of the search matters (see `connectivity`);
//! * the whole computation is also compiled for AVX2 and for AVX-512, and the widest
//!   copy the CPU has runs (see `sample::simd`); its buffers are kept per thread from
//!   call to call.

mod centres;
mod connectivity;
mod lab;
mod search;
mod tiles;

#[cfg(target_arch = "x86_64")]
use crate::sample::simd;
use centres::{Centre, Means};
use connectivity::enforce_connectivity;
use lab::Lab;
use search::Search;
use serde::{Deserialize, Serialize};
use std::cell::RefCell;
use superflow_common::InvalidSetting;

/// scikit-image's `max_size_factor`: connected components are grown up to this many times
/// the mean segment size; larger ones are split.
const MAX_SIZE_FACTOR: f64 = 3.0;

/// Half-width of the search window around a centre, in grid steps (scikit-image's `2 S`).
const WINDOW_STEPS: f32 = 2.0;

/// Largest accepted `sigma`, pixels (the kernel and its cost grow with it).
const MAX_SIGMA: f32 = 100.0;

/// Largest `n_segments`: half the 16-bit ids a batch stores, so that the segments split
/// off while enforcing connectivity still fit.
pub const MAX_SEGMENTS: u32 = 32_768;

/// SLIC parameters (defaults = the paper's: 150 segments, compactness 6, sigma 3).
#[derive(Debug, Clone, Copy, PartialEq, Serialize, Deserialize)]
#[serde(default, deny_unknown_fields)]
pub struct SlicParams {
    /// Approximate number of segments (the initial grid has about this many cells).
    pub n_segments: u32,
    /// Balance of colour and space: larger is more compact (square) superpixels. It
    /// weighs the spatial term as `D² = d_lab² + (d_xy / S)² · compactness²`.
    pub compactness: f32,
    /// Standard deviation of the Gaussian smoothing (of the Lab image), pixels; 0 disables
    /// it.
    pub sigma: f32,
    /// Most assignment passes (scikit-image's `max_num_iter`), at least 1.
    pub max_iterations: u32,
    /// Components smaller than this fraction of the mean segment size are merged into a
    /// neighbour.
    pub min_size_factor: f32,
}

impl Default for SlicParams {
    fn default() -> Self {
        SlicParams {
            n_segments: 150,
            compactness: 6.0,
            sigma: 3.0,
            max_iterations: 10,
            min_size_factor: 0.5,
        }
    }
}

impl SlicParams {
    /// Checks the parameters: `n_segments` and `max_iterations` at least 1, `compactness`
    /// finite and positive, `sigma` in `[0, 100]`, `min_size_factor` in `[0, 3)`.
    /// The error names the parameter as `slic.<field>` (the caller adds its own prefix,
    /// e.g. `sample.`).
    pub fn validate(&self) -> Result<(), InvalidSetting> {
        if !(1..=MAX_SEGMENTS).contains(&self.n_segments) {
            return Err(InvalidSetting::new(
                "slic.n_segments",
                self.n_segments,
                format!(
                    "must be in 1..={MAX_SEGMENTS} (batches store 16-bit ids, and enforcing connectivity can split segments)"
                ),
            ));
        }
        if self.max_iterations == 0 {
            return Err(InvalidSetting::new(
                "slic.max_iterations",
                self.max_iterations,
                "must be at least 1",
            ));
        }
        if !(self.compactness.is_finite() && self.compactness > 0.0) {
            return Err(InvalidSetting::new(
                "slic.compactness",
                self.compactness,
                "must be finite and positive",
            ));
        }
        if !(self.sigma.is_finite() && (0.0..=MAX_SIGMA).contains(&self.sigma)) {
            return Err(InvalidSetting::new(
                "slic.sigma",
                self.sigma,
                format!("must be in [0, {MAX_SIGMA}] pixels"),
            ));
        }
        if !(self.min_size_factor.is_finite()
            && self.min_size_factor >= 0.0
            && f64::from(self.min_size_factor) < MAX_SIZE_FACTOR)
        {
            return Err(InvalidSetting::new(
                "slic.min_size_factor",
                self.min_size_factor,
                format!("must be in [0, {MAX_SIZE_FACTOR})"),
            ));
        }
        Ok(())
    }
}

/// A superpixel segmentation.
#[derive(Debug, Clone, PartialEq, Eq)]
pub struct Segmentation {
    /// One label per pixel, row-major; the labels are dense in `0..count`, numbered in
    /// raster order of first appearance, and every segment is 4-connected.
    pub labels: Vec<u32>,
    /// Number of segments.
    pub count: u32,
}

/// Segments an interleaved RGB8 image (`rgb.len() == 3 * width * height`, row-major).
/// Returns one label per pixel (row-major), labels dense in 0..count, and count.
///
/// An empty image (`width` or `height` 0) gives no labels and `count` 0; any other image
/// gets at least one segment. Parameters are not validated here (see
/// [`SlicParams::validate`]); out-of-range values are clamped: `n_segments` 0 counts as 1,
/// a non-finite or negative `compactness` as the default, a `sigma` that is not in
/// `(0, 100]` as no smoothing (or 100), `max_iterations` 0 as 1 (the spatial grid).
///
/// # Panics
///
/// If `rgb.len() != 3 * width * height`.
#[allow(unsafe_code)]
pub fn slic(rgb: &[u8], width: usize, height: usize, params: &SlicParams) -> Segmentation {
    #[cfg(target_arch = "x86_64")]
    if simd::has_avx512() {
        // SAFETY: the CPU runs AVX-512 F and BW (checked just above), the only
        // requirement of calling a function compiled with them enabled.
        return unsafe { slic_avx512(rgb, width, height, params) };
    }
    #[cfg(target_arch = "x86_64")]
    if simd::has_avx2() {
        // SAFETY: the CPU runs AVX2 (checked just above), the only requirement of calling
        // a function compiled with it enabled.
        return unsafe { slic_avx2(rgb, width, height, params) };
    }
    slic_inline(rgb, width, height, params)
}

/// [`slic`] compiled with AVX2 enabled (see `sample::simd`).
#[cfg(target_arch = "x86_64")]
#[target_feature(enable = "avx2")]
fn slic_avx2(rgb: &[u8], width: usize, height: usize, params: &SlicParams) -> Segmentation {
    slic_inline(rgb, width, height, params)
}

/// [`slic`] compiled with AVX-512 enabled (sixteen lanes; the same operations, so the
/// same labels).
#[cfg(target_arch = "x86_64")]
#[target_feature(enable = "avx512f,avx512bw,avx2")]
fn slic_avx512(rgb: &[u8], width: usize, height: usize, params: &SlicParams) -> Segmentation {
    slic_inline(rgb, width, height, params)
}

/// [`slic`], inlined into each compiled copy (as are the functions it calls that matter
/// for speed).
#[inline(always)]
fn slic_inline(rgb: &[u8], width: usize, height: usize, params: &SlicParams) -> Segmentation {
    let n = width.checked_mul(height);
    assert!(
        n.and_then(|n| n.checked_mul(3)) == Some(rgb.len()),
        "slic: rgb has {} bytes, expected 3 * {width} * {height}",
        rgb.len()
    );
    if n == Some(0) {
        return Segmentation {
            labels: Vec::new(),
            count: 0,
        };
    }
    let mut scratch = SCRATCH.try_with(RefCell::take).unwrap_or_default();
    let segmentation = segment(&mut scratch, rgb, [width, height], params);
    // Only fails while the thread is being torn down, when the buffers are not needed.
    let _ = SCRATCH.try_with(|kept| kept.replace(scratch));
    segmentation
}

/// Buffers kept from call to call on each thread: a 448×224 image needs about 7 MB,
/// which would otherwise be allocated (and faulted in) anew every time.
#[derive(Debug, Default)]
struct Scratch {
    lab: Lab,
    labels: Vec<u32>,
    search: Search,
    means: Means,
    components: connectivity::Scratch,
}

thread_local! {
    static SCRATCH: RefCell<Scratch> = RefCell::new(Scratch::default());
}

/// The segmentation of a non-empty image (see [`slic`]).
#[inline(always)]
fn segment(
    scratch: &mut Scratch,
    rgb: &[u8],
    [width, height]: [usize; 2],
    params: &SlicParams,
) -> Segmentation {
    let n = width * height;
    let compactness = if params.compactness.is_finite() && params.compactness >= 0.0 {
        params.compactness
    } else {
        SlicParams::default().compactness
    };
    let sigma = if params.sigma.is_finite() && params.sigma > 0.0 {
        params.sigma.min(MAX_SIGMA)
    } else {
        0.0
    };
    let min_size_factor = if params.min_size_factor.is_finite() {
        f64::from(params.min_size_factor).max(0.0)
    } else {
        0.0
    };

    scratch.lab.compute(rgb, width, height, sigma);
    let grid = regular_grid(height, width, params.n_segments.max(1));
    let mut centres = initial_centres(grid, [width, height], &mut scratch.labels);
    if params.max_iterations > 1 {
        let [(_, step_y), (_, step_x)] = grid;
        let step = step_y.max(step_x) as f32;
        let weight = (compactness / step) * (compactness / step);
        let window = [WINDOW_STEPS * step_y as f32, WINDOW_STEPS * step_x as f32];
        let (lab, labels, search, means) = (
            &scratch.lab,
            &mut scratch.labels,
            &mut scratch.search,
            &mut scratch.means,
        );
        search.prepare(lab, labels, [width, height], window, weight);
        means.prepare(lab);
        means.update(width, (labels, width), &mut centres);
        for pass in 2..=params.max_iterations {
            // The centres after the last pass are not needed.
            if !search.assign(&centres) || pass == params.max_iterations {
                break;
            }
            means.update(width, search.labels(), &mut centres);
        }
        let (padded, stride) = search.labels();
        for (row, src) in labels
            .chunks_exact_mut(width)
            .zip(padded.chunks_exact(stride))
        {
            row.copy_from_slice(&src[..width]);
        }
    }

    // scikit-image's sizes, from the number of centres actually placed.
    let segment_size = n as f64 / centres.len() as f64;
    let min_size = (min_size_factor * segment_size) as usize;
    let max_size = ((MAX_SIZE_FACTOR * segment_size) as usize).max(1);
    let (labels, count) = enforce_connectivity(
        &scratch.labels,
        [width, height],
        [min_size, max_size],
        &mut scratch.components,
    );
    Segmentation { labels, count }
}

/// The centres on scikit-image's regular `grid` (`[(start, step)]` of the rows and the
/// columns), and the labels of scikit-image's first pass into `labels`: it starts every
/// centre colour at zero, so its first assignment is the nearest grid centre, which on a
/// regular grid is separable.
#[inline(always)]
fn initial_centres(
    [(start_y, step_y), (start_x, step_x)]: [(usize, usize); 2],
    [width, height]: [usize; 2],
    labels: &mut Vec<u32>,
) -> Vec<Centre> {
    let ys: Vec<usize> = (start_y..height).step_by(step_y).collect();
    let xs: Vec<usize> = (start_x..width).step_by(step_x).collect();
    let centres = ys
        .iter()
        .flat_map(|&y| {
            xs.iter().map(move |&x| Centre {
                y: y as f32,
                x: x as f32,
                lab: [0.0; 3],
            })
        })
        .collect();
    let near_y = nearest_on_grid(height, start_y, step_y, ys.len());
    let near_x = nearest_on_grid(width, start_x, step_x, xs.len());
    labels.resize(width * height, 0);
    for (row, &ky) in labels.chunks_exact_mut(width).zip(&near_y) {
        for (label, &kx) in row.iter_mut().zip(&near_x) {
            *label = ky * xs.len() as u32 + kx;
        }
    }
    centres
}

/// scikit-image's `regular_grid` for the shape `(1, height, width)` (its SLIC works on
/// 3-D volumes): the `(start, step)` of the rows and of the columns of the initial
/// centres. `height`, `width` and `n_points` are positive.
fn regular_grid(height: usize, width: usize, n_points: u32) -> [(usize, usize); 2] {
    let shape = [1.0, height as f64, width as f64];
    let n_points = f64::from(n_points);
    let space_size = shape.iter().product::<f64>();
    if space_size <= n_points {
        return [(0, 1), (0, 1)];
    }
    let mut order = [0usize, 1, 2];
    order.sort_by(|&a, &b| shape[a].total_cmp(&shape[b]));
    let sorted = order.map(|i| shape[i]);
    let mut steps = [(space_size / n_points).cbrt(); 3];
    if sorted.iter().zip(&steps).any(|(d, s)| d < s) {
        for dim in 0..2 {
            steps[dim] = sorted[dim];
            let rest = sorted[dim + 1..].iter().product::<f64>();
            let step = (rest / n_points).powf(1.0 / (2 - dim) as f64);
            for s in &mut steps[dim + 1..] {
                *s = step;
            }
            if sorted.iter().zip(&steps).all(|(d, s)| d >= s) {
                break;
            }
        }
    }
    let mut out = [(0, 1); 3];
    for (sorted_dim, &dim) in order.iter().enumerate() {
        let step = steps[sorted_dim];
        let len = shape[dim] as usize;
        let start = ((step / 2.0).floor() as usize).min(len.saturating_sub(1));
        out[dim] = (start, (step.round_ties_even() as usize).max(1));
    }
    [out[1], out[2]]
}

/// For each of `len` positions, the index of the nearest of the `count` grid points
/// `start + k * step` (the lower one on ties).
fn nearest_on_grid(len: usize, start: usize, step: usize, count: usize) -> Vec<u32> {
    let last = count.saturating_sub(1);
    (0..len)
        .map(|i| {
            let k = if i <= start {
                0
            } else {
                let (k, rem) = ((i - start) / step, (i - start) % step);
                if 2 * rem > step { k + 1 } else { k }
            };
            k.min(last) as u32
        })
        .collect()
}

#[cfg(test)]
mod tests;
