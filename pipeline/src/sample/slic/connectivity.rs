//! SLIC's last step: connectivity enforced as scikit-image does it, labels made dense
//! in raster order.

/// A pixel without a new label yet.
const UNSET: u32 = u32::MAX;

/// scikit-image's `_enforce_label_connectivity_cython` (2-D, 4-connectivity): a raster
/// scan grows each unlabelled pixel's component of equal SLIC label breadth-first, up to
/// `max_size` pixels; a component under `min_size` takes the label of the last
/// already-labelled neighbour met in the search, any other one gets the next new label.
/// Returns the dense labels (raster order of first appearance) and their count.
///
/// A component is first filled span by span, which is faster than breadth-first and
/// reaches the same pixels when the whole component is taken; only a component that is
/// too small or too large, where the order of the search matters, is searched again
/// breadth-first.
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
    let mut next = 0u32;
    for start in 0..labels.len() {
        if search.out[start] != UNSET {
            continue;
        }
        let size = search.fill(start, next, max_size);
        if min_size <= size && size < max_size {
            next += 1;
            continue;
        }
        for &p in &search.pixels {
            search.out[p] = UNSET;
        }
        let (size, adjacent) = search.breadth_first(start, next, max_size);
        if size < min_size {
            // Only a component holding the first pixel can have no labelled neighbour
            // (every later one touches the pixel before it in raster order); it keeps
            // the next label, which the following component then shares and extends.
            if let Some(adjacent) = adjacent {
                for &p in &search.pixels {
                    search.out[p] = adjacent;
                }
            }
        } else {
            next += 1;
        }
    }
    // All small so far: the pixels hold the not-yet-counted label `next` (= 0).
    let count = if next == 0 { 1 } else { next };
    (scratch.pixels, scratch.seeds) = (search.pixels, search.seeds);
    (search.out, count)
}

/// Buffers of the connectivity step, kept from image to image.
#[derive(Debug, Default)]
pub(super) struct Scratch {
    pixels: Vec<usize>,
    seeds: Vec<usize>,
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
