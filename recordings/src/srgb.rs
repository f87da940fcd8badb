//! Linear to 8-bit sRGB-ish gamma (exponent 1/2.2) by table: the same bytes as
//! `round(x^(1/2.2)·255)`, without a `powf` per colour channel.
//!
//! The function is a step function of `x`; the table holds the smallest `x` at which each
//! output value starts, found by bisection over the `f64` bit patterns with the exact
//! formula, and a coarse index into it.

use std::sync::OnceLock;

/// The formula the table reproduces.
pub fn to_srgb_exact(linear: f64) -> u8 {
    (linear.clamp(0.0, 1.0).powf(1.0 / 2.2) * 255.0).round() as u8
}

/// Buckets of the coarse index over `[0, 1)`.
const BUCKETS: usize = 4096;

/// The steps of [`to_srgb_exact`].
struct Table {
    /// `starts[v]`: the smallest `x` in `[0, 1]` with output `v` or more (`starts[0] = 0`).
    starts: [f64; 256],
    /// `first[b]`: the output at `b / BUCKETS`.
    first: Vec<u8>,
}

/// The smallest non-negative `x ≤ 1` with `to_srgb_exact(x) >= value` (`value ≥ 1`).
fn step_start(value: u8) -> f64 {
    // Non-negative floats order as their bit patterns.
    let (mut lo, mut hi) = (0u64, 1.0f64.to_bits());
    while hi - lo > 1 {
        let mid = lo + (hi - lo) / 2;
        if to_srgb_exact(f64::from_bits(mid)) >= value {
            hi = mid;
        } else {
            lo = mid;
        }
    }
    f64::from_bits(hi)
}

fn table() -> &'static Table {
    static TABLE: OnceLock<Table> = OnceLock::new();
    TABLE.get_or_init(|| {
        let mut starts = [0.0; 256];
        for (value, start) in starts.iter_mut().enumerate().skip(1) {
            *start = step_start(value as u8);
        }
        let first = (0..BUCKETS)
            .map(|b| count_steps(&starts, 0, b as f64 / BUCKETS as f64))
            .collect();
        Table { starts, first }
    })
}

/// The output at `x`: `from` plus the steps after it that start at or below `x`.
fn count_steps(starts: &[f64; 256], from: u8, x: f64) -> u8 {
    let mut value = from;
    while value < 255 && starts[usize::from(value) + 1] <= x {
        value += 1;
    }
    value
}

/// `round(clamp(linear, 0, 1)^(1/2.2)·255)`, by table.
pub fn to_srgb(linear: f64) -> u8 {
    // Also NaN, as `clamp` then `powf` would give 0.
    if linear.is_nan() || linear <= 0.0 {
        return 0;
    }
    if linear >= 1.0 {
        return 255;
    }
    let table = table();
    // Exact: scaling by a power of two, then truncation of a value in [0, BUCKETS).
    let bucket = (linear * BUCKETS as f64) as usize;
    let from = table.first.get(bucket).copied().unwrap_or(0);
    count_steps(&table.starts, from, linear)
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn the_table_reproduces_the_formula_around_every_step_and_elsewhere() {
        let starts = table().starts;
        for start in starts.iter().skip(1) {
            let bits = start.to_bits();
            for bits in bits - 20_000..bits + 20_000 {
                let x = f64::from_bits(bits);
                assert_eq!(to_srgb(x), to_srgb_exact(x), "{x:e}");
            }
        }
        let mut rng = crate::scene::SplitMix::new(7);
        for _ in 0..1_000_000 {
            let x = rng.uniform(-0.1, 1.1);
            assert_eq!(to_srgb(x), to_srgb_exact(x), "{x:e}");
        }
        for x in [
            0.0,
            -0.0,
            1.0,
            f64::NAN,
            f64::INFINITY,
            f64::NEG_INFINITY,
            1e-300,
        ] {
            assert_eq!(to_srgb(x), to_srgb_exact(x), "{x:e}");
        }
    }
}
