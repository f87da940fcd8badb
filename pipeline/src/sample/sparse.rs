//! Sparse-convolution maps for a sparse residual UNet (MinkUNet): for every level, the
//! 3×3×3 neighbour map of the submanifold convolutions, and the kernel-2 stride-2 map
//! down to the next level (whose transpose is the up-sampling map). A map lists, per
//! kernel offset, `(input row, output row)` pairs: the trainer gathers input rows,
//! multiplies by that offset's weights and scatter-adds into output rows.

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

/// The 3×3×3 neighbour map of unique `coords`.
pub fn neighbour_map(coords: &[[i32; 3]]) -> KernelMap {
    let rows = row_index(coords);
    let offsets = cube_offsets();
    let mut map = KernelMap {
        offsets: offsets.clone(),
        pairs: Vec::with_capacity(coords.len() * 8),
        starts: vec![0],
    };
    for o in &offsets {
        for (out_row, c) in coords.iter().enumerate() {
            let neighbour = [c[0] + o[0], c[1] + o[1], c[2] + o[2]];
            if let Some(in_row) = rows.get(&neighbour) {
                map.pairs.push([*in_row, out_row as u32]);
            }
        }
        map.starts.push(map.pairs.len() as u32);
    }
    map
}

/// Halves `coords` (floor division by 2): the next level's unique cells, in order of
/// first occurrence, and the kernel-2 stride-2 map whose offset is the position of the
/// input cell inside its 2×2×2 block.
pub fn downsample(coords: &[[i32; 3]]) -> (Vec<[i32; 3]>, KernelMap) {
    let mut rows: HashMap<[i32; 3], u32> =
        HashMap::with_capacity_and_hasher(coords.len() / 2, Default::default());
    let mut coarse = Vec::new();
    let parent: Vec<u32> = coords
        .iter()
        .map(|c| {
            let p = [c[0].div_euclid(2), c[1].div_euclid(2), c[2].div_euclid(2)];
            *rows.entry(p).or_insert_with(|| {
                coarse.push(p);
                (coarse.len() - 1) as u32
            })
        })
        .collect();
    let offsets: Vec<[i32; 3]> = (0..8)
        .map(|k| [(k >> 2) & 1, (k >> 1) & 1, k & 1])
        .collect();
    let mut map = KernelMap {
        offsets: offsets.clone(),
        pairs: Vec::with_capacity(coords.len()),
        starts: vec![0],
    };
    for o in &offsets {
        for (in_row, c) in coords.iter().enumerate() {
            let within = [c[0].rem_euclid(2), c[1].rem_euclid(2), c[2].rem_euclid(2)];
            if within == *o {
                map.pairs.push([in_row as u32, parent[in_row]]);
            }
        }
        map.starts.push(map.pairs.len() as u32);
    }
    (coarse, map)
}

/// Every level of a UNet with `levels` resolutions (MinkUNet: 5, strides 1 to 16),
/// starting from the unique voxel `coords`.
pub fn build_levels(coords: &[[i32; 3]], levels: usize) -> Vec<Level> {
    let mut out: Vec<Level> = Vec::with_capacity(levels);
    let mut current = coords.to_vec();
    for l in 0..levels {
        let neighbours = neighbour_map(&current);
        let (down, next) = if l + 1 < levels {
            let (coarse, map) = downsample(&current);
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

    #[test]
    fn neighbour_map_equals_brute_force() {
        let coords = random_coords(400, 7, 6);
        let map = neighbour_map(&coords);
        assert_eq!(map.offsets.len(), 27);
        assert_eq!(map.starts.len(), 28);
        for (k, o) in map.offsets.iter().enumerate() {
            let got: BTreeSet<[u32; 2]> = map.pairs_of(k).iter().copied().collect();
            let mut expected = BTreeSet::new();
            for (out_row, c) in coords.iter().enumerate() {
                for (in_row, d) in coords.iter().enumerate() {
                    if *d == [c[0] + o[0], c[1] + o[1], c[2] + o[2]] {
                        expected.insert([in_row as u32, out_row as u32]);
                    }
                }
            }
            assert_eq!(got, expected, "offset {o:?}");
        }
        // The centre offset maps every row onto itself.
        let centre = map.offsets.iter().position(|o| *o == [0, 0, 0]).unwrap();
        assert_eq!(map.pairs_of(centre).len(), coords.len());
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
