//! SLIC's centre update: every centre moves to the mean position and colour of its
//! pixels.

use super::lab::Lab;

/// A cluster centre: position (row, column) and mean colour (CIELAB).
#[derive(Debug, Clone, Copy)]
pub(super) struct Centre {
    pub(super) y: f32,
    pub(super) x: f32,
    pub(super) lab: [f32; 3],
}

/// Rows summed side by side: their runs are independent, so interleaving them keeps
/// several additions in flight where one row alone waits on each.
const ROWS: usize = 4;

/// A run of equal labels along a row: label, first and one-past-last column, and the
/// `f32` sums of its L, a and b (added left to right; the fourth lane is padding).
type Run = (u32, usize, usize, [f32; 4]);

/// The centre update and its scratch.
#[derive(Debug, Default)]
pub(super) struct Means {
    /// Per centre: pixel count, sums of row, column, L, a and b.
    sums: Vec<[f64; 6]>,
    /// The runs of each of the rows being summed.
    runs: [Vec<Run>; ROWS],
    /// The image's L, a and b per pixel, and a padding lane (0).
    pixels: Vec<[f32; 4]>,
}

impl Means {
    /// Takes the pixels' colours from `lab` (the image's, for the following updates).
    #[inline(always)]
    pub(super) fn prepare(&mut self, lab: &Lab) {
        self.pixels.clear();
        self.pixels.extend(
            lab.l
                .iter()
                .zip(&lab.a)
                .zip(&lab.b)
                .map(|((&l, &a), &b)| [l, a, b, 0.0]),
        );
    }

    /// Moves every centre to the mean position and colour of its pixels (a centre without
    /// pixels stays where it is), given the labels of the `width`-pixel rows of the image
    /// of [`Means::prepare`] as rows of `stride` labels.
    ///
    /// Each run of equal labels along a row is summed in `f32` from left to right, and
    /// the runs are added to the centre's `f64` sums in raster order.
    #[inline(always)]
    pub(super) fn update(
        &mut self,
        width: usize,
        (labels, stride): (&[u32], usize),
        centres: &mut [Centre],
    ) {
        self.sums.clear();
        self.sums.resize(centres.len(), [0.0; 6]);
        let height = self.pixels.len() / width;
        for y0 in (0..height).step_by(ROWS) {
            let rows = y0..(y0 + ROWS).min(height);
            if rows.len() == ROWS {
                self.runs_of_rows(width, (labels, stride), y0);
            } else {
                for (r, y) in rows.clone().enumerate() {
                    let row = &labels[y * stride..][..width];
                    let pixels = &self.pixels[y * width..(y + 1) * width];
                    runs_of_row(row, pixels, &mut self.runs[r]);
                }
            }
            for (y, runs) in rows.zip(&self.runs) {
                for &(k, x0, x1, [l, a, b, _]) in runs {
                    if let Some(s) = self.sums.get_mut(k as usize) {
                        let n = (x1 - x0) as f64;
                        s[0] += n;
                        s[1] += n * y as f64;
                        s[2] += n * (x0 + x1 - 1) as f64 * 0.5;
                        s[3] += f64::from(l);
                        s[4] += f64::from(a);
                        s[5] += f64::from(b);
                    }
                }
            }
        }
        for (c, s) in centres.iter_mut().zip(&self.sums) {
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

    /// The runs of the `ROWS` rows from `y0`, walked side by side.
    #[inline(always)]
    fn runs_of_rows(&mut self, width: usize, (labels, stride): (&[u32], usize), y0: usize) {
        let span = |r: usize| (y0 + r) * width..(y0 + r + 1) * width;
        let labels: [&[u32]; ROWS] = std::array::from_fn(|r| &labels[(y0 + r) * stride..][..width]);
        let pixels: [&[[f32; 4]]; ROWS] = std::array::from_fn(|r| &self.pixels[span(r)]);
        let mut k: [u32; ROWS] = std::array::from_fn(|r| labels[r][0]);
        let mut start = [0usize; ROWS];
        let mut acc = [[0f32; 4]; ROWS];
        self.runs.iter_mut().for_each(Vec::clear);
        for x in 0..width {
            for r in 0..ROWS {
                let label = labels[r][x];
                if label != k[r] {
                    self.runs[r].push((k[r], start[r], x, acc[r]));
                    (k[r], start[r], acc[r]) = (label, x, [0.0; 4]);
                }
                acc[r] = add(acc[r], pixels[r][x]);
            }
        }
        for r in 0..ROWS {
            self.runs[r].push((k[r], start[r], width, acc[r]));
        }
    }
}

/// The runs of one row (`labels` and its pixels) into `runs`.
#[inline(always)]
fn runs_of_row(labels: &[u32], pixels: &[[f32; 4]], runs: &mut Vec<Run>) {
    runs.clear();
    let (mut k, mut start, mut acc) = (labels[0], 0, [0f32; 4]);
    for (x, (&label, &p)) in labels.iter().zip(pixels).enumerate() {
        if label != k {
            runs.push((k, start, x, acc));
            (k, start, acc) = (label, x, [0.0; 4]);
        }
        acc = add(acc, p);
    }
    runs.push((k, start, labels.len(), acc));
}

/// Lane-wise sum.
#[inline(always)]
fn add(a: [f32; 4], b: [f32; 4]) -> [f32; 4] {
    [a[0] + b[0], a[1] + b[1], a[2] + b[2], a[3] + b[3]]
}
