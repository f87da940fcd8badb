//! Sparse-convolution maps for a sparse residual UNet (MinkUNet): for every level, the
//! 3×3×3 neighbour map of the submanifold convolutions, and the kernel-2 stride-2 map
//! down to the next level (whose transpose is the up-sampling map). A map lists, per
//! kernel offset, `(input row, output row)` pairs: the trainer gathers input rows,
//! multiplies by that offset's weights and scatter-adds into output rows.

use super::cellkey::{CellKeys, Keyed, count_runs, sort_cells};
use rustc_hash::FxHashMap as HashMap;

/// `(input row, output row)` pairs grouped by kernel offset.
#[derive(Debug, Clone, PartialEq, Eq, Default)]
pub struct KernelMap {
    /// The kernel offsets, in the order their pairs appear.
    pub offsets: Vec<[i32; 3]>,
    /// All pairs, offset by offset.
    pub pairs: Vec<[u32; 2]>,
    /// Pairs of offset `k` are `pairs[starts[k]..starts[k + 1]]` (`offsets.len() + 1` entries).
    pub starts: Vec<u32>,
}

impl KernelMap {
    /// The pairs of offset number `k`.
    pub fn pairs_of(&self, k: usize) -> &[[u32; 2]] {
        let (a, b) = (self.starts[k] as usize, self.starts[k + 1] as usize);
        &self.pairs[a..b]
    }

    /// The same map with inputs and outputs swapped (a transposed convolution).
    pub fn transposed(&self) -> KernelMap {
        KernelMap {
            offsets: self.offsets.clone(),
            pairs: self.pairs.iter().map(|[i, o]| [*o, *i]).collect(),
            starts: self.starts.clone(),
        }
    }
}

/// One resolution level of the UNet.
#[derive(Debug, Clone, PartialEq, Eq)]
pub struct Level {
    /// Tensor stride of the level (1, 2, 4, ...), in input voxels.
    pub stride: i32,
    /// Cells of this level, in the level's own units (input cells divided by `stride`).
    pub coords: Vec<[i32; 3]>,
    /// 3×3×3 submanifold map: output row `o` gathers input row `i` at `coords[o] + offset`.
    pub neighbours: KernelMap,
    /// Kernel-2 stride-2 map to the next level: input row of this level, output row of the
    /// next; `None` on the last level. Its transpose up-samples.
    pub down: Option<KernelMap>,
}

/// The 27 offsets of a 3×3×3 kernel, x slowest, z fastest.
pub fn cube_offsets() -> Vec<[i32; 3]> {
    let mut out = Vec::with_capacity(27);
    for x in -1..=1 {
        for y in -1..=1 {
            for z in -1..=1 {
                out.push([x, y, z]);
            }
        }
    }
    out
}

fn row_index(coords: &[[i32; 3]]) -> HashMap<[i32; 3], u32> {
    coords
        .iter()
        .enumerate()
        .map(|(i, c)| (*c, i as u32))
        .collect()
}

/// Index of a 3×3×3 offset in [`cube_offsets`].
fn cube_index(o: [i32; 3]) -> usize {
    ((o[0] + 1) * 9 + (o[1] + 1) * 3 + (o[2] + 1)) as usize
}

/// The 3×3×3 neighbour map of unique `coords` (any order; the levels of
/// [`build_levels`] are sorted, which is the fast path). Pairs of each offset are in
/// output-row order.
///
/// The cells are sorted as packed keys ([`CellKeys`]); the 13 offsets `o` after the
/// centre in lexicographic order are found by five linear passes over the sorted keys,
/// one per column `(dx, dy)` of offsets (a merge of the keys with themselves shifted by
/// the column's `dz = −1` offset; in the cell's own column a look at the next key). Each
/// pair `c + o = d` is also the pair `d − o = c` of the opposite offset: five passes
/// instead of 27 hash lookups per cell.
pub fn neighbour_map(coords: &[[i32; 3]]) -> KernelMap {
    neighbour_map_keyed(coords, None)
}

/// [`neighbour_map`], given the packed keys of `coords` when they are sorted and unique
/// and the sort that found them packed them (`known`); else they are computed here.
fn neighbour_map_keyed(coords: &[[i32; 3]], known: Option<Keyed>) -> KernelMap {
    let offsets = cube_offsets();
    let (order, keyed) = match known.filter(|(_, keys)| keys.len() == coords.len()) {
        Some(known) => (None, Some(known)),
        None if coords.windows(2).all(|w| w[0] < w[1]) => {
            let keyed = CellKeys::covering(coords)
                .map(|keys| (keys, coords.iter().map(|c| keys.key(*c)).collect()));
            (None, keyed)
        }
        None => {
            let (order, keyed) = sort_cells(coords);
            (Some(order), keyed)
        }
    };
    let Some((keys, sorted)) = keyed else {
        return hashed_neighbour_map(coords);
    };
    let n = coords.len();
    let centre = cube_index([0, 0, 0]);
    // The pairs of the 13 offsets after the centre, by column (dx, dy): one pass finds
    // every dz. In the cell's own column only dz = +1 comes after the centre, and that
    // neighbour can only be the next key.
    let mut after: Vec<Vec<[u32; 2]>> = vec![Vec::new(); offsets.len()];
    after[cube_index([0, 0, 1])] = next_in_column(&sorted);
    for (dx, dy) in [(0, 1), (1, -1), (1, 0), (1, 1)] {
        let found = merge_column(&sorted, keys.delta([dx, dy, -1]));
        for (dz, pairs) in (-1..=1).zip(found) {
            after[cube_index([dx, dy, dz])] = pairs;
        }
    }
    let total = n + 2 * after.iter().map(Vec::len).sum::<usize>();
    let mut map = KernelMap {
        offsets,
        pairs: Vec::with_capacity(total),
        starts: Vec::with_capacity(28),
    };
    map.starts.push(0);
    for k in 0..map.offsets.len() {
        match k.cmp(&centre) {
            // The opposite of an offset after the centre: the same pairs, input and
            // output swapped, in the same sequence (which is also output order).
            std::cmp::Ordering::Less => map
                .pairs
                .extend(after[2 * centre - k].iter().map(|&[c, a]| [a, c])),
            std::cmp::Ordering::Equal => map.pairs.extend((0..n as u32).map(|i| [i, i])),
            std::cmp::Ordering::Greater => map.pairs.extend_from_slice(&after[k]),
        }
        map.starts.push(map.pairs.len() as u32);
    }
    if let Some(order) = order {
        // Sorted positions back to rows, each offset's pairs back in output-row order.
        for k in 0..map.offsets.len() {
            let (from, to) = (map.starts[k] as usize, map.starts[k + 1] as usize);
            let pairs = &mut map.pairs[from..to];
            for p in pairs.iter_mut() {
                *p = [order[p[0] as usize], order[p[1] as usize]];
            }
            pairs.sort_unstable_by_key(|p| p[1]);
        }
    }
    map
}

/// For sorted unique keys, the pairs `[a + 1, a]` with `key[a + 1] = key[a] + 1` (the
/// offset `(0, 0, 1)`), in `a` order. Branch-free: every step writes its pair at the end
/// of the list and counts it only if it is one.
#[allow(unsafe_code)]
fn next_in_column(sorted: &[u64]) -> Vec<[u32; 2]> {
    let steps = sorted.len().saturating_sub(1);
    let mut out: Vec<[u32; 2]> = Vec::with_capacity(steps);
    let spare = out.spare_capacity_mut();
    let mut len = 0;
    for (a, w) in sorted.windows(2).enumerate() {
        // `len <= a < steps`: in bounds.
        spare[len].write([a as u32 + 1, a as u32]);
        len += usize::from(w[1] == w[0].wrapping_add(1));
    }
    // SAFETY: the first `len` slots were written in the loop (slot `len` at every step
    // before `len` grew past it).
    unsafe { out.set_len(len) };
    out
}

/// For sorted unique keys, the pairs `[b, a]` with `key[b] = key[a] + delta + j`, for
/// `j` = 0, 1, 2 (`delta > 0`: the offsets `dz` = −1, 0, 1 of one column), in `a` order,
/// which is also `b` order (for a given `j`, `b` grows with `a`).
///
/// Each list gets room for one pair per cell (a cell has at most one neighbour per
/// offset) and is written through its spare capacity, its length kept in a register
/// (pushing to a `Vec<Vec<_>>` would keep the lengths in memory, loaded and stored at
/// every push).
#[allow(unsafe_code)]
fn merge_column(sorted: &[u64], delta: u64) -> [Vec<[u32; 2]>; 3] {
    let n = sorted.len();
    let mut out: [Vec<[u32; 2]>; 3] = std::array::from_fn(|_| Vec::with_capacity(n));
    let [o0, o1, o2] = &mut out;
    let (s0, s1, s2) = (
        o0.spare_capacity_mut(),
        o1.spare_capacity_mut(),
        o2.spare_capacity_mut(),
    );
    let (mut l0, mut l1, mut l2) = (0, 0, 0);
    let mut b = 0;
    'cells: for (a, &key) in sorted.iter().enumerate() {
        let first = key.wrapping_add(delta);
        loop {
            match sorted.get(b) {
                Some(&k) if k < first => b += 1,
                Some(_) => break,
                None => break 'cells,
            }
        }
        let mut c = b;
        while let Some(&k) = sorted.get(c) {
            // `k >= first`; each `j` is met at most once per cell, so no list outgrows
            // `n` (the indexing checks it anyway).
            let j = k - first;
            if j > 2 {
                break;
            }
            let pair = [c as u32, a as u32];
            match j {
                0 => {
                    s0[l0].write(pair);
                    l0 += 1;
                }
                1 => {
                    s1[l1].write(pair);
                    l1 += 1;
                }
                _ => {
                    s2[l2].write(pair);
                    l2 += 1;
                }
            }
            c += 1;
        }
    }
    let lens = [l0, l1, l2];
    for (list, len) in out.iter_mut().zip(lens) {
        // SAFETY: the first `len` slots of each list were written in the loop.
        unsafe { list.set_len(len) };
    }
    out
}

/// [`neighbour_map`] by hashing, for cells whose range does not pack into 64 bits.
fn hashed_neighbour_map(coords: &[[i32; 3]]) -> KernelMap {
    let rows = row_index(coords);
    let offsets = cube_offsets();
    let mut map = KernelMap {
        offsets: offsets.clone(),
        pairs: Vec::with_capacity(coords.len() * 8),
        starts: vec![0],
    };
    for o in &offsets {
        for (out_row, c) in coords.iter().enumerate() {
            let neighbour = [
                c[0].wrapping_add(o[0]),
                c[1].wrapping_add(o[1]),
                c[2].wrapping_add(o[2]),
            ];
            if let Some(in_row) = rows.get(&neighbour) {
                map.pairs.push([*in_row, out_row as u32]);
            }
        }
        map.starts.push(map.pairs.len() as u32);
    }
    map
}

/// Halves `coords` (floor division by 2): the next level's unique cells, sorted
/// lexicographically, and the kernel-2 stride-2 map whose offset is the position of the
/// input cell inside its 2×2×2 block (pairs of each offset in input-row order).
pub fn downsample(coords: &[[i32; 3]]) -> (Vec<[i32; 3]>, KernelMap) {
    let (coarse, map, _) = downsample_keyed(coords);
    (coarse, map)
}

/// [`downsample`], and the coarse cells' packed keys when they have a packing.
fn downsample_keyed(coords: &[[i32; 3]]) -> (Vec<[i32; 3]>, KernelMap, Option<Keyed>) {
    let parents: Vec<[i32; 3]> = coords
        .iter()
        .map(|c| [c[0] >> 1, c[1] >> 1, c[2] >> 1])
        .collect();
    let (order, keyed) = sort_cells(&parents);
    let same = |s: usize, t: usize| match &keyed {
        Some((_, keys)) => keys[s] == keys[t],
        None => parents[order[s] as usize] == parents[order[t] as usize],
    };
    let unique = keyed.as_ref().map_or(0, |(_, keys)| count_runs(keys));
    let mut coarse = Vec::with_capacity(unique);
    let mut coarse_keys = Vec::with_capacity(unique);
    let mut parent = vec![0u32; coords.len()];
    for (s, &row) in order.iter().enumerate() {
        if s == 0 || !same(s - 1, s) {
            coarse.push(parents[row as usize]);
            if let Some((_, keys)) = &keyed {
                coarse_keys.push(keys[s]);
            }
        }
        parent[row as usize] = (coarse.len() - 1) as u32;
    }
    let offsets: Vec<[i32; 3]> = (0..8)
        .map(|k| [(k >> 2) & 1, (k >> 1) & 1, k & 1])
        .collect();
    // `c & 1` is `c mod 2` for negative c too (two's complement).
    let within = |c: &[i32; 3]| ((c[0] & 1) << 2 | (c[1] & 1) << 1 | (c[2] & 1)) as usize;
    let mut starts = vec![0u32; 9];
    for c in coords {
        starts[within(c) + 1] += 1;
    }
    for k in 0..8 {
        starts[k + 1] += starts[k];
    }
    let mut cursor: Vec<usize> = starts[..8].iter().map(|&s| s as usize).collect();
    let mut pairs = vec![[0u32; 2]; coords.len()];
    for (in_row, c) in coords.iter().enumerate() {
        let k = within(c);
        pairs[cursor[k]] = [in_row as u32, parent[in_row]];
        cursor[k] += 1;
    }
    let coarse_keys = keyed.map(|(packing, _)| (packing, coarse_keys));
    (
        coarse,
        KernelMap {
            offsets,
            pairs,
            starts,
        },
        coarse_keys,
    )
}

/// Every level of a UNet with `levels` resolutions (MinkUNet: 5, strides 1 to 16),
/// starting from the unique voxel `coords`.
pub fn build_levels(coords: &[[i32; 3]], levels: usize) -> Vec<Level> {
    build_levels_keyed(coords, None, levels)
}

/// [`build_levels`] from voxels whose packed keys their sort already found (`keys`, from
/// `voxel::voxelize_keyed`): each level's neighbour map takes the keys its cells were
/// sorted by (the voxels', then each down-sampling's) instead of packing them again.
pub(crate) fn build_levels_keyed(
    coords: &[[i32; 3]],
    keys: Option<Keyed>,
    levels: usize,
) -> Vec<Level> {
    let mut out: Vec<Level> = Vec::with_capacity(levels);
    let mut current = coords.to_vec();
    let mut current_keys = keys;
    for l in 0..levels {
        let neighbours = neighbour_map_keyed(&current, current_keys.take());
        let (down, next) = if l + 1 < levels {
            let (coarse, map, coarse_keys) = downsample_keyed(&current);
            current_keys = coarse_keys;
            (Some(map), coarse)
        } else {
            (None, Vec::new())
        };
        out.push(Level {
            stride: 1 << l,
            coords: std::mem::replace(&mut current, next),
            neighbours,
            down,
        });
    }
    out
}

#[cfg(test)]
mod tests {
    use super::*;
    use std::collections::BTreeSet;

    fn random_coords(n: usize, seed: u64, span: i32) -> Vec<[i32; 3]> {
        let mut state = seed;
        let mut next = move || {
            state ^= state << 13;
            state ^= state >> 7;
            state ^= state << 17;
            (state % (2 * span as u64)) as i32 - span
        };
        let mut set = BTreeSet::new();
        let mut out = Vec::new();
        while out.len() < n {
            let c = [next(), next(), next() / 4];
            if set.insert(c) {
                out.push(c);
            }
        }
        out
    }

    /// Every offset's pairs against a brute-force search, in output-row order.
    fn assert_brute_force(coords: &[[i32; 3]]) {
        let map = neighbour_map(coords);
        assert_eq!(map.offsets, cube_offsets());
        assert_eq!(map.starts.len(), 28);
        for (k, o) in map.offsets.iter().enumerate() {
            let mut expected = Vec::new();
            for (out_row, c) in coords.iter().enumerate() {
                let n = [
                    c[0].wrapping_add(o[0]),
                    c[1].wrapping_add(o[1]),
                    c[2].wrapping_add(o[2]),
                ];
                if let Some(in_row) = coords.iter().position(|d| *d == n) {
                    expected.push([in_row as u32, out_row as u32]);
                }
            }
            assert_eq!(map.pairs_of(k), expected, "offset {o:?}");
        }
        // The centre offset maps every row onto itself.
        let centre = map.offsets.iter().position(|o| *o == [0, 0, 0]).unwrap();
        assert_eq!(map.pairs_of(centre).len(), coords.len());
    }

    #[test]
    fn neighbour_map_equals_brute_force() {
        // Any order (sorted, then mapped back), sorted (the levels' fast path), and a
        // range too wide to pack (hashing).
        let coords = random_coords(400, 7, 6);
        assert_brute_force(&coords);
        let mut sorted = coords.clone();
        sorted.sort();
        assert_brute_force(&sorted);
        let mut wide = coords;
        wide[0] = [i32::MAX, 0, 0];
        wide[1] = [i32::MIN, i32::MAX, i32::MIN];
        wide[2] = [i32::MAX - 1, 0, 0];
        assert_brute_force(&wide);
        assert_brute_force(&[]);
        assert_brute_force(&[[0, 0, 0]]);
        assert_brute_force(&[[0, 0, 0], [0, 0, 1]]);
        assert_brute_force(&[[0, 0, 0], [0, 0, 2], [0, 1, 1], [1, -1, 3]]);
    }

    #[test]
    fn downsampled_cells_are_sorted_and_unique_for_any_range() {
        let mut coords = random_coords(300, 5, 20);
        coords[0] = [i32::MIN, -1, i32::MAX];
        let (coarse, map) = downsample(&coords);
        assert!(coarse.windows(2).all(|w| w[0] < w[1]));
        for [i, out] in &map.pairs {
            let c = coords[*i as usize];
            assert_eq!(coarse[*out as usize], [c[0] >> 1, c[1] >> 1, c[2] >> 1]);
        }
        let rows: Vec<u32> = (0..8)
            .flat_map(|k| map.pairs_of(k).iter().map(|p| p[0]))
            .collect();
        assert_eq!(rows.len(), coords.len());
        for k in 0..8 {
            assert!(map.pairs_of(k).windows(2).all(|w| w[0][0] < w[1][0]));
        }
    }

    #[test]
    fn downsampling_covers_every_fine_cell_once_and_transposes() {
        let coords = random_coords(500, 11, 9);
        let (coarse, map) = downsample(&coords);
        assert_eq!(map.pairs.len(), coords.len());
        let fine_rows: BTreeSet<u32> = map.pairs.iter().map(|p| p[0]).collect();
        assert_eq!(fine_rows.len(), coords.len());
        let unique: BTreeSet<[i32; 3]> = coarse.iter().copied().collect();
        assert_eq!(unique.len(), coarse.len());
        for (k, o) in map.offsets.iter().enumerate() {
            for [i, out] in map.pairs_of(k) {
                let c = coords[*i as usize];
                let p = coarse[*out as usize];
                // Negative coordinates floor correctly: c = 2p + offset.
                assert_eq!([2 * p[0] + o[0], 2 * p[1] + o[1], 2 * p[2] + o[2]], c);
            }
        }
        let up = map.transposed();
        assert!(
            up.pairs
                .iter()
                .zip(&map.pairs)
                .all(|(u, d)| *u == [d[1], d[0]])
        );
    }

    #[test]
    fn levels_from_the_sorts_keys_equal_maps_packed_afresh() {
        // Keys handed on from voxelization and each down-sampling give the maps that
        // packing each level's cells again gives, level by level.
        let mut rng = crate::test_rng::TestRng(0x51_7cc1_b727_220a);
        let mut coord = move |span: f32| (rng.next() >> 40) as f32 / (1u64 << 24) as f32 * span;
        let points: Vec<[f32; 3]> = (0..20_000)
            .map(|_| [coord(80.0) - 40.0, coord(80.0) - 40.0, coord(6.0) - 2.0])
            .collect();
        let grid = super::super::voxel::VoxelGrid::default();
        let (voxels, keys) = super::super::voxel::voxelize_keyed(&points, &grid);
        assert!(keys.is_some());
        let levels = build_levels_keyed(&voxels.coords, keys, 5);
        assert_eq!(levels, build_levels(&voxels.coords, 5));
        for level in &levels {
            assert_eq!(level.neighbours, neighbour_map(&level.coords));
        }
        // Keys that do not match the cells are not used.
        let short = Some((CellKeys::covering(&voxels.coords).unwrap(), vec![0u64; 3]));
        assert_eq!(
            neighbour_map_keyed(&voxels.coords, short),
            neighbour_map(&voxels.coords)
        );
    }

    #[test]
    fn levels_halve_until_the_last() {
        let coords = random_coords(2_000, 3, 40);
        let levels = build_levels(&coords, 5);
        assert_eq!(levels.len(), 5);
        assert_eq!(
            levels.iter().map(|l| l.stride).collect::<Vec<_>>(),
            [1, 2, 4, 8, 16]
        );
        for pair in levels.windows(2) {
            assert!(pair[1].coords.len() <= pair[0].coords.len());
            let down = pair[0].down.as_ref().unwrap();
            assert!(
                down.pairs
                    .iter()
                    .all(|[i, o]| (*i as usize) < pair[0].coords.len()
                        && (*o as usize) < pair[1].coords.len())
            );
        }
        assert!(levels[4].down.is_none());
        assert_eq!(levels[0].coords, coords);
    }
}
