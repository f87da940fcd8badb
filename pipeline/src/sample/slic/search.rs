//! SLIC's clustering: the assignment passes ([`Search`], pixels to the nearest centre
//! within its window, with a pruning bound that skips most of the window without
//! changing the result) and the centre update between them.

use super::Centre;
use super::lab::Lab;

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
pub(super) struct Search {
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
    pub(super) fn new(width: usize, height: usize, window: [f32; 2], weight: f32) -> Self {
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
    pub(super) fn assign(&mut self, lab: &Lab, centres: &[Centre], labels: &mut [u32]) {
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
pub(super) fn update_centres(
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
