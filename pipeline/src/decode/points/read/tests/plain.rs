//! The plain loop against the general loop on random clouds of the recorders' layouts:
//! the same points, rings and times, and `None` wherever the general loop must decide.

use crate::decode::context::Ctx;
use crate::decode::points::error::PointsError;
use crate::decode::points::field::{Endianness, FieldPlan, NamedField, NumericType};
use crate::decode::points::grid::Grid;
use crate::decode::points::layout::PointLayout;
use crate::decode::points::read::columns::{Attributes, Points};
use crate::decode::points::read::general::{Float32Xyz, fill};
use crate::decode::points::read::plain::{Plain, fill_plain};
use crate::decode::points::time::{TimeConversion, TimeReference, TimeUnit};
use crate::test_rng::TestRng;
use superflow_schemas::Stamp;

fn plan(offset: usize, numeric: NumericType) -> FieldPlan {
    FieldPlan {
        offset,
        numeric,
        endianness: Endianness::Little,
    }
}

fn named(name: &str, plan: FieldPlan) -> NamedField {
    NamedField {
        name: name.to_string(),
        plan,
    }
}

/// A layout of FLOAT32 x, y, z at 0, 4, 8, with an intensity and a ring as given.
fn layout(step: usize, intensity: Option<usize>, ring: Option<FieldPlan>) -> PointLayout {
    PointLayout {
        point_step: step,
        xyz: [0, 4, 8].map(|o| plan(o, NumericType::Float32)),
        intensity: intensity.map(|o| named("intensity", plan(o, NumericType::Float32))),
        ring: ring.map(|p| named("ring", p)),
        time: None,
        label: None,
    }
}

/// `rows` rows of `width` points, `pad` bytes after each row: random coordinates
/// (every `nan_every`th point with a NaN or infinite one), intensities, and rings
/// that are ring indices except on some non-finite points (and on finite point
/// `bad_ring` if given).
fn cloud(
    rng: &mut TestRng,
    layout: &PointLayout,
    [rows, width, pad]: [usize; 3],
    nan_every: u64,
    bad_ring: Option<usize>,
) -> (Vec<u8>, Grid) {
    cloud_timed(rng, layout, [rows, width, pad], nan_every, bad_ring, None)
}

/// [`cloud`] with a time field `(offset, bad point, type)`: FLOAT32 relative seconds,
/// FLOAT64 absolute seconds (around 1.7e9) or UINT32 nanoseconds; a float time is not
/// finite on some dropped points and on kept point `bad point` if given.
fn cloud_timed(
    rng: &mut TestRng,
    layout: &PointLayout,
    [rows, width, pad]: [usize; 3],
    nan_every: u64,
    bad_ring: Option<usize>,
    time: Option<(usize, Option<usize>, NumericType)>,
) -> (Vec<u8>, Grid) {
    let step = layout.point_step;
    let row_step = width * step + pad;
    let mut data = vec![0u8; rows * row_step];
    let mut n = 0;
    for r in 0..rows {
        for c in 0..width {
            let p = &mut data[r * row_step + c * step..][..step];
            for b in p.iter_mut() {
                *b = rng.next() as u8;
            }
            let mut xyz = [0f32; 3].map(|_| (rng.next() % 200_000) as f32 / 1000.0 - 100.0);
            let broken = nan_every > 0 && rng.next().is_multiple_of(nan_every);
            if broken {
                let which = (rng.next() % 3) as usize;
                xyz[which] = [f32::NAN, f32::INFINITY, f32::NEG_INFINITY][which];
            }
            for (k, v) in xyz.iter().enumerate() {
                p[4 * k..4 * k + 4].copy_from_slice(&v.to_le_bytes());
            }
            if let Some(i) = layout.intensity.as_ref() {
                let v = (rng.next() % 256) as f32;
                p[i.plan.offset..i.plan.offset + 4].copy_from_slice(&v.to_le_bytes());
            }
            if let Some(ring) = layout.ring.as_ref() {
                let o = ring.plan.offset;
                let index = (rng.next() % 64) as f32;
                let value = if (broken && rng.next().is_multiple_of(2)) || bad_ring == Some(n) {
                    [0.5, -1.0, 70_000.0, f32::NAN][(rng.next() % 4) as usize]
                } else {
                    index
                };
                match ring.plan.numeric {
                    NumericType::Float32 => {
                        p[o..o + 4].copy_from_slice(&value.to_le_bytes());
                    }
                    _ => p[o..o + 2].copy_from_slice(&(index as u16).to_le_bytes()),
                }
            }
            if let Some((o, bad_time, numeric)) = time {
                let bad = (broken && rng.next().is_multiple_of(2)) || bad_time == Some(n);
                let not_finite = [f64::NAN, f64::INFINITY][(rng.next() % 2) as usize];
                let fraction = (rng.next() % 100_000) as f64 * 1e-6;
                match numeric {
                    NumericType::Float32 => {
                        let t = if bad { not_finite } else { fraction - 0.05 };
                        p[o..o + 4].copy_from_slice(&(t as f32).to_le_bytes());
                    }
                    NumericType::Float64 => {
                        let t = if bad { not_finite } else { 1.7e9 + fraction };
                        p[o..o + 8].copy_from_slice(&t.to_le_bytes());
                    }
                    _ => {
                        let t = (fraction * 1e9) as u32;
                        p[o..o + 4].copy_from_slice(&t.to_le_bytes());
                    }
                }
            }
            if !broken {
                n += 1;
            }
        }
    }
    let grid = Grid {
        rows,
        width,
        row_step,
    };
    (data, grid)
}

/// The plain loop's points, or `None`, beside the general loop's.
fn both(
    layout: &PointLayout,
    data: &[u8],
    grid: Grid,
) -> (Option<Points>, Result<Points, PointsError>) {
    both_timed(layout, data, grid, None)
}

/// [`both`] with a time column read through `time`.
fn both_timed(
    layout: &PointLayout,
    data: &[u8],
    grid: Grid,
    time: Option<TimeConversion>,
) -> (Option<Points>, Result<Points, PointsError>) {
    let step = layout.point_step;
    let capacity = grid.rows * grid.width;
    let attributes = Attributes {
        intensity: layout.intensity.as_ref().map(|f| f.plan),
        ring: layout.ring.as_ref().map(|f| f.plan),
        time,
        label: None,
        kept_indices: false,
    };
    let plain = Plain::of(layout, &attributes).expect("a plain layout");
    let ctx = Ctx {
        frame_id: "lidar",
        stamp: Stamp::from_nanos(1),
    };
    let general = fill(
        &ctx,
        layout,
        data,
        grid,
        capacity,
        Float32Xyz::<false>([0, 4, 8]),
        attributes,
    );
    (fill_plain(data, grid, step, capacity, plain), general)
}

fn bits(v: &[f32]) -> Vec<u32> {
    v.iter().map(|x| x.to_bits()).collect()
}

#[test]
fn the_plain_loop_keeps_what_the_general_loop_keeps() {
    let mut rng = TestRng(0x9E37_79B9);
    let layouts = [
        // nuScenes: x y z intensity ring, all FLOAT32.
        layout(20, Some(12), Some(plan(16, NumericType::Float32))),
        // velodyne without its time: ring UINT16 at 16.
        layout(22, Some(12), Some(plan(16, NumericType::Uint16))),
        // A UINT16 ring in the point's last two bytes.
        layout(18, Some(12), Some(plan(16, NumericType::Uint16))),
        // KITTI: x y z intensity.
        layout(16, Some(12), None),
        // No intensity, padded points.
        layout(24, None, Some(plan(20, NumericType::Float32))),
    ];
    for layout in &layouts {
        for (shape, nan_every) in [
            ([1, 5_000, 0], 0),
            ([1, 5_000, 0], 7),
            ([16, 300, 13], 3),
            ([4, 1, 0], 1),
            ([0, 10, 0], 2),
        ] {
            let (data, grid) = cloud(&mut rng, layout, shape, nan_every, None);
            let (plain, general) = both(layout, &data, grid);
            let (plain, general) = (plain.expect("rings are fine"), general.unwrap());
            assert_eq!(plain.xyz.len(), general.xyz.len());
            let flat = |p: &Points| bits(p.xyz.as_flattened());
            assert_eq!(flat(&plain), flat(&general));
            assert_eq!(bits(&plain.intensity), bits(&general.intensity));
            assert_eq!(plain.ring, general.ring);
            assert_eq!(plain.dropped, general.dropped);
            assert!(plain.time_offset.is_none() && plain.label.is_none());
        }
    }
}

#[test]
fn fields_past_the_point_step_go_to_the_general_loop() {
    // Layouts are checked against their point step when a cloud's fields are
    // planned; the plain loop, which reads without bounds checks, checks again.
    let mut rng = TestRng(0x00DD_BA11);
    for (step, overrun) in [(16, Some(13)), (18, None)] {
        let ring = if overrun.is_none() {
            Some(plan(16, NumericType::Float32))
        } else {
            None
        };
        let fits = layout(20, Some(12), ring);
        let (data, grid) = cloud(&mut rng, &fits, [1, 50, 0], 0, None);
        let mut short = fits.clone();
        short.point_step = step;
        if let Some(at) = overrun {
            short.intensity = Some(named("intensity", plan(at, NumericType::Float32)));
        }
        let (plain, _) = both(&short, &data, grid);
        assert!(plain.is_none(), "step {step}");
    }
}

#[test]
fn a_bad_ring_on_a_kept_point_goes_to_the_general_loop() {
    let mut rng = TestRng(0x51ED_270B);
    let layout = layout(20, Some(12), Some(plan(16, NumericType::Float32)));
    let (data, grid) = cloud(&mut rng, &layout, [1, 1_000, 0], 5, Some(400));
    let (plain, general) = both(&layout, &data, grid);
    assert!(plain.is_none());
    assert!(
        matches!(general, Err(PointsError::BadRing { .. })),
        "{general:?}"
    );
}

#[test]
fn only_plain_layouts_take_the_plain_loop() {
    let attributes = |layout: &PointLayout| Attributes {
        intensity: layout.intensity.as_ref().map(|f| f.plan),
        ring: layout.ring.as_ref().map(|f| f.plan),
        time: None,
        label: None,
        kept_indices: false,
    };
    let nuscenes = layout(20, Some(12), Some(plan(16, NumericType::Float32)));
    assert!(Plain::of(&nuscenes, &attributes(&nuscenes)).is_some());
    let indices = Attributes {
        kept_indices: true,
        ..attributes(&nuscenes)
    };
    assert!(Plain::of(&nuscenes, &indices).is_none());
    let mut big = nuscenes.clone();
    big.xyz[1].endianness = Endianness::Big;
    assert!(Plain::of(&big, &attributes(&big)).is_none());
    let byte_intensity = layout(16, None, None);
    let mut byte_intensity = byte_intensity;
    byte_intensity.intensity = Some(named("intensity", plan(12, NumericType::Uint8)));
    assert!(Plain::of(&byte_intensity, &attributes(&byte_intensity)).is_none());
    let f64_ring = layout(24, Some(12), Some(plan(16, NumericType::Float64)));
    assert!(Plain::of(&f64_ring, &attributes(&f64_ring)).is_none());
}

#[test]
fn the_plain_loop_converts_times_as_the_general_loop() {
    let mut rng = TestRng(0x7F4A_7C15);
    let stamp = Stamp::from_nanos(1_700_000_000_123_456_789);
    let conversion = |offset, numeric, unit, reference| {
        TimeConversion::new(plan(offset, numeric), unit, reference, stamp)
    };
    let (seconds, relative) = (TimeUnit::Seconds, TimeReference::RelativeToStamp);
    let cases = [
        // velodyne's PointcloudXYZIRT: ring UINT16 at 16, time FLOAT32 s at 18.
        (
            layout(22, Some(12), Some(plan(16, NumericType::Uint16))),
            conversion(18, NumericType::Float32, seconds, relative),
        ),
        // PCL-aligned, no ring, time FLOAT32 s at 16.
        (
            layout(32, Some(12), None),
            conversion(16, NumericType::Float32, seconds, relative),
        ),
        // Ouster-like: time UINT32 ns at 20, ring UINT16 at 26.
        (
            layout(48, Some(16), Some(plan(26, NumericType::Uint16))),
            conversion(20, NumericType::Uint32, TimeUnit::Nanoseconds, relative),
        ),
        // Hesai-like: absolute FLOAT64 seconds at 24, ring UINT16 at 32.
        (
            layout(48, Some(16), Some(plan(32, NumericType::Uint16))),
            conversion(24, NumericType::Float64, seconds, TimeReference::Absolute),
        ),
        // FLOAT32 read as microseconds.
        (
            layout(24, None, None),
            conversion(16, NumericType::Float32, TimeUnit::Microseconds, relative),
        ),
    ];
    for (layout, time) in &cases {
        let field = (time.field.offset, None, time.field.numeric);
        for (shape, nan_every) in [([1, 4_000, 0], 0), ([8, 500, 6], 5), ([2, 3, 0], 1)] {
            let (data, grid) = cloud_timed(&mut rng, layout, shape, nan_every, None, Some(field));
            let (plain, general) = both_timed(layout, &data, grid, Some(*time));
            let (plain, general) = (plain.expect("times are finite"), general.unwrap());
            let times = |p: &Points| p.time_offset.as_deref().map(bits);
            assert!(plain.time_offset.is_some());
            assert_eq!(times(&plain), times(&general), "{time:?}");
            assert_eq!(plain.max_abs_time.to_bits(), general.max_abs_time.to_bits());
            assert_eq!(
                bits(plain.xyz.as_flattened()),
                bits(general.xyz.as_flattened())
            );
            assert_eq!(bits(&plain.intensity), bits(&general.intensity));
            assert_eq!(plain.ring, general.ring);
            assert_eq!(plain.dropped, general.dropped);
        }
    }
    // A kept point whose time is not finite: the general loop names it.
    let (layout, time) = &cases[0];
    let field = Some((18, Some(300), NumericType::Float32));
    let (data, grid) = cloud_timed(&mut rng, layout, [1, 900, 0], 4, None, field);
    let (plain, general) = both_timed(layout, &data, grid, Some(*time));
    assert!(plain.is_none());
    assert!(
        matches!(general, Err(PointsError::BadTime { .. })),
        "{general:?}"
    );
    // Other time types and byte orders take the general loop.
    let attributes = |time| Attributes {
        intensity: None,
        ring: None,
        time: Some(time),
        label: None,
        kept_indices: false,
    };
    for numeric in [NumericType::Int8, NumericType::Uint16, NumericType::Int32] {
        let other = conversion(18, numeric, TimeUnit::Nanoseconds, relative);
        assert!(
            Plain::of(layout, &attributes(other)).is_none(),
            "{numeric:?}"
        );
    }
    let mut big = conversion(18, NumericType::Float32, seconds, relative);
    big.field.endianness = Endianness::Big;
    assert!(Plain::of(layout, &attributes(big)).is_none());
}
