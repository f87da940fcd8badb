//! SLIC's last step: connectivity enforced as scikit-image does it, labels made dense
//! in raster order.

/// scikit-image's `_enforce_label_connectivity_cython` (2-D, 4-connectivity): a raster
/// scan grows each unlabelled pixel's component of equal SLIC label breadth-first, up to
/// `max_size` pixels; a component under `min_size` takes the label of the last
/// already-labelled neighbour met in the search, any other one gets the next new label.
/// Returns the dense labels (raster order of first appearance) and their count.
pub(super) fn enforce_connectivity(
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
