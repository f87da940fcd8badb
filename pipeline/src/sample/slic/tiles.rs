//! The data of SLIC's tiled search: the Lab image cut into tile rows with each tile's Lab
//! bounding box (once per image), and the centres whose windows meet a band of tiles,
//! with their lower bounds on a tile (each pass).

use super::centres::Centre;
use super::lab::Lab;
use std::ops::Range;

/// Tile width, pixels: a row of a tile is offered to a centre as a unit.
pub(super) const TW: usize = 16;
/// Tile height, rows.
pub(super) const TH: usize = 16;

/// The Lab image cut into rows of tiles (`TW` pixels of each plane side by side, padded
/// with zeros at the right edge), and the Lab bounding box of each tile's pixels.
#[derive(Debug, Default)]
pub(super) struct Tiles {
    /// Image width, pixels.
    pub width: usize,
    /// Image height, pixels.
    pub height: usize,
    /// Tiles per row.
    tiles_x: usize,
    /// Per image row and tile column (row-major): the tile row's L, a and b.
    cells: Vec<[[f32; TW]; 3]>,
    /// Per tile (row-major): `[l_min, l_max, a_min, a_max, b_min, b_max]`.
    boxes: Vec<[f32; 6]>,
    /// Per tile (row-major): the same per row of the tile.
    row_boxes: Vec<[[f32; TH]; 6]>,
}

impl Tiles {
    /// Cuts `lab` (`width × height`, both positive) into tiles and bounds them.
    #[inline(always)]
    pub(super) fn prepare(&mut self, lab: &Lab, width: usize, height: usize) {
        let tiles_x = width.div_ceil(TW);
        (self.width, self.height, self.tiles_x) = (width, height, tiles_x);
        // Every cell is written below but the padding, which only needs to be finite.
        let cells = &mut self.cells;
        cells.resize(tiles_x * height, [[0f32; TW]; 3]);
        for (y, cells) in cells.chunks_exact_mut(tiles_x).enumerate() {
            let row = y * width..(y + 1) * width;
            for (dst, src) in [&lab.l[row.clone()], &lab.a[row.clone()], &lab.b[row]]
                .into_iter()
                .enumerate()
            {
                for (cell, src) in cells.iter_mut().zip(src.chunks(TW)) {
                    cell[dst][..src.len()].copy_from_slice(src);
                }
            }
        }
        self.bound_rows(width, height);
    }

    /// The Lab bounding boxes of the rows of each tile, then of each tile.
    #[inline(always)]
    fn bound_rows(&mut self, width: usize, height: usize) {
        let tiles_x = self.tiles_x;
        let tiles = tiles_x * height.div_ceil(TH);
        // Rows below the image get empty boxes (infinitely far from any colour).
        let empty = [[f32::INFINITY; TH], [f32::NEG_INFINITY; TH]];
        let empty = [empty[0], empty[1], empty[0], empty[1], empty[0], empty[1]];
        self.row_boxes.clear();
        self.row_boxes.resize(tiles, empty);
        for (y, cells) in self.cells.chunks_exact(tiles_x).enumerate() {
            let boxes = &mut self.row_boxes[y / TH * tiles_x..][..tiles_x];
            for (tx, (cell, bx)) in cells.iter().zip(boxes).enumerate() {
                let n = TW.min(width - tx * TW);
                for (p, plane) in cell.iter().enumerate() {
                    let plane = &plane[..n];
                    bx[2 * p][y % TH] = plane.iter().fold(f32::INFINITY, |m, &v| min(m, v));
                    bx[2 * p + 1][y % TH] = plane.iter().fold(f32::NEG_INFINITY, |m, &v| max(m, v));
                }
            }
        }
        self.boxes.clear();
        self.boxes.extend(self.row_boxes.iter().map(|rows| {
            let mut bx = [0f32; 6];
            for (p, b) in bx.iter_mut().enumerate() {
                let fold = if p % 2 == 0 { min } else { max };
                *b = rows[p].iter().copied().reduce(fold).unwrap_or(0.0);
            }
            bx
        }));
    }

    /// The Lab bounding boxes of the rows of the tile at `(y0, x0)` (multiples of `TH`
    /// and `TW`): `[l_min, l_max, a_min, a_max, b_min, b_max]`, each per row.
    #[inline(always)]
    pub(super) fn row_boxes(&self, y0: usize, x0: usize) -> &[[f32; TH]; 6] {
        &self.row_boxes[y0 / TH * self.tiles_x + x0 / TW]
    }

    /// The L, a and b of the `TW` pixels from `(y, x0)`, `x0` a multiple of `TW`.
    #[inline(always)]
    pub(super) fn cell(&self, y: usize, x0: usize) -> &[[f32; TW]; 3] {
        &self.cells[y * self.tiles_x + x0 / TW]
    }

    /// The Lab bounding box of the tile at `(y0, x0)`, multiples of `TH` and `TW`.
    #[inline(always)]
    pub(super) fn tile_box(&self, y0: usize, x0: usize) -> [f32; 6] {
        self.boxes[y0 / TH * self.tiles_x + x0 / TW]
    }
}

/// The centres whose windows meet a band of rows, in order of their columns, as arrays;
/// and, for the current tile, their lower bounds.
#[derive(Debug, Default)]
pub(super) struct Band {
    /// Centre index.
    pub k: Vec<u32>,
    /// The window's rows, relative to the band's first row and clipped to the band.
    pub rows: Vec<[u32; 2]>,
    /// The window's columns `x0..x1`.
    pub columns: Vec<[u32; 2]>,
    /// First column of the window.
    pub x0: Vec<f32>,
    /// One past the last column of the window.
    pub x1: Vec<f32>,
    /// Centre row.
    pub cy: Vec<f32>,
    /// Centre column.
    pub cx: Vec<f32>,
    /// Centre colour: L, a and b.
    pub lab: [Vec<f32>; 3],
    /// The least row spatial term over the band's rows within the window.
    dy2: Vec<f32>,
    /// For the current tile: the lower bound of the distance (infinite once tried).
    pub bound: Vec<f32>,
    /// Each centre's position in the band (`u32::MAX`: not in it).
    pub slot: Vec<u32>,
}

impl Band {
    /// Number of centres.
    pub(super) fn len(&self) -> usize {
        self.k.len()
    }

    /// Collects the centres of `members` (in that order) whose windows meet `rows`.
    #[inline(always)]
    pub(super) fn gather(
        &mut self,
        centres: &[Centre],
        windows: &[[usize; 4]],
        members: &[u32],
        rows: Range<usize>,
        weight: f32,
    ) {
        self.k.clear();
        self.rows.clear();
        self.columns.clear();
        self.x0.clear();
        self.x1.clear();
        self.cy.clear();
        self.cx.clear();
        self.lab.iter_mut().for_each(Vec::clear);
        self.dy2.clear();
        self.slot.clear();
        self.slot.resize(centres.len(), u32::MAX);
        for &k in members {
            let [y0, y1, x0, x1] = windows[k as usize];
            if y0 >= rows.end || y1 <= rows.start || x0 >= x1 {
                continue;
            }
            let c = &centres[k as usize];
            let (top, bottom) = (y0.max(rows.start), y1.min(rows.end));
            // The window's row in the band nearest the centre (its own row if inside).
            let near = c.y.max(top as f32).min((bottom - 1) as f32);
            self.slot[k as usize] = self.k.len() as u32;
            self.k.push(k);
            self.rows
                .push([(top - rows.start) as u32, (bottom - rows.start) as u32]);
            self.columns.push([x0 as u32, x1 as u32]);
            self.x0.push(x0 as f32);
            self.x1.push(x1 as f32);
            self.cy.push(c.y);
            self.cx.push(c.x);
            for (plane, &v) in self.lab.iter_mut().zip(&c.lab) {
                plane.push(v);
            }
            self.dy2.push(spatial(weight, c.y - near));
        }
        let n = self.k.len();
        self.bound.resize(n, 0.0);
    }

    /// The lower bounds of centres `active` on the tile of columns `cols` with the Lab
    /// bounding box `colour`.
    #[inline(always)]
    pub(super) fn bounds(
        &mut self,
        active: Range<usize>,
        cols: Range<usize>,
        colour: [f32; 6],
        weight: f32,
    ) {
        let n = active.len();
        let (x0, x1, cx) = (
            &self.x0[active.clone()],
            &self.x1[active.clone()][..n],
            &self.cx[active.clone()][..n],
        );
        let [l, a, b] = &self.lab;
        let (l, a, b) = (
            &l[active.clone()][..n],
            &a[active.clone()][..n],
            &b[active.clone()][..n],
        );
        let (dy2, out) = (&self.dy2[active.clone()][..n], &mut self.bound[active][..n]);
        for i in 0..n {
            let dx2 = column_term([x0[i], x1[i], cx[i]], cols.clone(), weight);
            out[i] = colour_gap([l[i], a[i], b[i]], colour) + (dy2[i] + dx2);
        }
    }

    /// The least column spatial term of centre `i` over the columns `cols` of a tile
    /// within its window.
    #[inline(always)]
    pub(super) fn column_term(&self, i: usize, cols: Range<usize>, weight: f32) -> f32 {
        column_term([self.x0[i], self.x1[i], self.cx[i]], cols, weight)
    }
}

/// The larger of two (non-NaN) values, without `f32::max`'s NaN handling.
#[inline(always)]
fn max(a: f32, b: f32) -> f32 {
    if a > b { a } else { b }
}

/// The smaller of two (non-NaN) values, without `f32::min`'s NaN handling.
#[inline(always)]
fn min(a: f32, b: f32) -> f32 {
    if a < b { a } else { b }
}

/// A lower bound of the colour term of the distance of a centre of colour `lab` to the
/// pixels of a Lab bounding box (`[l_min, l_max, a_min, a_max, b_min, b_max]`), computed
/// as the term is: differences `pixel - centre`, each no larger in magnitude than for any
/// pixel inside the box (0 inside), squared and added in the same order.
#[inline(always)]
pub(super) fn colour_gap(lab: [f32; 3], bx: [f32; 6]) -> f32 {
    let gap = |lo: f32, hi: f32, v: f32| max(max(lo - v, v - hi), 0.0);
    let dl = gap(bx[0], bx[1], lab[0]);
    let da = gap(bx[2], bx[3], lab[1]);
    let db = gap(bx[4], bx[5], lab[2]);
    dl * dl + da * da + db * db
}

/// The least column spatial term over the columns `cols` of a tile within the window
/// (`x0..x1`) of a centre of column `cx`: the term at the window's column nearest the
/// centre (0 if that is the centre's own).
#[inline(always)]
fn column_term([x0, x1, cx]: [f32; 3], cols: Range<usize>, weight: f32) -> f32 {
    let (left, right) = (cols.start as f32, (cols.end - 1) as f32);
    let near = min(max(cx, max(x0, left)), min(x1 - 1.0, right));
    spatial(weight, near - cx)
}

/// `weight · d²` for a coordinate difference `d`: the spatial term of one axis.
#[inline(always)]
pub(super) fn spatial(weight: f32, d: f32) -> f32 {
    weight * d * d
}
