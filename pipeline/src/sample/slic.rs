//! SLIC superpixels (Achanta et al., 2012), the way SuperFlow and SLidR make them:
//! scikit-image's `slic(image, n_segments=150, compactness=6, sigma=3, start_label=0,
//! enforce_connectivity=True, min_size_factor=0.5, max_size_factor=3, convert2lab=True)`.
//!
//! The steps follow scikit-image:
//!
//! 1. each RGB channel (as `[0, 1]` floats) is smoothed by a Gaussian of `sigma` pixels
//!    (separable, truncated at 4 σ, `reflect` borders — `d c b a | a b c d | d c b a`);
//! 2. the smoothed image is converted to CIELAB (sRGB gamma, D65 white);
//! 3. cluster centres start on scikit-image's `regular_grid` of about `n_segments` cells
//!    (step `S ≈ √(W·H / n_segments)`); the first assignment is purely spatial (scikit-image
//!    starts the centre colours at zero, which makes its first pass spatial);
//! 4. each later iteration assigns every pixel within `±2S` of a centre (scikit-image's
//!    window) to the centre minimising `D² = d_lab² + (d_xy / S)² · m²`, `m` the
//!    compactness, and moves the centres to the means; it stops early when no label
//!    changes (a fixed point, so the result equals running all iterations);
//! 5. connectivity is enforced as scikit-image does: a raster scan grows 4-connected
//!    components (capped at `3 ·` the mean segment size), components smaller than
//!    `min_size_factor ·` the mean segment size join an already-labelled neighbour, and
//!    labels come out dense, numbered in raster order of first appearance.
//!
//! Everything is single-threaded, `f32` and deterministic.

use serde::{Deserialize, Serialize};
use std::sync::OnceLock;

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
    /// Standard deviation of the Gaussian pre-smoothing, pixels; 0 disables it.
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
/// `(0, 100]` as no smoothing (or 100), `max_iterations` 0 keeps the initial spatial grid.
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
        let columns: Vec<f32> = (0..width).map(|x| x as f32).collect();
        let mut distance = vec![f32::INFINITY; n];
        let mut previous = vec![0u32; n];
        let mut sums = vec![[0f64; 6]; centres.len()];
        update_centres(&lab, width, &labels, &mut centres, &mut sums);
        for _ in 1..params.max_iterations {
            previous.copy_from_slice(&labels);
            assign(
                &lab,
                width,
                height,
                &centres,
                window,
                spatial_weight,
                &columns,
                &mut distance,
                &mut labels,
            );
            if labels == previous {
                break;
            }
            update_centres(&lab, width, &labels, &mut centres, &mut sums);
        }
    }

    let segment_size = n as f64 / centres.len() as f64;
    let min_size = (min_size_factor * segment_size) as usize;
    let max_size = ((MAX_SIZE_FACTOR * segment_size) as usize).max(1);
    if std::env::var("SLIC_DEBUG").is_ok() { let mut sz = vec![0usize; centres.len()]; for &l in &labels { sz[l as usize]+=1; } let nonempty = sz.iter().filter(|&&s| s>0).count(); eprintln!("DEBUG clusters {} nonempty {} min {} max {} min_size {min_size} max_size {max_size}", centres.len(), nonempty, sz.iter().min().unwrap_or(&0), sz.iter().max().unwrap_or(&0)); }
    if std::env::var("SLIC_DEBUG").is_ok() { debug_dump("/tmp/pre.ppm", rgb, &labels, width, height); }
    let (labels, count) = enforce_connectivity(&labels, width, height, min_size, max_size);
    if std::env::var("SLIC_DEBUG").is_ok() { debug_dump("/tmp/post.ppm", rgb, &labels, width, height); }
    Segmentation { labels, count }
}


fn debug_dump(path: &str, rgb: &[u8], labels: &[u32], width: usize, height: usize) {
    use std::io::Write;
    let mut out = format!("P6\n{width} {height}\n255\n").into_bytes();
    for y in 0..height { for x in 0..width { let i = y*width+x; let b = (x+1<width && labels[i+1]!=labels[i]) || (y+1<height && labels[i+width]!=labels[i]);
        if b { out.extend_from_slice(&[0,0,0]); } else { out.extend_from_slice(&rgb[3*i..3*i+3]); } } }
    let _ = std::fs::File::create(path).and_then(|mut f| f.write_all(&out));
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

/// CIELAB planes of a smoothed image.
struct Lab {
    l: Vec<f32>,
    a: Vec<f32>,
    b: Vec<f32>,
}

/// Splits the RGB8 image into `[0, 1]` planes, smooths them by `sigma` (0: not at all) and
/// converts them to CIELAB.
fn smoothed_lab(rgb: &[u8], width: usize, height: usize, sigma: f32) -> Lab {
    let n = width * height;
    let mut planes = [vec![0f32; n], vec![0f32; n], vec![0f32; n]];
    {
        let [r, g, b] = &mut planes;
        for (((px, r), g), b) in rgb
            .chunks_exact(3)
            .zip(r.iter_mut())
            .zip(g.iter_mut())
            .zip(b.iter_mut())
        {
            *r = f32::from(px[0]) * (1.0 / 255.0);
            *g = f32::from(px[1]) * (1.0 / 255.0);
            *b = f32::from(px[2]) * (1.0 / 255.0);
        }
    }
    if sigma > 0.0 {
        let kernel = gaussian_half_kernel(sigma);
        let mut scratch = vec![0f32; n];
        let mut pad = Vec::new();
        for plane in &mut planes {
            blur_rows(plane, &mut scratch, width, &kernel, &mut pad);
            blur_columns(&scratch, plane, width, height, &kernel);
        }
    }

    let luts = luts();
    let [r, g, b] = &planes;
    let mut lab = Lab {
        l: vec![0f32; n],
        a: vec![0f32; n],
        b: vec![0f32; n],
    };
    for (i, (((&r, &g), &b), l)) in r.iter().zip(g).zip(b).zip(&mut lab.l).enumerate() {
        let (r, g, b) = (
            luts.linear(r),
            luts.linear(g),
            luts.linear(b),
        );
        // sRGB (D65) → XYZ, normalised by the D65 white (0.95047, 1, 1.08883).
        let x = (0.412453 * r + 0.357580 * g + 0.180423 * b) * (1.0 / 0.95047);
        let y = 0.212671 * r + 0.715160 * g + 0.072169 * b;
        let z = (0.019334 * r + 0.119193 * g + 0.950227 * b) * (1.0 / 1.08883);
        let (fx, fy, fz) = (luts.f(x), luts.f(y), luts.f(z));
        *l = 116.0 * fy - 16.0;
        lab.a[i] = 500.0 * (fx - fy);
        lab.b[i] = 200.0 * (fy - fz);
    }
    lab
}

/// Entries (minus one) of the colour look-up tables over `[0, 1]`.
const LUT_STEPS: usize = 4096;

/// Look-up tables (linearly interpolated) of the sRGB gamma expansion and of CIELAB's `f`.
struct Luts {
    gamma: Vec<f32>,
    f: Vec<f32>,
}

impl Luts {
    fn lookup(table: &[f32], t: f32) -> f32 {
        let s = t.clamp(0.0, 1.0) * LUT_STEPS as f32;
        let i = (s as usize).min(LUT_STEPS - 1);
        let frac = s - i as f32;
        match (table.get(i), table.get(i + 1)) {
            (Some(&lo), Some(&hi)) => lo + frac * (hi - lo),
            _ => 0.0,
        }
    }

    /// sRGB-encoded `[0, 1]` → linear.
    fn linear(&self, c: f32) -> f32 {
        Self::lookup(&self.gamma, c)
    }

    /// CIELAB's `f(t)`: `∛t` above 0.008856, `7.787 t + 16/116` below (scikit-image's).
    fn f(&self, t: f32) -> f32 {
        Self::lookup(&self.f, t)
    }
}

fn luts() -> &'static Luts {
    static LUTS: OnceLock<Luts> = OnceLock::new();
    LUTS.get_or_init(|| {
        let grid = || (0..=LUT_STEPS).map(|i| i as f64 / LUT_STEPS as f64);
        Luts {
            gamma: grid()
                .map(|c| {
                    if c > 0.04045 {
                        ((c + 0.055) / 1.055).powf(2.4) as f32
                    } else {
                        (c / 12.92) as f32
                    }
                })
                .collect(),
            f: grid()
                .map(|t| {
                    if t > 0.008856 {
                        t.cbrt() as f32
                    } else {
                        (7.787 * t + 16.0 / 116.0) as f32
                    }
                })
                .collect(),
        }
    })
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

/// One SLIC assignment pass: every pixel within the window of a centre goes to the
/// centre of least `d_lab² + spatial_weight · d_xy²` (the first such centre on ties);
/// pixels no window reaches keep their label.
#[allow(clippy::too_many_arguments)]
fn assign(
    lab: &Lab,
    width: usize,
    height: usize,
    centres: &[Centre],
    window: [f32; 2],
    spatial_weight: f32,
    columns: &[f32],
    distance: &mut [f32],
    labels: &mut [u32],
) {
    distance.fill(f32::INFINITY);
    for (k, c) in (0u32..).zip(centres) {
        // scikit-image's window: [max(c - 2S, 0), min(c + 2S + 1, len)), truncated.
        let y0 = (c.y - window[0]).max(0.0) as usize;
        let y1 = (c.y + window[0] + 1.0).min(height as f32) as usize;
        let x0 = (c.x - window[1]).max(0.0) as usize;
        let x1 = (c.x + window[1] + 1.0).min(width as f32) as usize;
        if x0 >= x1 {
            continue;
        }
        let [cl, ca, cb] = c.lab;
        let (cx, w) = (c.x, spatial_weight);
        let xs = &columns[x0..x1];
        for y in y0..y1 {
            let dy = c.y - y as f32;
            let dy2 = w * dy * dy;
            let span = y * width + x0..y * width + x1;
            let ls = &lab.l[span.clone()];
            let as_ = &lab.a[span.clone()];
            let bs = &lab.b[span.clone()];
            let ds = &mut distance[span.clone()];
            let ks = &mut labels[span];
            for (((((d, kk), &l), &a), &b), &x) in ds
                .iter_mut()
                .zip(ks.iter_mut())
                .zip(ls)
                .zip(as_)
                .zip(bs)
                .zip(xs)
            {
                let (dl, da, db, dx) = (l - cl, a - ca, b - cb, x - cx);
                let dist = dl * dl + da * da + db * db + (dy2 + w * dx * dx);
                let closer = dist < *d;
                *d = if closer { dist } else { *d };
                *kk = if closer { k } else { *kk };
            }
        }
    }
}

/// Moves every centre to the mean position and colour of its pixels (a centre without
/// pixels stays where it is).
fn update_centres(
    lab: &Lab,
    width: usize,
    labels: &[u32],
    centres: &mut [Centre],
    sums: &mut [[f64; 6]],
) {
    sums.fill([0.0; 6]);
    for (y, row) in labels.chunks_exact(width).enumerate() {
        let offset = y * width;
        for (x, &k) in row.iter().enumerate() {
            let i = offset + x;
            if let Some(s) = sums.get_mut(k as usize) {
                s[0] += 1.0;
                s[1] += y as f64;
                s[2] += x as f64;
                s[3] += f64::from(lab.l[i]);
                s[4] += f64::from(lab.a[i]);
                s[5] += f64::from(lab.b[i]);
            }
        }
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
    let mut queue: Vec<usize> = Vec::with_capacity(max_size.min(n));
    let mut next = 0u32;
    for start in 0..n {
        if out[start] != UNSET {
            continue;
        }
        let label = labels[start];
        out[start] = next;
        queue.clear();
        queue.push(start);
        let mut adjacent = None;
        let mut visited = 0;
        'grow: while visited < queue.len() && queue.len() < max_size {
            let p = queue[visited];
            let (y, x) = (p / width, p % width);
            // scikit-image's neighbour order: +x, -x, +y, -y.
            let neighbours = [
                (x + 1 < width).then(|| p + 1),
                (x > 0).then(|| p - 1),
                (y + 1 < height).then(|| p + width),
                (y > 0).then(|| p - width),
            ];
            for q in neighbours.into_iter().flatten() {
                if labels[q] == label && out[q] == UNSET {
                    out[q] = next;
                    queue.push(q);
                    if queue.len() >= max_size {
                        break 'grow;
                    }
                } else if out[q] != UNSET && out[q] != next {
                    adjacent = Some(out[q]);
                }
            }
            visited += 1;
        }
        if queue.len() < min_size {
            // Only a component holding the first pixel can have no labelled neighbour
            // (every later one touches the pixel before it in raster order); it keeps
            // the next label, which the following component then shares and extends.
            if let Some(adjacent) = adjacent {
                for &q in &queue {
                    out[q] = adjacent;
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

    /// 4×3 blocks of distinct colours plus a diagonal stripe: the true region of each
    /// pixel and the (noisy) RGB8 image.
    fn synthetic() -> (Vec<u32>, Vec<u8>) {
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
        let mut regions = vec![0u32; W * H];
        let mut rgb = vec![0u8; 3 * W * H];
        for y in 0..H {
            for x in 0..W {
                let i = y * W + x;
                let stripe = (x as i64 - 2 * y as i64).abs() < 24;
                let region = if stripe {
                    12
                } else {
                    (x * 4 / W + 4 * (y * 3 / H)) as u32
                };
                regions[i] = region;
                for c in 0..3 {
                    let v = i32::from(COLOURS[region as usize][c]) + noise(i, c, 8);
                    rgb[3 * i + c] = v.clamp(0, 255) as u8;
                }
            }
        }
        (regions, rgb)
    }

    /// Pixels whose right or lower neighbour has another value.
    fn boundaries(map: &[u32], width: usize, height: usize) -> Vec<bool> {
        let mut out = vec![false; map.len()];
        for y in 0..height {
            for x in 0..width {
                let i = y * width + x;
                if (x + 1 < width && map[i + 1] != map[i])
                    || (y + 1 < height && map[i + width] != map[i])
                {
                    out[i] = true;
                }
            }
        }
        out
    }

    fn check_dense_and_connected(seg: &Segmentation, width: usize, height: usize) {
        assert_eq!(seg.labels.len(), width * height);
        let count = seg.count as usize;
        // Dense and numbered in raster order of first appearance.
        let mut next = 0;
        let mut seen = vec![false; count];
        for &l in &seg.labels {
            let l = l as usize;
            assert!(l < count, "label {l} >= count {count}");
            if !seen[l] {
                assert_eq!(l, next, "labels not in raster order of first appearance");
                seen[l] = true;
                next += 1;
            }
        }
        assert_eq!(next, count, "labels are not dense");
        // 4-connected: a flood fill from each label's first pixel reaches all of it.
        let mut size = vec![0usize; count];
        for &l in &seg.labels {
            size[l as usize] += 1;
        }
        let mut reached = vec![false; seg.labels.len()];
        for start in 0..seg.labels.len() {
            if reached[start] {
                continue;
            }
            let l = seg.labels[start];
            let mut stack = vec![start];
            reached[start] = true;
            let mut filled = 0;
            while let Some(p) = stack.pop() {
                filled += 1;
                let (y, x) = (p / width, p % width);
                let mut visit = |q: usize| {
                    if !reached[q] && seg.labels[q] == l {
                        reached[q] = true;
                        stack.push(q);
                    }
                };
                if x + 1 < width {
                    visit(p + 1);
                }
                if x > 0 {
                    visit(p - 1);
                }
                if y + 1 < height {
                    visit(p + width);
                }
                if y > 0 {
                    visit(p - width);
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
            SlicParams {
                n_segments: 0,
                ..p
            },
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
    fn slic_lab_matches_reference_values() {
        // scikit-image rgb2lab of pure colours (no smoothing).
        let cases: [([u8; 3], [f32; 3]); 4] = [
            ([255, 255, 255], [100.0, 0.0, 0.0]),
            ([255, 0, 0], [53.24, 80.09, 67.20]),
            ([0, 0, 255], [32.30, 79.19, -107.86]),
            ([128, 128, 128], [53.59, 0.0, 0.0]),
        ];
        for (rgb, expected) in cases {
            let lab = smoothed_lab(&rgb, 1, 1, 0.0);
            let got = [lab.l[0], lab.a[0], lab.b[0]];
            for (g, e) in got.iter().zip(expected) {
                assert!((g - e).abs() < 0.05, "{rgb:?}: {got:?} vs {expected:?}");
            }
        }
    }

    #[test]
    fn slic_follows_edges_of_synthetic_image() {
        let (regions, rgb) = synthetic();
        let seg = slic(&rgb, W, H, &SlicParams::default());
        check_dense_and_connected(&seg, W, H);
        let count = seg.count;
        println!("slic: {count} segments on the synthetic {W}x{H} image (asked 150)");
        assert!((97..=202).contains(&count), "{count} segments");

        // Boundary recall: true edges with a segment boundary within 2 px.
        let truth = boundaries(&regions, W, H);
        let found = boundaries(&seg.labels, W, H);
        let (mut edges, mut recalled) = (0usize, 0usize);
        for y in 0..H {
            for x in 0..W {
                if !truth[y * W + x] {
                    continue;
                }
                edges += 1;
                let near = (y.saturating_sub(2)..(y + 3).min(H))
                    .any(|yy| (x.saturating_sub(2)..(x + 3).min(W)).any(|xx| found[yy * W + xx]));
                recalled += usize::from(near);
            }
        }
        let recall = recalled as f64 / edges as f64;

        // Purity: the share of each segment's pixels in its majority region.
        let mut hist = vec![[0usize; 13]; count as usize];
        for (&l, &r) in seg.labels.iter().zip(&regions) {
            hist[l as usize][r as usize] += 1;
        }
        let purity = hist
            .iter()
            .map(|h| {
                *h.iter().max().unwrap() as f64 / h.iter().sum::<usize>() as f64
            })
            .sum::<f64>()
            / f64::from(count);
        println!("slic: boundary recall {recall:.4} ({edges} edge px), purity {purity:.4}");
        assert!(recall >= 0.90, "boundary recall {recall}");
        assert!(purity >= 0.95, "purity {purity}");
    }

    #[test]
    fn slic_is_deterministic_and_timed() {
        let (_, rgb) = synthetic();
        let params = SlicParams::default();
        let first = slic(&rgb, W, H, &params);
        let runs = 20;
        let t = Instant::now();
        for _ in 0..runs {
            let again = slic(&rgb, W, H, &params);
            assert_eq!(again, first);
        }
        let ms = t.elapsed().as_secs_f64() * 1e3 / f64::from(runs);
        println!("slic: {ms:.2} ms per {W}x{H} image ({} segments)", first.count);
    }

    #[test]
    fn slic_constant_image_is_a_grid() {
        let rgb = vec![90u8; 3 * W * H];
        let seg = slic(&rgb, W, H, &SlicParams::default());
        check_dense_and_connected(&seg, W, H);
        println!("slic: {} segments on a constant image", seg.count);
        // The 9 × 17 grid of scikit-image's regular_grid.
        assert_eq!(seg.count, 153);
        // Compact: every segment fits in a box of about one grid step.
        let count = seg.count as usize;
        let mut boxes = vec![[usize::MAX, usize::MAX, 0, 0]; count];
        let mut sizes = vec![0usize; count];
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
            // Square-ish cells that fill most of their box.
            assert!(size * 10 >= h * w * 9, "size {size} in box {h}x{w}");
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
        assert_eq!(one, Segmentation { labels: vec![0], count: 1 });
        for (w, h) in [(3, 500), (500, 3), (1, 700), (700, 1), (2, 2), (13, 9), (20, 20)] {
            let rgb: Vec<u8> = (0..3 * w * h).map(|i| (i * 37 % 251) as u8).collect();
            for params in [
                p,
                SlicParams {
                    n_segments: 1,
                    ..p
                },
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
                assert!(seg.count >= 1);
                check_dense_and_connected(&seg, w, h);
            }
        }
    }
}
