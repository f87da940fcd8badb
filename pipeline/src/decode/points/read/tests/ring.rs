//! The ring index of a FLOAT32, in `f32` (both loops) and through `f64`: the same verdict
//! and index for every value.

use crate::decode::points::field::{Endianness, FieldPlan, NumericType};
use crate::decode::points::read::general::ring_index;
use crate::decode::points::read::plain::float32_ring;

/// The round trip through `f64` the FLOAT32 fast path replaces.
fn through_f64(v: f32) -> Option<u16> {
    let index = v as u16;
    (f64::from(index) == f64::from(v)).then_some(index)
}

#[test]
fn float32_rings_in_f32_are_the_f64_round_trip() {
    let plan = |endianness| FieldPlan {
        offset: 2,
        numeric: NumericType::Float32,
        endianness,
    };
    let point = |v: f32, big: bool| {
        let bytes = if big {
            v.to_be_bytes()
        } else {
            v.to_le_bytes()
        };
        let mut p = vec![0xAB, 0xCD];
        p.extend_from_slice(&bytes);
        p
    };
    let mut values: Vec<f32> = (0..=65_535).map(|i| i as f32).collect();
    values.extend((0..=65_535).map(|i| i as f32 + 0.5));
    values.extend([
        -0.0,
        -1.0,
        -0.5,
        1e-30,
        0.999_999_94,
        65_535.5,
        65_536.0,
        65_537.0,
        8_388_608.0,
        16_777_216.0,
        f32::MAX,
        f32::MIN,
        f32::INFINITY,
        f32::NEG_INFINITY,
        f32::NAN,
        -f32::NAN,
    ]);
    let mut rng = crate::test_rng::TestRng(0x2545_F491);
    for _ in 0..1_000_000 {
        let bits = rng.next() as u32;
        values.push(f32::from_bits(bits));
        values.push((bits % 140_000) as f32 / 2.0 - 1_000.0);
    }
    for v in values {
        let want = through_f64(v);
        // The plain loop's branch-free copy: the same verdict and index.
        let (index, ok) = float32_ring(v);
        assert_eq!(ok.then_some(index), want, "{v}");
        assert_eq!(
            ring_index(plan(Endianness::Little), &point(v, false)),
            want,
            "{v}"
        );
        // Big-endian rings take the general path: the same answers.
        assert_eq!(
            ring_index(plan(Endianness::Big), &point(v, true)),
            want,
            "{v}"
        );
    }
}
