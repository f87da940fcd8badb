//! SLIC's last step: connectivity enforced as scikit-image does it, labels made dense
//! in raster order.

use std::cmp::Reverse;
use std::collections::BinaryHeap;

/// A pixel without a new label yet.
const UNSET: u32 = u32::MAX;

/// scikit-image's `_enforce_label_connectivity_cython` (2-D, 4-connectivity): a raster
/// scan grows each unlabelled pixel's component of equal SLIC label breadth-first, up to
/// `max_size` pixels; a component under `min_size` takes the label of the last
/// already-labelled neighbour met in the search, any other one gets the next new label.
/// Returns the dense labels (raster order of first appearance) and their count.
///
/// The components are found first from the runs of equal labels along the rows (runs in
/// neighbouring rows that overlap are joined); the scan then meets them in the raster
/// order of their first pixels, and one it takes whole (neither too small nor too large)
/// just gets the next label. Only where the order of the search matters is it followed
/// pixel by pixel: a small component is searched breadth-first (its neighbour depends on
/// the order), and so is a large one (the search stops part-way); the scan meets the
/// rest of a large one later, at its first unlabelled pixel, where its part is first
/// filled span by span (the same pixels as breadth-first when taken whole).
#[inline(always)]
pub(super) fn enforce_connectivity(
    labels: &[u32],
    [width, height]: [usize; 2],
    [min_size, max_size]: [usize; 2],
    scratch: &mut Scratch,
) -> (Vec<u32>, u32) {
    let mut search = Components {
        labels,
        width,
        height,
        out: vec![UNSET; labels.len()],
        pixels: std::mem::take(&mut scratch.pixels),
        seeds: std::mem::take(&mut scratch.seeds),
    };
    let runs = &mut scratch.runs;
    runs.find(labels, width);
    // Parts of components too large to be taken whole, by their first unlabelled pixel.
    let mut rest = BinaryHeap::new();
    let (mut next, mut c) = (0u32, 0);
    loop {
        let first = |c: usize| {
            runs.of_component(c)
                .first()
                .map(|&(y, x0, _)| y * width + x0)
        };
        let whole = if c < runs.sizes.len() { first(c) } else { None };
        let part = rest.peek().map(|&Reverse(part)| part);
        let (start, component) = match (whole, part) {
            (Some(start), Some((p, _))) if start < p => (start, c),
            (Some(start), None) => (start, c),
            (_, Some(part)) => {
                rest.pop();
                part
            }
            (None, None) => break,
        };
        let is_whole = Some(start) == whole;
        let size = if is_whole {
            c += 1;
            runs.sizes[component]
        } else {
            search.fill(start, next, max_size)
        };
        if min_size <= size && size < max_size {
            if is_whole {
                for &(y, x0, x1) in runs.of_component(component) {
                    search.out[y * width + x0..y * width + x1].fill(next);
                }
            }
            next += 1;
        } else {
            if !is_whole {
                for &p in &search.pixels {
                    search.out[p] = UNSET;
                }
            }
            if size < min_size {
                search.small(start, next, max_size);
            } else {
                search.breadth_first(start, next, max_size);
                next += 1;
            }
        }
        if !is_whole || size >= max_size {
            // The scan meets the rest of the component at its first unlabelled pixel.
            let unlabelled = runs
                .of_component(component)
                .iter()
                .find_map(|&(y, x0, x1)| {
                    let row = y * width;
                    (row + x0.max(start.saturating_sub(row))..row + x1)
                        .find(|&p| p > start && search.out[p] == UNSET)
                });
            if let Some(p) = unlabelled {
                rest.push(Reverse((p, component)));
            }
        }
    }
    let count = next;
    (scratch.pixels, scratch.seeds) = (search.pixels, search.seeds);
    // All small so far: the pixels hold the not-yet-counted label `next` (= 0).
    (search.out, count.max(1))
}

/// Buffers of the connectivity step, kept from image to image.
#[derive(Debug, Default)]
pub(super) struct Scratch {
    pixels: Vec<usize>,
    seeds: Vec<usize>,
    runs: Runs,
}

/// Calls `f` with each column of `row` whose label differs from the one before, in order.
#[inline(always)]
fn for_each_change(row: &[u32], mut f: impl FnMut(usize)) {
    const LANES: usize = 16;
    let pairs = row.chunks_exact(LANES).zip(row[1..].chunks_exact(LANES));
    let mut x = 1;
    // Sixteen comparisons at a time, as bits.
    for (a, b) in pairs {
        let mut bits = 0u32;
        for i in 0..LANES {
            bits |= u32::from(a[i] != b[i]) << i;
        }
        while bits != 0 {
            f(x + bits.trailing_zeros() as usize);
            bits &= bits - 1;
        }
        x += LANES;
    }
    for x in x..row.len() {
        if row[x] != row[x - 1] {
            f(x);
        }
    }
}

/// The runs of equal labels along the rows and the components they form.
#[derive(Debug, Default)]
struct Runs {
    /// Each run: row, first column, one past the last column (raster order).
    runs: Vec<(usize, usize, usize)>,
    /// Per run: its parent in the union-find forest (then its root).
    parent: Vec<u32>,
    /// Per run: its component.
    component: Vec<u32>,
    /// Per component (numbered in raster order of their first pixels): pixel count.
    sizes: Vec<usize>,
    /// The runs of component `c` are `by_component[starts[c]..starts[c + 1]]`.
    starts: Vec<usize>,
    by_component: Vec<(usize, usize, usize)>,
    /// Scratch for listing them.
    fill: Vec<usize>,
}

impl Runs {
    /// Finds the runs of `labels` (rows of `width`) and their components.
    #[inline(always)]
    fn find(&mut self, labels: &[u32], width: usize) {
        self.runs.clear();
        self.parent.clear();
        let mut previous = 0..0;
        for (y, row) in labels.chunks_exact(width).enumerate() {
            let first = self.runs.len();
            let mut x0 = 0;
            for_each_change(row, |x| {
                self.runs.push((y, x0, x));
                x0 = x;
            });
            self.runs.push((y, x0, width));
            self.parent.extend(first as u32..self.runs.len() as u32);
            // Runs of equal labels that overlap the row above are joined.
            let (mut i, mut j) = (previous.start, first);
            while i < previous.end && j < self.runs.len() {
                let ((ya, a0, a1), (_, b0, b1)) = (self.runs[i], self.runs[j]);
                if a0 < b1 && b0 < a1 && labels[ya * width + a0] == row[b0] {
                    self.union(i, j);
                }
                if a1 <= b1 {
                    i += 1;
                } else {
                    j += 1;
                }
            }
            previous = first..self.runs.len();
        }
        self.components();
    }

    /// The root of run `i`'s tree (halving the path on the way).
    #[inline(always)]
    fn root(&mut self, mut i: usize) -> usize {
        while self.parent[i] as usize != i {
            let up = self.parent[self.parent[i] as usize];
            self.parent[i] = up;
            i = up as usize;
        }
        i
    }

    /// Joins the trees of runs `i` and `j` (under the earlier root).
    #[inline(always)]
    fn union(&mut self, i: usize, j: usize) {
        let (a, b) = (self.root(i), self.root(j));
        let (low, high) = if a < b { (a, b) } else { (b, a) };
        self.parent[high] = low as u32;
    }

    /// Numbers the components in raster order of their first pixels (a root is its
    /// tree's first run) and lists their runs.
    #[inline(always)]
    fn components(&mut self) {
        for i in 0..self.runs.len() {
            self.parent[i] = self.root(i) as u32;
        }
        self.sizes.clear();
        self.component.clear();
        for (i, &(_, x0, x1)) in self.runs.iter().enumerate() {
            let root = self.parent[i] as usize;
            let c = if root == i {
                self.sizes.push(0);
                self.sizes.len() - 1
            } else {
                self.component[root] as usize
            };
            self.sizes[c] += x1 - x0;
            self.component.push(c as u32);
        }
        self.starts.clear();
        self.starts.resize(self.sizes.len() + 1, 0);
        for &c in &self.component {
            self.starts[c as usize + 1] += 1;
        }
        for c in 1..self.starts.len() {
            self.starts[c] += self.starts[c - 1];
        }
        self.by_component.resize(self.runs.len(), (0, 0, 0));
        self.fill.clear();
        self.fill.extend_from_slice(&self.starts);
        for (&c, &run) in self.component.iter().zip(&self.runs) {
            self.by_component[self.fill[c as usize]] = run;
            self.fill[c as usize] += 1;
        }
    }

    /// The runs of component `c`, the first first.
    #[inline(always)]
    fn of_component(&self, c: usize) -> &[(usize, usize, usize)] {
        &self.by_component[self.starts[c]..self.starts[c + 1]]
    }
}

/// The connectivity search over SLIC's `labels`.
struct Components<'a> {
    labels: &'a [u32],
    width: usize,
    height: usize,
    /// The new labels (`UNSET` where none yet).
    out: Vec<u32>,
    /// The pixels of the component being grown.
    pixels: Vec<usize>,
    /// Span fill: pixels whose spans are still to be grown.
    seeds: Vec<usize>,
}

impl Components<'_> {
    /// scikit-image's handling of the small component holding `start`: searched
    /// breadth-first (labelled `next`), it takes the label of the last labelled
    /// neighbour met, if any.
    #[inline(always)]
    fn small(&mut self, start: usize, next: u32, max_size: usize) {
        let (_, adjacent) = self.breadth_first(start, next, max_size);
        // Only a component holding the first pixel can have no labelled neighbour (every
        // later one touches the pixel before it in raster order); it keeps the next
        // label, which the following component then shares and extends.
        if let Some(adjacent) = adjacent {
            for &p in &self.pixels {
                self.out[p] = adjacent;
            }
        }
    }

    /// Gives label `next` to the unlabelled pixels of `start`'s component (4-connected,
    /// equal SLIC label), span by span, stopping once it has `max_size` pixels; returns
    /// how many it took (listed in `pixels`).
    #[inline(always)]
    fn fill(&mut self, start: usize, next: u32, max_size: usize) -> usize {
        let (width, label) = (self.width, self.labels[start]);
        let (out, labels) = (&mut self.out, self.labels);
        let joins = |out: &[u32], q: usize| out[q] == UNSET && labels[q] == label;
        self.pixels.clear();
        self.seeds.clear();
        out[start] = next;
        self.pixels.push(start);
        self.seeds.push(start);
        while let Some(seed) = self.seeds.pop() {
            let row = seed - seed % width;
            // Grow the seed's span both ways.
            let (mut left, mut right) = (seed, seed + 1);
            while left > row && joins(out, left - 1) {
                left -= 1;
                out[left] = next;
                self.pixels.push(left);
            }
            while right < row + width && joins(out, right) {
                out[right] = next;
                self.pixels.push(right);
                right += 1;
            }
            if self.pixels.len() >= max_size {
                return self.pixels.len();
            }
            // One new seed per run of joining pixels above and below the span.
            let above = (row >= width).then(|| left - width);
            let below = (row + width < width * self.height).then_some(left + width);
            for first in [above, below].into_iter().flatten() {
                let mut q = first;
                while q < first + (right - left) {
                    if joins(out, q) {
                        out[q] = next;
                        self.pixels.push(q);
                        self.seeds.push(q);
                        q += 1;
                        while q < first + (right - left) && joins(out, q) {
                            q += 1;
                        }
                    } else {
                        q += 1;
                    }
                }
            }
        }
        self.pixels.len()
    }

    /// scikit-image's breadth-first search from `start` with label `next`, up to
    /// `max_size` pixels (listed in `pixels`): returns how many it took and the last
    /// already-labelled neighbour it met.
    #[inline(always)]
    fn breadth_first(&mut self, start: usize, next: u32, max_size: usize) -> (usize, Option<u32>) {
        let (width, height, label) = (self.width, self.height, self.labels[start]);
        let (out, labels, queue) = (&mut self.out, self.labels, &mut self.pixels);
        queue.clear();
        out[start] = next;
        queue.push(start);
        let mut adjacent = None;
        let mut visited = 0;
        // scikit-image: `while bfs_visited < current_segment_size < max_size`.
        while queue.len() < max_size {
            let Some(&p) = queue.get(visited) else {
                break;
            };
            visited += 1;
            let (x, y) = (p % width, p / width);
            // A neighbour of the same SLIC label joins the component; any other one that
            // already has a new label is remembered as adjacent. Returns whether the
            // component is full.
            let mut visit = |q: usize| {
                let seen = out[q];
                if seen == UNSET {
                    if labels[q] == label {
                        out[q] = next;
                        queue.push(q);
                        return queue.len() >= max_size;
                    }
                } else if seen != next {
                    adjacent = Some(seen);
                }
                false
            };
            // scikit-image's neighbour order: +x, -x, +y, -y.
            if (x + 1 < width && visit(p + 1))
                || (x > 0 && visit(p - 1))
                || (y + 1 < height && visit(p + width))
                || (y > 0 && visit(p - width))
            {
                break;
            }
        }
        (queue.len(), adjacent)
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    /// scikit-image's algorithm as written: a raster scan growing each unlabelled pixel's
    /// component breadth-first.
    fn reference(labels: &[u32], w: usize, h: usize, min: usize, max: usize) -> (Vec<u32>, u32) {
        let mut out = vec![UNSET; labels.len()];
        let mut queue = Vec::new();
        let mut next = 0;
        for start in 0..labels.len() {
            if out[start] != UNSET {
                continue;
            }
            out[start] = next;
            queue.clear();
            queue.push(start);
            let (mut visited, mut adjacent) = (0, None);
            'grow: while queue.len() < max && visited < queue.len() {
                let p = queue[visited];
                visited += 1;
                let (x, y) = (p % w, p / w);
                let neighbours = [
                    (x + 1 < w).then(|| p + 1),
                    (x > 0).then(|| p - 1),
                    (y + 1 < h).then(|| p + w),
                    (y > 0).then(|| p - w),
                ];
                for q in neighbours.into_iter().flatten() {
                    if out[q] == UNSET && labels[q] == labels[start] {
                        out[q] = next;
                        queue.push(q);
                        if queue.len() >= max {
                            break 'grow;
                        }
                    } else if out[q] != UNSET && out[q] != next {
                        adjacent = Some(out[q]);
                    }
                }
            }
            if queue.len() >= min {
                next += 1;
            } else if let Some(adjacent) = adjacent {
                queue.iter().for_each(|&p| out[p] = adjacent);
            }
        }
        (out, next.max(1))
    }

    #[test]
    fn slic_connectivity_matches_the_breadth_first_scan() {
        let mut state = 0x1234_5678_9abc_def1u64;
        let mut random = |n: u64| {
            state ^= state << 13;
            state ^= state >> 7;
            state ^= state << 17;
            (state % n) as usize
        };
        let mut scratch = Scratch::default();
        for _ in 0..3000 {
            let (w, h) = (1 + random(40), 1 + random(40));
            // Blocks of random labels with some noise: components of all sizes.
            let (block, labels_count, noise) = (1 + random(6), 1 + random(6), random(4));
            let blocks: Vec<u32> = (0..(w / block + 1) * (h / block + 1))
                .map(|_| random(labels_count as u64) as u32)
                .collect();
            let labels: Vec<u32> = (0..w * h)
                .map(|p| {
                    let (x, y) = (p % w, p / w);
                    if noise > 0 && random(10 * noise as u64) == 0 {
                        random(labels_count as u64) as u32
                    } else {
                        blocks[y / block * (w / block + 1) + x / block]
                    }
                })
                .collect();
            let min = random(12);
            let max = min + 1 + random(60);
            assert_eq!(
                enforce_connectivity(&labels, [w, h], [min, max], &mut scratch),
                reference(&labels, w, h, min, max),
                "{w}x{h}, sizes {min}..{max}"
            );
        }
    }
}
