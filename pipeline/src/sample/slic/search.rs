//! SLIC's assignment passes ([`Search`]): each pixel to the nearest centre within its
//! window, tile by tile, with lower bounds that skip most centres without changing the
//! result.

use super::centres::Centre;
use super::lab::Lab;
use super::tiles::{Band, TH, TW, Tiles, colour_gap, spatial};
use std::ops::Range;

/// The assignment passes, the labels and the scratch.
///
/// A pass gives every pixel within the window of a centre to the centre of least
/// `d_lab² + weight · d_xy²`, the lowest index on ties (scikit-image visits the centres in
/// order and keeps strictly better ones); pixels that no window reaches keep their label.
///
/// The result is that of trying every centre on its whole window, but the work goes tile
/// by tile (`TW × TH` pixels), keeping for each pixel the least `(distance, index)` so
/// far, which ends as scikit-image's winner whatever the order of the centres. A tile is
/// first offered to the centres its pixels had (whose distances are then a tight bound),
/// then to each other centre whose window meets it unless a lower bound of its distance
/// (from the spatial terms at the tile's nearest row and column, and the Lab bounding box
/// of the tile's pixels) exceeds every pixel's best distance so far: such a centre can
/// neither win nor tie. A row of a tile is likewise skipped when the bound on that row
/// (from the row's own Lab bounding box) exceeds the row's best distances. The bounds
/// are computed with the same `f32` operations as the distances, in the same order, on
/// operands that are no larger, so they never exceed a distance as computed (rounding is
/// monotone). A tile whose pixels all had one centre is skipped whole when that centre
/// provably stays the nearest (see [`Search::still_stable`]).
#[derive(Debug, Default)]
pub(super) struct Search {
    /// The image's tiles and their Lab bounding boxes.
    tiles: Tiles,
    /// The labels, row-major with `stride` (a multiple of `TW`) columns; the columns
    /// right of the image hold `u32::MAX`.
    labels: Vec<u32>,
    stride: usize,
    /// Half-sizes of the search window (rows, columns): scikit-image's `2 S`.
    window: [f32; 2],
    /// `(compactness / S)²`.
    weight: f32,
    /// Each centre's window this pass: rows `y0..y1`, columns `x0..x1`.
    windows: Vec<[usize; 4]>,
    /// The centres in order of their column (then index).
    order: Vec<u32>,
    /// The centres whose windows meet each band of `TH` rows (in `order`): band `b`'s
    /// are `members[band_starts[b]..band_starts[b + 1]]`.
    members: Vec<u32>,
    band_starts: Vec<usize>,
    /// The centres whose windows meet the current band of tile rows.
    band: Band,
    /// The current tile.
    tile: Tile,
    /// The centres of the previous pass.
    previous: Vec<Centre>,
    /// How far each centre moved since the previous pass, in the metric whose square is
    /// the distance (infinite in the first pass).
    drift: Vec<f64>,
    /// Per tile (row-major): the centre all its pixels had after the previous pass
    /// (`u32::MAX`: none) and an upper bound of their distances to it as computed.
    stable: Vec<(u32, f64)>,
}

/// The state of one tile during a pass: each pixel's best distance so far (its centre is
/// in the labels).
#[derive(Debug, Default)]
struct Tile {
    /// Rows of the image.
    rows: Range<usize>,
    /// First column.
    x0: usize,
    /// Columns in the image (`TW` but at the right edge).
    n: usize,
    /// The rows as `f32`.
    ys: [f32; TH],
    /// Best distance so far (0 right of the image: never beaten, never bounding).
    best: [[f32; TW]; TH],
    /// The largest `best` of each row (0 below the image).
    row_max: [f32; TH],
    /// Whether no centre has been offered to a row yet.
    fresh: [bool; TH],
    /// The best distance before any offer: infinite in the image, 0 right of it.
    pad: [f32; TW],
    /// Whether a label changed.
    changed: bool,
}

impl Search {
    /// Prepares the passes over `lab` (`width × height`, both positive) starting from
    /// `labels` (row-major), with the window half-sizes (rows, columns) and the spatial
    /// weight.
    #[inline(always)]
    pub(super) fn prepare(
        &mut self,
        lab: &Lab,
        labels: &[u32],
        [width, height]: [usize; 2],
        window: [f32; 2],
        weight: f32,
    ) {
        let stride = width.div_ceil(TW) * TW;
        self.labels.clear();
        self.labels.resize(stride * height, u32::MAX);
        for (dst, src) in self
            .labels
            .chunks_exact_mut(stride)
            .zip(labels.chunks_exact(width))
        {
            dst[..width].copy_from_slice(src);
        }
        self.tiles.prepare(lab, width, height);
        (self.stride, self.window, self.weight) = (stride, window, weight);
        self.previous.clear();
        self.stable.clear();
        let tiles = stride / TW * height.div_ceil(TH);
        self.stable.resize(tiles, (u32::MAX, f64::INFINITY));
    }

    /// The labels, row-major with the returned number of columns per row (the image's
    /// first).
    pub(super) fn labels(&self) -> (&[u32], usize) {
        (&self.labels, self.stride)
    }

    /// One assignment pass (see [`Search`]); returns whether any label changed.
    #[inline(always)]
    pub(super) fn assign(&mut self, centres: &[Centre]) -> bool {
        let (width, height) = (self.tiles.width, self.tiles.height);
        // scikit-image's window: [max(c - 2S, 0), min(c + 2S + 1, len)), truncated.
        let ([ry, rx], (w, h)) = (self.window, (width as f32, height as f32));
        self.windows.clear();
        self.windows.extend(centres.iter().map(|c| {
            [
                (c.y - ry).max(0.0) as usize,
                (c.y + ry + 1.0).min(h) as usize,
                (c.x - rx).max(0.0) as usize,
                (c.x + rx + 1.0).min(w) as usize,
            ]
        }));
        // Both window edges grow with the column, so in this order the windows meeting
        // a range of columns are consecutive.
        self.order.clear();
        self.order.extend(0..centres.len() as u32);
        self.order
            .sort_by(|&i, &j| centres[i as usize].x.total_cmp(&centres[j as usize].x));
        self.measure_drift(centres);
        self.sort_into_bands(height);
        let mut changed = false;
        for (b, y0) in (0..height).step_by(TH).enumerate() {
            let rows = y0..(y0 + TH).min(height);
            let members = &self.members[self.band_starts[b]..self.band_starts[b + 1]];
            self.band
                .gather(centres, &self.windows, members, rows.clone(), self.weight);
            changed |= self.band_pass(rows);
        }
        changed
    }

    /// Lists the centres whose windows meet each band of `TH` rows, in `order`.
    #[inline(always)]
    fn sort_into_bands(&mut self, height: usize) {
        let bands = height.div_ceil(TH);
        let windows = &self.windows;
        let band_range = |k: u32| {
            let [y0, y1, x0, x1] = windows[k as usize];
            if y0 < y1 && x0 < x1 {
                y0 / TH..(y1 - 1) / TH + 1
            } else {
                0..0
            }
        };
        let starts = &mut self.band_starts;
        starts.clear();
        starts.resize(bands + 2, 0);
        for &k in &self.order {
            for b in band_range(k) {
                starts[b + 2] += 1;
            }
        }
        for b in 2..starts.len() {
            starts[b] += starts[b - 1];
        }
        // starts[b + 1] is now where band b's list starts; filling moves it to its end.
        self.members.resize(starts[bands + 1], 0);
        for &k in &self.order {
            for b in band_range(k) {
                self.members[starts[b + 1]] = k;
                starts[b + 1] += 1;
            }
        }
    }

    /// Records how far each centre moved since the previous pass.
    #[inline(always)]
    fn measure_drift(&mut self, centres: &[Centre]) {
        self.drift.clear();
        if self.previous.len() == centres.len() {
            let w = f64::from(self.weight);
            let d = |a: f32, b: f32| (f64::from(a) - f64::from(b)).powi(2);
            self.drift
                .extend(centres.iter().zip(&self.previous).map(|(c, p)| {
                    let [l, a, b] = [0, 1, 2].map(|i| d(c.lab[i], p.lab[i]));
                    (l + a + b + w * (d(c.y, p.y) + d(c.x, p.x))).sqrt()
                }));
        } else {
            self.drift.resize(centres.len(), f64::INFINITY);
        }
        self.previous.clear();
        self.previous.extend_from_slice(centres);
    }

    /// The tiles of one band of rows, left to right; returns whether a label changed.
    #[inline(always)]
    fn band_pass(&mut self, rows: Range<usize>) -> bool {
        let width = self.tiles.width;
        let (mut lo, mut hi) = (0, 0);
        let mut changed = false;
        let first_tile = rows.start / TH * (self.stride / TW);
        for x0 in (0..width).step_by(TW) {
            let x1 = (x0 + TW).min(width);
            // The band's centres whose windows meet columns x0..x1.
            let band = &self.band;
            while hi < band.len() && (band.columns[hi][0] as usize) < x1 {
                hi += 1;
            }
            while lo < hi && band.columns[lo][1] as usize <= x0 {
                lo += 1;
            }
            let t = first_tile + x0 / TW;
            if lo == hi {
                self.stable[t] = (u32::MAX, f64::INFINITY);
                continue;
            }
            let colour = self.tiles.tile_box(rows.start, x0);
            self.band.bounds(lo..hi, x0..x1, colour, self.weight);
            if self.still_stable(t, rows.clone(), x0..x1, lo..hi) {
                continue;
            }
            self.tile.start(rows.clone(), x0..x1);
            let single = self.search_tile(lo..hi);
            changed |= self.tile.changed;
            self.stable[t] = match single {
                true => self.certificate(),
                false => (u32::MAX, f64::INFINITY),
            };
        }
        changed
    }

    /// Whether tile `t` (rows `rows`, columns `cols`) provably keeps the one label all its
    /// pixels had, given the bounds of the band's centres `active` on it; if so, updates
    /// its certificate.
    ///
    /// Its pixels were at most `√u` from their centre `k`, which has since moved by `δ`,
    /// so they are now at most `√u + δ` from it (the triangle inequality in the metric
    /// whose square is the distance); when that bound, with a margin for the rounding of
    /// the distances as computed, is below every other centre's lower bound, `k` stays
    /// strictly nearest for all of them.
    #[inline(always)]
    fn still_stable(
        &mut self,
        t: usize,
        rows: Range<usize>,
        cols: Range<usize>,
        active: Range<usize>,
    ) -> bool {
        /// Relative margin for the rounding of distances as computed (a few ulps).
        const MARGIN: f64 = 1e-5;
        let (k, u) = self.stable[t];
        let Some(&[y0, y1, x0, x1]) = self.windows.get(k as usize) else {
            return false;
        };
        if !(y0 <= rows.start && rows.end <= y1 && x0 <= cols.start && cols.end <= x1) {
            return false;
        }
        let grown = (u * (1.0 + MARGIN)).sqrt() + self.drift[k as usize];
        let u = grown * grown * (1.0 + MARGIN);
        let slot = self.band.slot[k as usize] as usize;
        let others = self.band.bound[active.clone()]
            .iter()
            .zip(active)
            .filter(|&(_, i)| i != slot)
            .fold(f32::INFINITY, |m, (&b, _)| m.min(b));
        if u < f64::from(others) {
            self.stable[t].1 = u;
            true
        } else {
            false
        }
    }

    /// The current tile's label and its largest distance if all its pixels have that
    /// label, else `(u32::MAX, ∞)`.
    #[inline(always)]
    fn certificate(&self) -> (u32, f64) {
        let tile = &self.tile;
        let row = |y: usize| &self.labels[y * self.stride + tile.x0..][..tile.n];
        let k = row(tile.rows.start)[0];
        if tile.rows.clone().all(|y| row(y).iter().all(|&l| l == k)) {
            (k, f64::from(largest(&tile.row_max)))
        } else {
            (u32::MAX, f64::INFINITY)
        }
    }

    /// Offers the current tile to the band's centres `active`: first to the centres its
    /// pixels had, then to every other centre whose bound does not exceed the tile's best
    /// distances. Returns whether the tile may have kept a single label (the ends of its
    /// rows had one and no label changed).
    #[inline(always)]
    fn search_tile(&mut self, active: Range<usize>) -> bool {
        let previous = self.previous_labels();
        let single = previous.len() == 1;
        for k in previous {
            if let Some(&i) = self.band.slot.get(k as usize)
                && active.contains(&(i as usize))
            {
                self.offer(i as usize);
                self.band.bound[i as usize] = f32::INFINITY;
            }
        }
        // The candidates under the bound, as bits (fewer unpredictable branches). The
        // bound only shrinks as centres are offered, but each centre's rows are checked
        // again against their own best distances.
        let limit = largest(&self.tile.row_max);
        for base in active.clone().step_by(64) {
            let bounds = &self.band.bound[base..active.end.min(base + 64)];
            let mut bits = bounds
                .iter()
                .enumerate()
                .fold(0u64, |m, (j, &b)| m | (u64::from(b <= limit) << j));
            while bits != 0 {
                let i = base + bits.trailing_zeros() as usize;
                bits &= bits - 1;
                self.offer(i);
            }
        }
        single && !self.tile.changed
    }

    /// The distinct labels at the ends of some of the current tile's rows (up to four):
    /// usually all of its labels.
    #[inline(always)]
    fn previous_labels(&self) -> std::iter::Take<std::array::IntoIter<u32, 4>> {
        let mut found = [u32::MAX; 4];
        let mut n = 0;
        let mut last = u32::MAX;
        let tile = &self.tile;
        // Every third row and the last (enough to catch the labels of most tiles; any
        // other centre is still tried after them).
        let rows = tile.rows.clone();
        for y in rows.clone().step_by(3).chain(rows.end - 1..rows.end) {
            let row = &self.labels[y * self.stride + tile.x0..][..tile.n];
            for k in [row[0], row[tile.n - 1]] {
                if k != last && n < found.len() && !found[..n].contains(&k) {
                    found[n] = k;
                    n += 1;
                }
                last = k;
            }
        }
        found.into_iter().take(n)
    }

    /// Offers the current tile to the band's centre `i`, row by row.
    #[inline(always)]
    fn offer(&mut self, i: usize) {
        let (band, tile, weight) = (&self.band, &mut self.tile, self.weight);
        let (k, cx, cy) = (band.k[i], band.cx[i], band.cy[i]);
        let lab = [band.lab[0][i], band.lab[1][i], band.lab[2][i]];
        // Columns outside the window get a NaN spatial term: never better.
        let (wx0, wx1, left) = (band.x0[i], band.x1[i], tile.x0 as f32);
        let mut dx2 = [0f32; TW];
        for (j, d) in dx2.iter_mut().enumerate() {
            let x = left + j as f32;
            let inside = u32::from(x >= wx0 && x < wx1).wrapping_neg();
            let term = spatial(weight, x - cx).to_bits();
            *d = f32::from_bits((term & inside) | (f32::NAN.to_bits() & !inside));
        }
        // Whether the window covers the tile's columns (which are all in the image).
        let full = tile.n == TW && wx0 <= left && left + TW as f32 <= wx1;
        let dx_bound = band.column_term(i, tile.x0..tile.x0 + tile.n, weight);
        let [r0, r1] = band.rows[i];
        // The rows the centre may win: its bound on each (from the row's Lab bounding box)
        // not above the row's best distances; all at once, as bits.
        let boxes = self.tiles.row_boxes(tile.rows.start, tile.x0);
        let mut bound = [0f32; TH];
        for (r, b) in bound.iter_mut().enumerate() {
            let bx = [
                boxes[0][r],
                boxes[1][r],
                boxes[2][r],
                boxes[3][r],
                boxes[4][r],
                boxes[5][r],
            ];
            *b = colour_gap(lab, bx) + (spatial(weight, cy - tile.ys[r]) + dx_bound);
        }
        let mut rows = 0u32;
        for (r, (&b, &m)) in bound.iter().zip(&tile.row_max).enumerate() {
            rows |= u32::from(b <= m) << r;
        }
        rows &= ((1u32 << r1) - 1) & !((1u32 << r0) - 1);
        let mut changed = [0u32; TW];
        while rows != 0 {
            let r = rows.trailing_zeros() as usize;
            rows &= rows - 1;
            let dy2 = spatial(weight, cy - tile.ys[r]);
            let y = tile.rows.start + r;
            let cell = self.tiles.cell(y, tile.x0);
            let labels = &mut self.labels[y * self.stride + tile.x0..][..TW];
            let Ok(label) = <&mut [u32; TW]>::try_from(labels) else {
                continue;
            };
            let best = &mut tile.best[r];
            let terms = (&dx2, dy2, lab, k);
            tile.row_max[r] = if !tile.fresh[r] {
                offer_row::<false, false>(best, label, cell, terms, &mut changed)
            } else if full {
                tile.fresh[r] = false;
                offer_row::<true, true>(best, label, cell, terms, &mut changed)
            } else {
                tile.fresh[r] = false;
                *best = tile.pad;
                offer_row::<true, false>(best, label, cell, terms, &mut changed)
            };
        }
        tile.changed |= changed.iter().fold(0, |a, &d| a | d) != 0;
    }
}

impl Tile {
    /// Makes this the tile over `rows` and columns `cols` (at most `TH × TW`), with no
    /// distances yet (the rows' `best` are set by their first offer, see [`offer_row`]).
    #[inline(always)]
    fn start(&mut self, rows: Range<usize>, cols: Range<usize>) {
        let n = cols.len();
        for (j, p) in self.pad.iter_mut().enumerate() {
            *p = if j < n { f32::INFINITY } else { 0.0 };
        }
        self.row_max = [0.0; TH];
        self.fresh = [false; TH];
        for (r, y) in rows.clone().enumerate() {
            self.row_max[r] = f32::INFINITY;
            self.fresh[r] = true;
            self.ys[r] = y as f32;
        }
        (self.rows, self.x0, self.n, self.changed) = (rows, cols.start, n, false);
    }
}

/// Offers centre `k` (colour `lab`, spatial terms `dy2` and `dx2`) to a row of a tile:
/// the pixels for which `(distance, k)` is less than their best so far take it. In a
/// `FRESH` row no centre has been offered yet, so any distance but NaN (outside the
/// window) wins: all of them if the window covers the `FULL` row. Branch-free, so that it vectorises; the rows are written whole (no
/// masked stores, which later loads cannot forward from). Returns the row's largest best
/// distance; sets bits of `changed` where a label changed.
#[inline(always)]
fn offer_row<const FRESH: bool, const FULL: bool>(
    best: &mut [f32; TW],
    label: &mut [u32; TW],
    [l, a, b]: &[[f32; TW]; 3],
    (dx2, dy2, lab, k): (&[f32; TW], f32, [f32; 3], u32),
    changed: &mut [u32; TW],
) -> f32 {
    let (old_best, old_label) = (*best, *label);
    let mut new_best = [0f32; TW];
    let mut new_label = [0u32; TW];
    for i in 0..TW {
        let dist = colour_distance(l[i], a[i], b[i], lab) + (dy2 + dx2[i]);
        let better = if FRESH && FULL {
            true
        } else if FRESH {
            dist < old_best[i]
        } else {
            (dist < old_best[i]) | ((dist == old_best[i]) & (k < old_label[i]))
        };
        let mask = u32::from(better).wrapping_neg();
        new_best[i] = f32::from_bits((old_best[i].to_bits() & !mask) | (dist.to_bits() & mask));
        new_label[i] = (old_label[i] & !mask) | (k & mask);
        changed[i] |= mask & (k ^ old_label[i]);
    }
    (*best, *label) = (new_best, new_label);
    largest(&new_best)
}

/// The largest of (non-NaN, non-negative) `values`, as a tree of lane-wise maxima.
#[inline(always)]
fn largest<const N: usize>(values: &[f32; N]) -> f32 {
    let max = |a: f32, b: f32| if a > b { a } else { b };
    let mut lanes = [0f32; 4];
    for chunk in values.chunks(4) {
        for (m, &v) in lanes.iter_mut().zip(chunk) {
            *m = max(*m, v);
        }
    }
    max(max(lanes[0], lanes[2]), max(lanes[1], lanes[3]))
}

/// Squared CIELAB distance of a pixel to a centre colour.
#[inline(always)]
fn colour_distance(l: f32, a: f32, b: f32, c: [f32; 3]) -> f32 {
    let (dl, da, db) = (l - c[0], a - c[1], b - c[2]);
    dl * dl + da * da + db * db
}
