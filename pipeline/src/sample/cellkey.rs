//! Integer cells packed into `u64` keys whose order is the cells' lexicographic
//! `(x, y, z)` order, so that voxels, their neighbours and their parents are found by
//! sorting and merging instead of hashing every cell 27 times.
//!
//! Each axis gets a field of just enough bits for its range plus one cell of margin on
//! both sides, so a neighbour `c + o` (`o` in `-1..=1` per axis) of any cell in the range
//! packs to `key(c) + delta(o)` without a carry or borrow between fields. Ranges too wide
//! for 64 bits (points thousands of kilometres apart) have no packing; callers then fall
//! back to sorting the cells themselves.

/// The packing of one set of cells.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub(crate) struct CellKeys {
    /// Smallest coordinate per axis, minus the one-cell margin.
    origin: [i64; 3],
    /// Bit position of the x and y fields (z starts at bit 0).
    shift: [u32; 2],
    /// Bits used by the three fields together.
    bits: u32,
}

/// The smallest and the largest value of each axis of `cells` (`i32::MAX` and `i32::MIN`
/// when empty). Eight cells at a time, as 24 lanes whose lane `j` holds axis `j % 3`, so
/// that the comparisons run in vector lanes; compiled with AVX2 where the CPU has it (the
/// baseline x86-64 has no packed `i32` minimum, and per cell and axis the scalar
/// comparisons waited on each other).
#[allow(unsafe_code)]
fn range(cells: &[[i32; 3]]) -> [[i32; 3]; 2] {
    #[cfg(target_arch = "x86_64")]
    if crate::sample::simd::has_avx2() {
        // SAFETY: the CPU runs AVX2 (checked just above), the only requirement of calling
        // a function compiled with it enabled.
        return unsafe { range_avx2(cells) };
    }
    range_lanes(cells)
}

/// [`range_lanes`] compiled with AVX2 enabled.
#[cfg(target_arch = "x86_64")]
#[target_feature(enable = "avx2")]
fn range_avx2(cells: &[[i32; 3]]) -> [[i32; 3]; 2] {
    range_lanes(cells)
}

#[inline(always)]
fn range_lanes(cells: &[[i32; 3]]) -> [[i32; 3]; 2] {
    const LANES: usize = 24;
    let mut lo = [i32::MAX; LANES];
    let mut hi = [i32::MIN; LANES];
    let (blocks, rest) = cells.as_flattened().as_chunks::<LANES>();
    for block in blocks {
        for j in 0..LANES {
            lo[j] = lo[j].min(block[j]);
            hi[j] = hi[j].max(block[j]);
        }
    }
    for (j, &v) in rest.iter().enumerate() {
        lo[j] = lo[j].min(v);
        hi[j] = hi[j].max(v);
    }
    let axis = |lanes: &[i32; LANES], a: usize, pick: fn(i32, i32) -> i32| {
        (a..LANES).step_by(3).map(|j| lanes[j]).fold(lanes[a], pick)
    };
    [
        std::array::from_fn(|a| axis(&lo, a, i32::min)),
        std::array::from_fn(|a| axis(&hi, a, i32::max)),
    ]
}

/// Bits needed to hold every value in `0..=max`.
fn bits_for(max: u64) -> u32 {
    64 - max.leading_zeros()
}

impl CellKeys {
    /// A packing covering every cell of `cells` and their 3×3×3 neighbours; `None` when
    /// the three ranges need more than 64 bits. Empty input packs trivially.
    pub(crate) fn covering(cells: &[[i32; 3]]) -> Option<CellKeys> {
        let [lo, hi] = if cells.is_empty() {
            [[0; 3]; 2]
        } else {
            range(cells).map(|r| r.map(i64::from))
        };
        // Values c - (lo - 1) lie in 1..=span+1; the neighbours in 0..=span+2.
        let width = |a: usize| bits_for((hi[a] - lo[a] + 2) as u64);
        let (bx, by, bz) = (width(0), width(1), width(2));
        let bits = bx + by + bz;
        (bits <= 64).then_some(CellKeys {
            origin: [lo[0] - 1, lo[1] - 1, lo[2] - 1],
            shift: [by + bz, bz],
            bits,
        })
    }

    /// Bits the keys use (at most 64).
    pub(crate) fn bits(&self) -> u32 {
        self.bits
    }

    /// The key of a cell inside the covered range (or one cell outside it).
    #[inline]
    pub(crate) fn key(&self, c: [i32; 3]) -> u64 {
        let field = |a: usize| (i64::from(c[a]) - self.origin[a]) as u64;
        (field(0) << self.shift[0]) | (field(1) << self.shift[1]) | field(2)
    }

    /// What `key(c + o) - key(c)` is for every covered `c`, as a wrapping difference.
    pub(crate) fn delta(&self, o: [i32; 3]) -> u64 {
        let f = |v: i32, s: u32| (i64::from(v) << s) as u64;
        f(o[0], self.shift[0])
            .wrapping_add(f(o[1], self.shift[1]))
            .wrapping_add(f(o[2], 0))
    }
}

/// Sorted cells' packing and their keys, in the cells' order: what a level's neighbour map
/// merges, handed on from the sort that found the cells so it is not computed twice.
pub(crate) type Keyed = (CellKeys, Vec<u64>);

/// The order of `cells` sorted lexicographically, as indices, with the sorted cells'
/// keys when there is a packing. Ties (equal cells) keep index order.
pub(crate) fn sort_cells(cells: &[[i32; 3]]) -> (Vec<u32>, Option<Keyed>) {
    let Some(keys) = CellKeys::covering(cells) else {
        let mut order: Vec<u32> = (0..cells.len() as u32).collect();
        order.sort_unstable_by_key(|&i| (cells[i as usize], i));
        return (order, None);
    };
    let index_bits = bits_for(cells.len() as u64);
    let (order, sorted): (Vec<u32>, Vec<u64>) = if keys.bits() <= 32 {
        // 32-bit keys beside their index: a stable radix sort of the key bytes only
        // (four passes at most, where key and index packed together would take six).
        let mut pairs: Vec<(u32, u32)> = cells
            .iter()
            .enumerate()
            .map(|(i, c)| (keys.key(*c) as u32, i as u32))
            .collect();
        radsort::sort_by_key(&mut pairs, |p| p.0);
        pairs.iter().map(|&(k, i)| (i, u64::from(k))).unzip()
    } else if keys.bits() + index_bits <= 64 {
        // Key and index in one u64: an integer radix sort; the index breaks ties.
        let mut packed: Vec<u64> = cells
            .iter()
            .enumerate()
            .map(|(i, c)| (keys.key(*c) << index_bits) | i as u64)
            .collect();
        radsort::sort(&mut packed);
        let mask = (1u64 << index_bits) - 1;
        packed
            .iter()
            .map(|p| ((p & mask) as u32, p >> index_bits))
            .unzip()
    } else {
        let mut pairs: Vec<(u64, u32)> = cells
            .iter()
            .enumerate()
            .map(|(i, c)| (keys.key(*c), i as u32))
            .collect();
        pairs.sort_unstable();
        pairs.iter().map(|&(k, i)| (i, k)).unzip()
    };
    (order, Some((keys, sorted)))
}

/// The number of runs of equal values in `sorted` (the unique cells of sorted keys):
/// what a pass keeping each run's first will keep, so that it can allocate that once
/// instead of growing (and copying) as it goes.
pub(crate) fn count_runs<T: PartialEq>(sorted: &[T]) -> usize {
    let changes = sorted.windows(2).filter(|w| w[0] != w[1]).count();
    changes + usize::from(!sorted.is_empty())
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn keys_order_like_cells_and_neighbours_add_deltas() {
        let cells = [[3, -7, 0], [-2, 5, 9], [3, -7, 1], [0, 0, 0], [-2, 4, 11]];
        let keys = CellKeys::covering(&cells).unwrap();
        for a in &cells {
            for b in &cells {
                assert_eq!(a.cmp(b), keys.key(*a).cmp(&keys.key(*b)), "{a:?} {b:?}");
            }
            for o in [[-1, -1, -1], [1, -1, 0], [0, 1, -1], [1, 1, 1]] {
                let n = [a[0] + o[0], a[1] + o[1], a[2] + o[2]];
                assert_eq!(keys.key(n), keys.key(*a).wrapping_add(keys.delta(o)));
            }
        }
        // A corner of the range still has neighbours outside it, one cell deep.
        let corner = [-2, -7, 0];
        let below = [-3, -8, -1];
        assert!(keys.key(below) < keys.key(corner));
    }

    #[test]
    fn ranges_in_lanes_are_each_axis_min_and_max() {
        let mut rng = crate::test_rng::TestRng(0x2545_F491);
        let mut next = move || rng.next() as i32;
        // Every remainder of the eight-cell blocks, extremes included; both compiled copies.
        for n in 1..=25 {
            let mut cells: Vec<[i32; 3]> = (0..n)
                .map(|_| [next(), next() % 1000, next() >> 20])
                .collect();
            if n > 5 {
                cells[n - 1][2] = i32::MIN;
                cells[3][0] = i32::MAX;
            }
            let want_lo: [i32; 3] =
                std::array::from_fn(|a| cells.iter().map(|c| c[a]).min().unwrap());
            let want_hi: [i32; 3] =
                std::array::from_fn(|a| cells.iter().map(|c| c[a]).max().unwrap());
            assert_eq!(range(&cells), [want_lo, want_hi], "{n} cells");
            assert_eq!(
                range_lanes(&cells),
                [want_lo, want_hi],
                "{n} cells, baseline"
            );
        }
    }

    #[test]
    fn wide_ranges_have_no_packing_and_sort_without_one() {
        let cells = [
            [i32::MAX, 0, 0],
            [i32::MIN, 5, 0],
            [0, i32::MIN, i32::MAX],
            [0, 0, 0],
        ];
        assert!(CellKeys::covering(&cells).is_none());
        let (order, keys) = sort_cells(&cells);
        assert!(keys.is_none());
        assert_eq!(order, [1, 2, 3, 0]);
    }

    #[test]
    fn both_packings_sort_the_same() {
        // Key + index over 64 bits: the (key, index) pair sort; fewer: the packed sort
        // (or, keys of 32 bits at most, the stable sort of keys beside indices).
        let wide: Vec<[i32; 3]> = (0..200)
            .map(|i| {
                let x = (i * 7919) % 3_000_001 - 1500;
                [x, (i * 104_729) % 4001, -(i % 13) * 40_000_000]
            })
            .collect();
        let narrow: Vec<[i32; 3]> = wide
            .iter()
            .map(|c| [c[0] % 7, c[1] % 5, c[2] % 3])
            .collect();
        let middle: Vec<[i32; 3]> = wide
            .iter()
            .map(|c| [c[0] % 3000, c[1] % 4001, c[2] / 20_000])
            .collect();
        for (cells, bits) in [(wide, 33..=64), (middle, 33..=56), (narrow, 0..=32)] {
            let (order, keys) = sort_cells(&cells);
            let (packing, sorted) = keys.unwrap();
            let index_bits = bits_for(cells.len() as u64);
            assert!(bits.contains(&packing.bits()), "{}", packing.bits());
            assert_eq!(
                packing.bits() + index_bits > 64,
                *bits.end() == 64,
                "pair sort expected for the wide cells only"
            );
            let mut expected: Vec<u32> = (0..cells.len() as u32).collect();
            expected.sort_by_key(|&i| (cells[i as usize], i));
            assert_eq!(order, expected);
            let unique: std::collections::BTreeSet<[i32; 3]> = cells.iter().copied().collect();
            assert_eq!(count_runs(&sorted), unique.len());
            assert_eq!(count_runs::<u64>(&[]), 0);
            assert!(sorted.windows(2).all(|w| w[0] <= w[1]));
        }
    }
}
