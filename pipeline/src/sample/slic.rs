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
//! Everything is single-threaded, `f32` and deterministic. A pass does not try every
//! centre on its whole window: a bound from each pixel's current centre lets most of the
//! window be skipped without changing the result (see `Search`).

use serde::{Deserialize, Serialize};

/// scikit-image's `max_size_factor`: connected components are grown up to this many times
/// the mean segment size; larger ones are split.
const MAX_SIZE_FACTOR: f64 = 3.0;

/// Gaussian kernels are truncated at this many standard deviations (SciPy's default).
const GAUSS_TRUNCATE: f32 = 4.0;

/// Half-width of the search window around a centre, in grid steps (scikit-image's `2 S`).
const WINDOW_STEPS: f32 = 2.0;

/// Largest accepted `sigma`, pixels (the kernel and its cost grow with it).
const MAX_SIGMA: f32 = 100.0;

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
    pub fn validate(&self) -> Result<(), String> {
        if self.n_segments == 0 {
            return Err("slic: n_segments must be at least 1".into());
        }
        if self.max_iterations == 0 {
            return Err("slic: max_iterations must be at least 1".into());
        }
        if !(self.compactness.is_finite() && self.compactness > 0.0) {
            return Err(format!(
                "slic: compactness must be finite and positive, got {}",
                self.compactness
            ));
        }
        if !(self.sigma.is_finite() && (0.0..=MAX_SIGMA).contains(&self.sigma)) {
            return Err(format!(
                "slic: sigma must be in [0, {MAX_SIGMA}] pixels, got {}",
                self.sigma
            ));
        }
        if !(self.min_size_factor.is_finite()
            && self.min_size_factor >= 0.0
            && f64::from(self.min_size_factor) < MAX_SIZE_FACTOR)
        {
            return Err(format!(
                "slic: min_size_factor must be in [0, {MAX_SIZE_FACTOR}), got {}",
                self.min_size_factor
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
pub fn slic(rgb: &[u8], width: usize, height: usize, params: &SlicParams) -> Segmentation {
    let n = width.checked_mul(height);
    assert!(
        n.and_then(|n| n.checked_mul(3)) == Some(rgb.len()),
        "slic: rgb has {} bytes, expected 3 * {width} * {height}",
        rgb.len()
    );
    let n = n.unwrap_or(0);
    if n == 0 {
        return Segmentation {
            labels: Vec::new(),
            count: 0,
        };
    }

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

    let lab = smoothed_lab(rgb, width, height, sigma);

    // Initial centres on scikit-image's regular grid.
    let [(start_y, step_y), (start_x, step_x)] =
        regular_grid(height, width, params.n_segments.max(1));
    let ys: Vec<usize> = (start_y..height).step_by(step_y).collect();
    let xs: Vec<usize> = (start_x..width).step_by(step_x).collect();
    let mut centres: Vec<Centre> = ys
        .iter()
        .flat_map(|&y| {
            xs.iter().map(move |&x| Centre {
                y: y as f32,
                x: x as f32,
                lab: [0.0; 3],
            })
        })
        .collect();

    // First pass: scikit-image starts every centre colour at zero, so its first
    // assignment is the nearest grid centre; on a regular grid that is separable.
    let near_y = nearest_on_grid(height, start_y, step_y, ys.len());
    let near_x = nearest_on_grid(width, start_x, step_x, xs.len());
    let mut labels = vec![0u32; n];
    for (row, &ky) in labels.chunks_exact_mut(width).zip(&near_y) {
        for (label, &kx) in row.iter_mut().zip(&near_x) {
            *label = ky * xs.len() as u32 + kx;
        }
    }

    if params.max_iterations > 1 {
        let step = step_y.max(step_x) as f32;
        let spatial_weight = (compactness / step) * (compactness / step);
        let window = [WINDOW_STEPS * step_y as f32, WINDOW_STEPS * step_x as f32];
        let mut search = Search::new(width, height, window, spatial_weight);
        let mut previous = vec![0u32; n];
        let mut sums = vec![[0f64; 6]; centres.len()];
        update_centres(&lab, width, &labels, &mut centres, &mut sums);
        for _ in 1..params.max_iterations {
            previous.copy_from_slice(&labels);
            search.assign(&lab, &centres, &mut labels);
            if labels == previous {
                break;
            }
            update_centres(&lab, width, &labels, &mut centres, &mut sums);
        }
    }

    // scikit-image's sizes, from the number of centres actually placed.
    let segment_size = n as f64 / centres.len() as f64;
    let min_size = (min_size_factor * segment_size) as usize;
    let max_size = ((MAX_SIZE_FACTOR * segment_size) as usize).max(1);
    let (labels, count) = enforce_connectivity(&labels, width, height, min_size, max_size);
    Segmentation { labels, count }
}

/// A cluster centre: position (row, column) and mean colour (CIELAB).
#[derive(Debug, Clone, Copy)]
struct Centre {
    y: f32,
    x: f32,
    lab: [f32; 3],
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

/// CIELAB planes of the (smoothed) image.
struct Lab {
    l: Vec<f32>,
    a: Vec<f32>,
    b: Vec<f32>,
}

/// scikit-image's pre-processing: the image is stretched to `[0, 1]` by its global
/// minimum and maximum (`image -= min; image /= max` over all channels; a no-op for
/// images spanning 0..255), converted to CIELAB, and each Lab plane is smoothed by a
/// Gaussian of `sigma` pixels (0: not at all).
fn smoothed_lab(rgb: &[u8], width: usize, height: usize, sigma: f32) -> Lab {
    let n = width * height;
    let lo = rgb.iter().copied().min().unwrap_or(0);
    let hi = rgb.iter().copied().max().unwrap_or(0);
    // sRGB-encoded byte → linear, after the stretch.
    let mut linear = [0f32; 256];
    for (v, lin) in linear.iter_mut().enumerate() {
        let c = if hi > lo {
            (v as f64 - f64::from(lo)) / f64::from(hi - lo)
        } else {
            0.0
        };
        *lin = if c > 0.04045 {
            ((c + 0.055) / 1.055).powf(2.4) as f32
        } else {
            (c / 12.92) as f32
        };
    }

    let mut lab = Lab {
        l: vec![0f32; n],
        a: vec![0f32; n],
        b: vec![0f32; n],
    };
    // sRGB (D65) → XYZ normalised by the D65 white (0.95047, 1, 1.08883), kept in the
    // planes for the moment.
    for (((px, x), y), z) in rgb
        .chunks_exact(3)
        .zip(&mut lab.l)
        .zip(&mut lab.a)
        .zip(&mut lab.b)
    {
        let (r, g, b) = (
            linear[usize::from(px[0])],
            linear[usize::from(px[1])],
            linear[usize::from(px[2])],
        );
        *x = (0.412453 * r + 0.357580 * g + 0.180423 * b) * (1.0 / 0.95047);
        *y = 0.212671 * r + 0.715160 * g + 0.072169 * b;
        *z = (0.019334 * r + 0.119193 * g + 0.950227 * b) * (1.0 / 1.08883);
    }
    // XYZ → CIELAB.
    for ((l, a), b) in lab.l.iter_mut().zip(&mut lab.a).zip(&mut lab.b) {
        let (fx, fy, fz) = (lab_f(*l), lab_f(*a), lab_f(*b));
        *l = 116.0 * fy - 16.0;
        *a = 500.0 * (fx - fy);
        *b = 200.0 * (fy - fz);
    }

    if sigma > 0.0 {
        let kernel = gaussian_half_kernel(sigma);
        let mut scratch = vec![0f32; n];
        let mut pad = Vec::new();
        for plane in [&mut lab.l, &mut lab.a, &mut lab.b] {
            blur_rows(plane, &mut scratch, width, &kernel, &mut pad);
            blur_columns(&scratch, plane, width, height, &kernel);
        }
    }
    lab
}

/// CIELAB's `f(t)` as scikit-image has it: `∛t` above 0.008856, `7.787 t + 16/116` below
/// (`t ≥ 0`). The cube root is a bit-level estimate refined by two Halley steps (within an
/// ulp or two of `f32::cbrt`), written so that a loop over it vectorises.
#[inline(always)]
fn lab_f(t: f32) -> f32 {
    let t = t.max(0.0);
    // Estimate: divide the exponent by three (the classic `bits / 3 + magic`).
    let mut y = f32::from_bits(t.to_bits() / 3 + 0x2a51_37a0);
    for _ in 0..2 {
        let y3 = y * y * y;
        y *= (y3 + 2.0 * t) / (2.0 * y3 + t);
    }
    if t > 0.008856 {
        y
    } else {
        7.787 * t + 16.0 / 116.0
    }
}

/// The normalised Gaussian of `sigma` truncated at 4 σ (SciPy's `gaussian_filter1d`),
/// from its centre outwards: `k[0]` is the centre tap, `k[j]` the taps at `±j`.
fn gaussian_half_kernel(sigma: f32) -> Vec<f32> {
    let radius = (GAUSS_TRUNCATE * sigma + 0.5) as usize;
    let sigma = f64::from(sigma);
    let taps: Vec<f64> = (0..=radius)
        .map(|j| (-0.5 * (j as f64 / sigma).powi(2)).exp())
        .collect();
    let total = taps.first().copied().unwrap_or(1.0) + 2.0 * taps.iter().skip(1).sum::<f64>();
    taps.iter().map(|t| (t / total) as f32).collect()
}

/// SciPy's `reflect` border: index `i` of an infinite `d c b a | a b c d | d c b a` line
/// over `len > 0` samples.
fn reflect(i: isize, len: usize) -> usize {
    let len = len as isize;
    let m = i.rem_euclid(2 * len);
    (if m < len { m } else { 2 * len - 1 - m }) as usize
}

/// Convolves every row of `src` with the symmetric `kernel` into `dst`.
fn blur_rows(src: &[f32], dst: &mut [f32], width: usize, kernel: &[f32], pad: &mut Vec<f32>) {
    let radius = kernel.len() - 1;
    let k0 = kernel.first().copied().unwrap_or(1.0);
    let index: Vec<usize> = (0..width + 2 * radius)
        .map(|i| reflect(i as isize - radius as isize, width))
        .collect();
    pad.resize(index.len(), 0.0);
    for (src, dst) in src.chunks_exact(width).zip(dst.chunks_exact_mut(width)) {
        for (p, &i) in pad.iter_mut().zip(&index) {
            *p = src[i];
        }
        for (d, &p) in dst.iter_mut().zip(&pad[radius..radius + width]) {
            *d = k0 * p;
        }
        for (j, &k) in kernel.iter().enumerate().skip(1) {
            let left = &pad[radius - j..radius - j + width];
            let right = &pad[radius + j..radius + j + width];
            for ((d, &a), &b) in dst.iter_mut().zip(left).zip(right) {
                *d += k * (a + b);
            }
        }
    }
}

/// Convolves every column of `src` with the symmetric `kernel` into `dst`.
fn blur_columns(src: &[f32], dst: &mut [f32], width: usize, height: usize, kernel: &[f32]) {
    let k0 = kernel.first().copied().unwrap_or(1.0);
    let row = |y: usize| &src[y * width..(y + 1) * width];
    for (y, dst) in dst.chunks_exact_mut(width).enumerate() {
        for (d, &p) in dst.iter_mut().zip(row(y)) {
            *d = k0 * p;
        }
        for (j, &k) in kernel.iter().enumerate().skip(1) {
            let above = row(reflect(y as isize - j as isize, height));
            let below = row(reflect((y + j) as isize, height));
            for ((d, &a), &b) in dst.iter_mut().zip(above).zip(below) {
                *d += k * (a + b);
            }
        }
    }
}

/// Pixels per row chunk of the search's pruning bound.
const CHUNK: usize = 8;

/// The assignment passes and their scratch.
///
/// A pass gives every pixel within the window of a centre to the centre of least
/// `d_lab² + weight · d_xy²`, the lowest index on ties (scikit-image visits the centres in
/// order and keeps strictly better ones); pixels that no window reaches keep their label.
/// The result is that of trying every centre on its whole window, but most of the work is
/// skipped: each pixel's distance to its current centre bounds its best distance, and a
/// centre skips the chunks of a row where its spatial term alone exceeds that bound.
struct Search {
    width: usize,
    height: usize,
    /// Half-sizes of the search window (rows, columns): scikit-image's `2 S`.
    window: [f32; 2],
    /// `(compactness / S)²`.
    weight: f32,
    /// Each centre's window this pass: rows `y0..y1`, columns `x0..x1`.
    windows: Vec<[usize; 4]>,
    /// Best distance of each pixel so far in the pass (also the seed distances).
    distance: Vec<f32>,
    /// The largest seed distance over each chunk of `CHUNK` pixels of a row.
    bound: Vec<f32>,
    chunks_per_row: usize,
    /// The column indices as `f32`.
    columns: Vec<f32>,
    /// `weight · dx²` over the current window's columns.
    dx2: Vec<f32>,
    /// The least of `dx2` over each chunk of the current window.
    near: Vec<f32>,
}

impl Search {
    fn new(width: usize, height: usize, window: [f32; 2], weight: f32) -> Self {
        let chunks_per_row = width.div_ceil(CHUNK);
        Search {
            width,
            height,
            window,
            weight,
            windows: Vec::new(),
            distance: vec![f32::INFINITY; width * height],
            bound: vec![f32::INFINITY; chunks_per_row * height],
            chunks_per_row,
            columns: (0..width).map(|x| x as f32).collect(),
            dx2: Vec::new(),
            near: Vec::new(),
        }
    }

    /// One assignment pass (see [`Search`]).
    fn assign(&mut self, lab: &Lab, centres: &[Centre], labels: &mut [u32]) {
        // scikit-image's window: [max(c - 2S, 0), min(c + 2S + 1, len)), truncated.
        let ([ry, rx], (w, h)) = (self.window, (self.width as f32, self.height as f32));
        self.windows.clear();
        self.windows.extend(centres.iter().map(|c| {
            [
                (c.y - ry).max(0.0) as usize,
                (c.y + ry + 1.0).min(h) as usize,
                (c.x - rx).max(0.0) as usize,
                (c.x + rx + 1.0).min(w) as usize,
            ]
        }));
        self.seed(lab, centres, labels);
        self.search(lab, centres, labels);
    }

    /// Bounds every chunk by the largest distance of its pixels to their current centres
    /// (infinite where a pixel is outside its centre's window).
    fn seed(&mut self, lab: &Lab, centres: &[Centre], labels: &[u32]) {
        let width = self.width;
        for (y, (((row, distance), bound), span)) in labels
            .chunks_exact(width)
            .zip(self.distance.chunks_exact_mut(width))
            .zip(self.bound.chunks_exact_mut(self.chunks_per_row))
            .zip((0..).step_by(width))
            .enumerate()
        {
            distance.fill(f32::INFINITY);
            let mut x = 0;
            while let Some(&k) = row.get(x) {
                let end = row[x..]
                    .iter()
                    .position(|&l| l != k)
                    .map_or(width, |p| x + p);
                if let (Some(c), Some(&[y0, y1, x0, x1])) =
                    (centres.get(k as usize), self.windows.get(k as usize))
                {
                    let a = x.max(x0).min(end);
                    let b = end.min(x1).max(a);
                    if (y0..y1).contains(&y) && a < b {
                        let pixels = span + a..span + b;
                        seed_span(
                            &mut distance[a..b],
                            [
                                &lab.l[pixels.clone()],
                                &lab.a[pixels.clone()],
                                &lab.b[pixels],
                            ],
                            &self.columns[a..b],
                            spatial(self.weight, c.y - y as f32),
                            self.weight,
                            c,
                        );
                    }
                }
                x = end;
            }
            for (m, chunk) in bound.iter_mut().zip(distance.chunks(CHUNK)) {
                *m = largest(chunk);
            }
        }
    }

    /// The pass proper: the centres in order, each on the chunks it may win.
    fn search(&mut self, lab: &Lab, centres: &[Centre], labels: &mut [u32]) {
        let width = self.width;
        self.distance.fill(f32::INFINITY);
        let (mut dx2, mut near) = (
            std::mem::take(&mut self.dx2),
            std::mem::take(&mut self.near),
        );
        for ((k, c), &[y0, y1, x0, x1]) in (0u32..).zip(centres).zip(&self.windows) {
            if x0 >= x1 {
                continue;
            }
            dx2.clear();
            dx2.extend(
                self.columns[x0..x1]
                    .iter()
                    .map(|&x| spatial(self.weight, x - c.x)),
            );
            // Chunks c0.. meet the window's columns; `near[j]` is the least spatial term
            // over chunk c0 + j's part of them: at its column nearest the centre (the
            // terms grow with the distance, rounding included).
            let c0 = x0 / CHUNK;
            near.clear();
            near.extend((c0..=(x1 - 1) / CHUNK).map(|chunk| {
                let a = (chunk * CHUNK).max(x0);
                let b = ((chunk + 1) * CHUNK).min(x1);
                if c.x < a as f32 {
                    dx2[a - x0]
                } else if c.x > (b - 1) as f32 {
                    dx2[b - 1 - x0]
                } else {
                    0.0
                }
            }));
            for y in y0..y1 {
                let dy2 = spatial(self.weight, c.y - y as f32);
                let bound = &self.bound[y * self.chunks_per_row + c0..][..near.len()];
                // The centre can only win pixels in chunks whose least spatial term is
                // not above their bound; the hull of those is searched.
                let may_win = |j: &usize| dy2 + near[*j] <= bound[*j];
                let Some(first) = (0..near.len()).find(may_win) else {
                    continue;
                };
                let last = (first..near.len()).rev().find(may_win).unwrap_or(first);
                let a = ((c0 + first) * CHUNK).max(x0);
                let b = ((c0 + last + 1) * CHUNK).min(x1);
                let pixels = y * width + a..y * width + b;
                search_span(
                    &mut self.distance[pixels.clone()],
                    &mut labels[pixels.clone()],
                    [
                        &lab.l[pixels.clone()],
                        &lab.a[pixels.clone()],
                        &lab.b[pixels],
                    ],
                    &dx2[a - x0..b - x0],
                    dy2,
                    c.lab,
                    k,
                );
            }
        }
        (self.dx2, self.near) = (dx2, near);
    }
}

/// Distances of a span of a row to centre `c` (its row's spatial term `dy2`).
#[inline(always)]
fn seed_span(
    distance: &mut [f32],
    [l, a, b]: [&[f32]; 3],
    columns: &[f32],
    dy2: f32,
    weight: f32,
    c: &Centre,
) {
    let n = distance.len();
    let (l, a, b, columns) = (&l[..n], &a[..n], &b[..n], &columns[..n]);
    for i in 0..n {
        let dx2 = spatial(weight, columns[i] - c.x);
        distance[i] = colour_distance(l[i], a[i], b[i], c.lab) + (dy2 + dx2);
    }
}

/// Offers centre `k` (colour `lab`, spatial terms `dy2` and `dx2`) to a span of a row:
/// the pixels it is strictly closer to take its label. Plain indexing over equal-length
/// slices and a branch-free blend keep the loop vectorised.
#[inline(always)]
fn search_span(
    distance: &mut [f32],
    labels: &mut [u32],
    [l, a, b]: [&[f32]; 3],
    dx2: &[f32],
    dy2: f32,
    lab: [f32; 3],
    k: u32,
) {
    let n = distance.len();
    let (labels, l, a, b, dx2) = (&mut labels[..n], &l[..n], &a[..n], &b[..n], &dx2[..n]);
    for i in 0..n {
        let dist = colour_distance(l[i], a[i], b[i], lab) + (dy2 + dx2[i]);
        let mask = u32::from(dist < distance[i]).wrapping_neg();
        distance[i] = f32::from_bits((distance[i].to_bits() & !mask) | (dist.to_bits() & mask));
        labels[i] = (labels[i] & !mask) | (k & mask);
    }
}

/// The largest of (non-NaN, non-negative) `values`; 0 for none. A full chunk is reduced
/// as a tree, which is several times faster than a serial fold.
#[inline(always)]
fn largest(values: &[f32]) -> f32 {
    let max = |a: f32, b: f32| if a > b { a } else { b };
    values.iter().fold(0.0, |m, &v| max(v, m))
}

/// `weight · d²` for a coordinate difference `d`: the spatial term of one axis.
#[inline(always)]
fn spatial(weight: f32, d: f32) -> f32 {
    weight * d * d
}

/// Squared CIELAB distance of a pixel to a centre colour.
#[inline(always)]
fn colour_distance(l: f32, a: f32, b: f32, c: [f32; 3]) -> f32 {
    let (dl, da, db) = (l - c[0], a - c[1], b - c[2]);
    dl * dl + da * da + db * db
}

/// Moves every centre to the mean position and colour of its pixels (a centre without
/// pixels stays where it is). `sums` is scratch, one entry per centre.
fn update_centres(
    lab: &Lab,
    width: usize,
    labels: &[u32],
    centres: &mut [Centre],
    sums: &mut [[f64; 6]],
) {
    sums.fill([0.0; 6]);
    for (y, row) in labels.chunks_exact(width).enumerate() {
        let span = y * width..(y + 1) * width;
        let (ls, as_, bs) = (&lab.l[span.clone()], &lab.a[span.clone()], &lab.b[span]);
        // Runs of equal labels along the row are summed in registers first.
        let mut flush = |k: u32, x0: usize, x1: usize, [l, a, b]: [f32; 3]| {
            if let Some(s) = sums.get_mut(k as usize) {
                let n = (x1 - x0) as f64;
                s[0] += n;
                s[1] += n * y as f64;
                s[2] += n * (x0 + x1 - 1) as f64 * 0.5;
                s[3] += f64::from(l);
                s[4] += f64::from(a);
                s[5] += f64::from(b);
            }
        };
        let (mut k, mut x0, mut acc) = (row.first().copied().unwrap_or(0), 0, [0f32; 3]);
        for (x, ((&label, &l), (&a, &b))) in row.iter().zip(ls).zip(as_.iter().zip(bs)).enumerate()
        {
            if label != k {
                flush(k, x0, x, acc);
                (k, x0, acc) = (label, x, [0.0; 3]);
            }
            acc = [acc[0] + l, acc[1] + a, acc[2] + b];
        }
        flush(k, x0, width, acc);
    }
    for (c, s) in centres.iter_mut().zip(sums.iter()) {
        if s[0] > 0.0 {
            let inv = 1.0 / s[0];
            *c = Centre {
                y: (s[1] * inv) as f32,
                x: (s[2] * inv) as f32,
                lab: [
                    (s[3] * inv) as f32,
                    (s[4] * inv) as f32,
                    (s[5] * inv) as f32,
                ],
            };
        }
    }
}

/// scikit-image's `_enforce_label_connectivity_cython` (2-D, 4-connectivity): a raster
/// scan grows each unlabelled pixel's component of equal SLIC label breadth-first, up to
/// `max_size` pixels; a component under `min_size` takes the label of the last
/// already-labelled neighbour met in the search, any other one gets the next new label.
/// Returns the dense labels (raster order of first appearance) and their count.
fn enforce_connectivity(
    labels: &[u32],
    width: usize,
    height: usize,
    min_size: usize,
    max_size: usize,
) -> (Vec<u32>, u32) {
    const UNSET: u32 = u32::MAX;
    let n = labels.len();
    let mut out = vec![UNSET; n];
    // The component being grown, as (column, row).
    let mut queue: Vec<(usize, usize)> = Vec::with_capacity(max_size.min(n));
    let mut next = 0u32;
    for start in 0..n {
        if out[start] != UNSET {
            continue;
        }
        let label = labels[start];
        out[start] = next;
        queue.clear();
        queue.push((start % width, start / width));
        let mut adjacent = None;
        let mut visited = 0;
        // scikit-image: `while bfs_visited < current_segment_size < max_size`.
        while queue.len() < max_size {
            let Some(&(x, y)) = queue.get(visited) else {
                break;
            };
            visited += 1;
            let p = y * width + x;
            // A neighbour of the same SLIC label joins the component; any other one that
            // already has a new label is remembered as adjacent. Returns whether the
            // component is full.
            let mut visit = |q: usize, nx: usize, ny: usize| {
                let seen = out[q];
                if seen == UNSET {
                    if labels[q] == label {
                        out[q] = next;
                        queue.push((nx, ny));
                        return queue.len() >= max_size;
                    }
                } else if seen != next {
                    adjacent = Some(seen);
                }
                false
            };
            // scikit-image's neighbour order: +x, -x, +y, -y.
            if (x + 1 < width && visit(p + 1, x + 1, y))
                || (x > 0 && visit(p - 1, x - 1, y))
                || (y + 1 < height && visit(p + width, x, y + 1))
                || (y > 0 && visit(p - width, x, y - 1))
            {
                break;
            }
        }
        if queue.len() < min_size {
            // Only a component holding the first pixel can have no labelled neighbour
            // (every later one touches the pixel before it in raster order); it keeps
            // the next label, which the following component then shares and extends.
            if let Some(adjacent) = adjacent {
                for &(x, y) in &queue {
                    out[y * width + x] = adjacent;
                }
            }
        } else {
            next += 1;
        }
    }
    // All small so far: the pixels hold the not-yet-counted label `next` (= 0).
    let count = if next == 0 { 1 } else { next };
    (out, count)
}

#[cfg(test)]
mod tests {
    use super::*;
    use std::time::Instant;

    const W: usize = 448;
    const H: usize = 224;

    /// Deterministic hash noise in `-amp..=amp`.
    fn noise(i: usize, c: usize, amp: i32) -> i32 {
        let mut h = (i as u64 * 3 + c as u64 + 1).wrapping_mul(0x9E37_79B9_7F4A_7C15);
        h ^= h >> 29;
        h = h.wrapping_mul(0xBF58_476D_1CE4_E5B9);
        h ^= h >> 32;
        (h % (2 * amp as u64 + 1)) as i32 - amp
    }

    const COLOURS: [[u8; 3]; 13] = [
        [220, 40, 40],
        [40, 200, 60],
        [40, 60, 220],
        [230, 220, 50],
        [200, 60, 200],
        [50, 200, 210],
        [250, 250, 250],
        [20, 20, 20],
        [240, 140, 30],
        [120, 60, 20],
        [130, 130, 130],
        [110, 180, 120],
        [150, 100, 250],
    ];

    /// A W×H image of `cols × rows` flat blocks of distinct colours and a diagonal stripe
    /// (`|x − 2y| < 24`), with ±8 noise: the true region of each pixel and the RGB8 image.
    fn blocks(cols: usize, rows: usize) -> (Vec<u32>, Vec<u8>) {
        let mut regions = vec![0u32; W * H];
        let mut rgb = vec![0u8; 3 * W * H];
        for y in 0..H {
            for x in 0..W {
                let i = y * W + x;
                let region = if (x as i64 - 2 * y as i64).abs() < 24 {
                    12
                } else {
                    x * cols / W + cols * (y * rows / H)
                };
                regions[i] = region as u32;
                for c in 0..3 {
                    let v = i32::from(COLOURS[region][c]) + noise(i, c, 8);
                    rgb[3 * i + c] = v.clamp(0, 255) as u8;
                }
            }
        }
        (regions, rgb)
    }

    /// A `width × height` patchwork of 11×9 cells of pseudo-random colours, ±12 noise.
    fn patchwork(width: usize, height: usize) -> Vec<u8> {
        let mut rgb = vec![0u8; 3 * width * height];
        for y in 0..height {
            for x in 0..width {
                let (i, cell) = (y * width + x, (y / 9) * 1000 + x / 11);
                for c in 0..3 {
                    let base = 128 + noise(cell + 7, c, 110);
                    rgb[3 * i + c] = (base + noise(i, c, 12)).clamp(0, 255) as u8;
                }
            }
        }
        rgb
    }

    /// FNV-1a over the labels' little-endian bytes.
    fn fnv(labels: &[u32]) -> u64 {
        let mut h = 0xcbf2_9ce4_8422_2325u64;
        for b in labels.iter().flat_map(|l| l.to_le_bytes()) {
            h = (h ^ u64::from(b)).wrapping_mul(0x0000_0100_0000_01b3);
        }
        h
    }

    /// Pixels whose right or lower neighbour has another value.
    fn boundaries(map: &[u32], width: usize, height: usize) -> Vec<bool> {
        let mut out = vec![false; map.len()];
        for y in 0..height {
            for x in 0..width {
                let i = y * width + x;
                out[i] = (x + 1 < width && map[i + 1] != map[i])
                    || (y + 1 < height && map[i + width] != map[i]);
            }
        }
        out
    }

    /// Asserts dense labels in raster order of first appearance and 4-connected segments.
    fn check_dense_and_connected(seg: &Segmentation, width: usize, height: usize) {
        assert_eq!(seg.labels.len(), width * height);
        let count = seg.count as usize;
        let mut next = 0;
        let mut size = vec![0usize; count];
        for &l in &seg.labels {
            let l = l as usize;
            assert!(l < count, "label {l} >= count {count}");
            if size[l] == 0 {
                assert_eq!(l, next, "labels not in raster order of first appearance");
                next += 1;
            }
            size[l] += 1;
        }
        assert_eq!(next, count, "labels are not dense");
        // A flood fill from each segment's first pixel reaches all of it.
        let mut reached = vec![false; seg.labels.len()];
        let mut stack = Vec::new();
        for start in 0..seg.labels.len() {
            if reached[start] {
                continue;
            }
            let l = seg.labels[start];
            let mut filled = 0;
            reached[start] = true;
            stack.push(start);
            while let Some(p) = stack.pop() {
                filled += 1;
                let (y, x) = (p / width, p % width);
                let neighbours = [
                    (x + 1 < width).then(|| p + 1),
                    (x > 0).then(|| p - 1),
                    (y + 1 < height).then(|| p + width),
                    (y > 0).then(|| p - width),
                ];
                for q in neighbours.into_iter().flatten() {
                    if !reached[q] && seg.labels[q] == l {
                        reached[q] = true;
                        stack.push(q);
                    }
                }
            }
            assert_eq!(filled, size[l as usize], "segment {l} is not 4-connected");
        }
    }

    #[test]
    fn slic_params_default_validate_and_deserialize() {
        let p = SlicParams::default();
        assert_eq!(
            (p.n_segments, p.compactness, p.sigma, p.max_iterations),
            (150, 6.0, 3.0, 10)
        );
        assert_eq!(p.min_size_factor, 0.5);
        p.validate().unwrap();
        for bad in [
            SlicParams { n_segments: 0, ..p },
            SlicParams {
                max_iterations: 0,
                ..p
            },
            SlicParams {
                compactness: 0.0,
                ..p
            },
            SlicParams {
                compactness: f32::NAN,
                ..p
            },
            SlicParams { sigma: -1.0, ..p },
            SlicParams {
                sigma: f32::INFINITY,
                ..p
            },
            SlicParams {
                min_size_factor: 3.0,
                ..p
            },
        ] {
            assert!(bad.validate().is_err(), "{bad:?}");
        }
        let q: SlicParams = serde_json::from_str(r#"{"n_segments": 100}"#).unwrap();
        assert_eq!(
            q,
            SlicParams {
                n_segments: 100,
                ..p
            }
        );
        assert!(serde_json::from_str::<SlicParams>(r#"{"segments": 100}"#).is_err());
    }

    #[test]
    fn slic_regular_grid_matches_scikit_image() {
        // 224×448, 150 segments: step √(100352/150) = 25.87 → start 12, step 26.
        assert_eq!(regular_grid(224, 448, 150), [(12, 26), (12, 26)]);
        assert_eq!(regular_grid(448, 224, 150), [(12, 26), (12, 26)]);
        // Fewer pixels than points: every pixel is a centre.
        assert_eq!(regular_grid(1, 1, 150), [(0, 1), (0, 1)]);
        assert_eq!(regular_grid(10, 10, 150), [(0, 1), (0, 1)]);
        // A thin strip: one row of centres.
        assert_eq!(regular_grid(3, 500, 150), [(1, 3), (1, 3)]);
        assert_eq!(regular_grid(500, 3, 150), [(1, 3), (1, 3)]);
        assert_eq!(nearest_on_grid(10, 1, 3, 3), [0, 0, 0, 1, 1, 1, 2, 2, 2, 2]);
        assert_eq!(nearest_on_grid(7, 1, 4, 2), [0, 0, 0, 0, 1, 1, 1]);
    }

    #[test]
    fn slic_reflect_and_kernel() {
        let idx: Vec<usize> = (-5..9).map(|i| reflect(i, 4)).collect();
        assert_eq!(idx, [3, 3, 2, 1, 0, 0, 1, 2, 3, 3, 2, 1, 0, 0]);
        assert!((-3..4).all(|i| reflect(i, 1) == 0));
        let k = gaussian_half_kernel(3.0);
        assert_eq!(k.len(), 13);
        let total = k[0] + 2.0 * k[1..].iter().sum::<f32>();
        assert!((total - 1.0).abs() < 1e-6);
    }

    #[test]
    fn slic_lab_f_is_close_to_the_cube_root() {
        let mut worst = 0f64;
        for i in 0..=100_000 {
            let t = i as f32 / 100_000.0;
            let exact = if f64::from(t) > 0.008856 {
                f64::from(t).cbrt()
            } else {
                7.787 * f64::from(t) + 16.0 / 116.0
            };
            worst = worst.max((f64::from(lab_f(t)) - exact).abs());
        }
        assert!(worst < 3e-7, "worst error {worst}");
    }

    #[test]
    fn slic_lab_matches_reference_values() {
        // scikit-image rgb2lab of pure colours (no smoothing); black and white are in the
        // image, so its [0, 1] stretch changes nothing.
        let cases: [([u8; 3], [f32; 3]); 5] = [
            ([255, 255, 255], [100.0, 0.0, 0.0]),
            ([0, 0, 0], [0.0, 0.0, 0.0]),
            ([255, 0, 0], [53.24, 80.09, 67.20]),
            ([0, 0, 255], [32.30, 79.19, -107.86]),
            ([128, 128, 128], [53.59, 0.0, 0.0]),
        ];
        let rgb: Vec<u8> = cases.iter().flat_map(|(rgb, _)| *rgb).collect();
        let lab = smoothed_lab(&rgb, cases.len(), 1, 0.0);
        for (i, (rgb, expected)) in cases.iter().enumerate() {
            let got = [lab.l[i], lab.a[i], lab.b[i]];
            for (g, e) in got.iter().zip(expected) {
                assert!((g - e).abs() < 0.01, "{rgb:?}: {got:?} vs {expected:?}");
            }
        }
        // The stretch: a dull image spans black to white after it.
        let lab = smoothed_lab(&[100, 100, 100, 150, 150, 150], 2, 1, 0.0);
        assert!(lab.l[0].abs() < 1e-3 && (lab.l[1] - 100.0).abs() < 1e-3);
        // A constant image is black.
        let lab = smoothed_lab(&[90; 6], 2, 1, 0.0);
        assert!(lab.l[0].abs() < 1e-3 && lab.l[1].abs() < 1e-3);
    }

    /// The golden cases: name, width, height, image, parameters.
    fn golden_cases() -> Vec<(&'static str, usize, usize, Vec<u8>, SlicParams)> {
        let p = SlicParams::default();
        vec![
            ("blocks 4x3", W, H, blocks(4, 3).1, p),
            ("blocks 2x2", W, H, blocks(2, 2).1, p),
            ("constant", W, H, vec![90; 3 * W * H], p),
            (
                "patchwork 97x61",
                97,
                61,
                patchwork(97, 61),
                SlicParams {
                    n_segments: 40,
                    compactness: 10.0,
                    sigma: 1.5,
                    max_iterations: 10,
                    min_size_factor: 0.3,
                },
            ),
            ("patchwork 61x97", 61, 97, patchwork(61, 97), p),
            ("patchwork 3x500", 500, 3, patchwork(500, 3), p),
        ]
    }

    /// scikit-image 0.26's labels for [`golden_cases`] (count, FNV-1a of the labels),
    /// from `skimage.segmentation.slic(rgb, n_segments, compactness, sigma,
    /// max_num_iter=max_iterations, min_size_factor=…, start_label=0)` (its defaults
    /// otherwise) on the same images written out as raw RGB8.
    const GOLDEN: [(u32, u64); 6] = [
        (85, 0x3a43_2130_7660_46fd),
        (103, 0x6f2b_5db1_c22c_cc6b),
        (153, 0x49f8_cef2_27ce_afc9),
        (55, 0x93a7_4440_2c1d_9330),
        (153, 0x942a_0b97_4fc6_34d5),
        (167, 0xe19c_116c_0b8b_7b18),
    ];

    #[test]
    fn slic_matches_scikit_image_exactly() {
        for ((name, w, h, rgb, params), (count, hash)) in golden_cases().into_iter().zip(GOLDEN) {
            let seg = slic(&rgb, w, h, &params);
            check_dense_and_connected(&seg, w, h);
            assert_eq!(
                (seg.count, fnv(&seg.labels)),
                (count, hash),
                "{name}: labels differ from scikit-image's"
            );
        }
    }

    #[test]
    fn slic_follows_edges_of_synthetic_image() {
        let (regions, rgb) = blocks(2, 2);
        let seg = slic(&rgb, W, H, &SlicParams::default());
        check_dense_and_connected(&seg, W, H);
        let count = seg.count;
        println!("slic: {count} segments on 2x2 blocks + stripe, {W}x{H} (asked 150)");
        assert!(
            (98..=202).contains(&count),
            "{count} segments, not within 35 % of 150"
        );

        // Boundary recall: true edge pixels with a segment boundary within `tol` px.
        let truth = boundaries(&regions, W, H);
        let found = boundaries(&seg.labels, W, H);
        let recall = |tol: usize| {
            let (mut edges, mut recalled) = (0usize, 0usize);
            for y in 0..H {
                for x in 0..W {
                    if truth[y * W + x] {
                        edges += 1;
                        let near = (y.saturating_sub(tol)..(y + tol + 1).min(H)).any(|yy| {
                            (x.saturating_sub(tol)..(x + tol + 1).min(W))
                                .any(|xx| found[yy * W + xx])
                        });
                        recalled += usize::from(near);
                    }
                }
            }
            recalled as f64 / edges as f64
        };
        // Undersegmentation: the share of each segment's pixels in its majority region.
        let mut hist = vec![[0usize; 13]; count as usize];
        for (&l, &r) in seg.labels.iter().zip(&regions) {
            hist[l as usize][r as usize] += 1;
        }
        let purity = hist
            .iter()
            .map(|h| *h.iter().max().unwrap() as f64 / h.iter().sum::<usize>() as f64)
            .sum::<f64>()
            / f64::from(count);
        let (r2, r3) = (recall(2), recall(3));
        println!(
            "slic: boundary recall {r2:.3} within 2 px, {r3:.3} within 3 px; purity {purity:.4}"
        );
        // scikit-image gives the same numbers: σ = 3 smoothing and compactness 6 leave thin
        // segments along the edges that the connectivity step merges into one side, so
        // boundaries sit up to 3 px off the true edges.
        assert!(r3 >= 0.90, "boundary recall {r3} within 3 px");
        assert!(purity >= 0.95, "purity {purity}");
    }

    #[test]
    fn slic_is_deterministic_and_timed() {
        let (_, rgb) = blocks(4, 3);
        let params = SlicParams::default();
        let first = slic(&rgb, W, H, &params);
        check_dense_and_connected(&first, W, H);
        let runs = if cfg!(debug_assertions) { 2 } else { 20 };
        let t = Instant::now();
        for _ in 0..runs {
            assert_eq!(slic(&rgb, W, H, &params), first);
        }
        let ms = t.elapsed().as_secs_f64() * 1e3 / f64::from(runs);
        println!(
            "slic: {ms:.2} ms per {W}x{H} image ({} segments; 4x3 blocks + stripe)",
            first.count
        );
    }

    #[test]
    fn slic_constant_image_is_a_grid() {
        let seg = slic(&vec![90u8; 3 * W * H], W, H, &SlicParams::default());
        check_dense_and_connected(&seg, W, H);
        // The 9 × 17 cells of scikit-image's regular_grid, each about a 26-px square.
        assert_eq!(seg.count, 153);
        let mut boxes = vec![[usize::MAX, usize::MAX, 0, 0]; seg.count as usize];
        let mut sizes = vec![0usize; seg.count as usize];
        for y in 0..H {
            for x in 0..W {
                let l = seg.labels[y * W + x] as usize;
                let b = &mut boxes[l];
                *b = [b[0].min(y), b[1].min(x), b[2].max(y), b[3].max(x)];
                sizes[l] += 1;
            }
        }
        for (b, &size) in boxes.iter().zip(&sizes) {
            let (h, w) = (b[2] - b[0] + 1, b[3] - b[1] + 1);
            assert!(h <= 32 && w <= 32, "box {h}x{w}");
            assert!(size * 10 >= h * w * 9, "size {size} in a {h}x{w} box");
        }
    }

    #[test]
    fn slic_degenerate_sizes_do_not_panic() {
        let p = SlicParams::default();
        let empty = slic(&[], 0, 0, &p);
        assert_eq!((empty.labels.len(), empty.count), (0, 0));
        assert_eq!(slic(&[], 0, 10, &p).count, 0);
        assert_eq!(slic(&[], 10, 0, &p).count, 0);
        let one = slic(&[1, 2, 3], 1, 1, &p);
        assert_eq!(
            one,
            Segmentation {
                labels: vec![0],
                count: 1
            }
        );
        let sizes = [
            (3, 500),
            (500, 3),
            (1, 700),
            (700, 1),
            (2, 2),
            (13, 9),
            (20, 20),
        ];
        for (w, h) in sizes {
            let rgb = patchwork(w, h);
            for params in [
                p,
                SlicParams { n_segments: 1, ..p },
                SlicParams {
                    n_segments: u32::MAX,
                    max_iterations: 2,
                    ..p
                },
                SlicParams {
                    n_segments: 0,
                    compactness: f32::NAN,
                    sigma: f32::INFINITY,
                    max_iterations: 0,
                    min_size_factor: f32::NAN,
                },
                SlicParams {
                    compactness: 0.0,
                    sigma: 0.0,
                    min_size_factor: 2.9,
                    ..p
                },
            ] {
                let seg = slic(&rgb, w, h, &params);
                assert!(seg.count >= 1, "{w}x{h} {params:?}");
                check_dense_and_connected(&seg, w, h);
            }
        }
    }
}
