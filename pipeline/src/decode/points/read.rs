//! The per-point loop: reads every point of a checked [`Grid`] with a [`PointLayout`],
//! drops the non-finite ones, converts ring and time, and resolves a float time field's
//! unit by the magnitude of its values.

use super::cloud::DecodedCloud;
use super::error::PointsError;
use super::field::{Endianness, FieldPlan, NamedField, NumericType, array};
use super::label::{LabelPlan, bad_label};
use super::layout::PointLayout;
use super::time::{
    TimeConversion, TimeFieldSpec, TimeReference, TimeRule, TimeUnit, magnitude_rule,
};
use crate::decode::context::Ctx;
use superflow_schemas::sensor::PointCloud;

/// Where the points lie in `data`: `rows` rows `row_step` bytes apart, each starting
/// with `width` points. Checked against the data's length before use.
#[derive(Debug, Clone, Copy)]
pub(super) struct Grid {
    /// Rows to visit.
    pub(super) rows: usize,
    /// Points per row.
    pub(super) width: usize,
    /// Bytes from one row's start to the next.
    pub(super) row_step: usize,
}

/// The bytes of each row's points.
pub(super) fn rows(data: &[u8], grid: Grid, point_step: usize) -> impl Iterator<Item = &[u8]> {
    let row_len = grid.width * point_step;
    (0..grid.rows).map(move |r| {
        let start = r * grid.row_step;
        data.get(start..start + row_len).unwrap_or(&[])
    })
}

/// Reads the position of a point. Implemented once for any layout ([`AnyXyz`]) and once,
/// without a type dispatch per point, for the usual FLOAT32 coordinates ([`Float32Xyz`]).
trait XyzReader: Copy {
    fn xyz(self, point: &[u8]) -> [f32; 3];
}

/// FLOAT32 `x`, `y`, `z` at these offsets, big-endian when `BIG`.
#[derive(Debug, Clone, Copy)]
struct Float32Xyz<const BIG: bool>([usize; 3]);

impl<const BIG: bool> XyzReader for Float32Xyz<BIG> {
    #[inline(always)]
    fn xyz(self, point: &[u8]) -> [f32; 3] {
        self.0.map(|offset| {
            let bytes = array::<4>(point, offset);
            if BIG {
                f32::from_be_bytes(bytes)
            } else {
                f32::from_le_bytes(bytes)
            }
        })
    }
}

/// Coordinates of any type.
#[derive(Debug, Clone, Copy)]
struct AnyXyz([FieldPlan; 3]);

impl XyzReader for AnyXyz {
    #[inline(always)]
    fn xyz(self, point: &[u8]) -> [f32; 3] {
        self.0.map(|f| f.read(point) as f32)
    }
}

/// The optional attributes to read from each kept point.
#[derive(Debug, Clone, Copy)]
struct Attributes<'a> {
    intensity: Option<FieldPlan>,
    ring: Option<FieldPlan>,
    time: Option<TimeConversion>,
    label: Option<&'a LabelPlan>,
    /// Record the message index of each kept point.
    kept_indices: bool,
}

/// The columns of the kept points.
#[derive(Debug)]
struct Points {
    xyz: Vec<[f32; 3]>,
    intensity: Vec<f32>,
    ring: Option<Vec<u16>>,
    time_offset: Option<Vec<f32>>,
    label: Option<Vec<u32>>,
    kept_indices: Option<Vec<u32>>,
    dropped: usize,
    /// The largest `|value|` of the time field over the kept points (0 without one).
    max_abs_time: f64,
}

/// The per-point loop: reads every point of `data` (laid out as `grid`), drops the
/// non-finite ones and converts the attributes of the others.
#[inline(always)]
fn fill<X: XyzReader>(
    ctx: &Ctx<'_>,
    layout: &PointLayout,
    data: &[u8],
    grid: Grid,
    capacity: usize,
    position: X,
    attributes: Attributes<'_>,
) -> Result<Points, PointsError> {
    let step = layout.point_step.max(1);
    let Attributes {
        intensity: intensity_plan,
        ring: ring_plan,
        time,
        label: label_plan,
        kept_indices,
    } = attributes;
    // Columns of `capacity` (the number of points) zeros, written in place and cut to the
    // kept points at the end: no capacity checks or growth calls in the loop.
    let sized = |wanted: bool| if wanted { capacity } else { 0 };
    let mut xyz = vec![[0f32; 3]; capacity];
    let mut intensity = vec![0f32; capacity];
    let mut ring = vec![0u16; sized(ring_plan.is_some())];
    let mut time_offset = vec![0f32; sized(time.is_some())];
    let mut label = vec![0u32; sized(label_plan.is_some())];
    let mut indices = vec![0u32; sized(kept_indices)];
    let mut kept = 0usize;
    let mut index = 0usize;
    let mut max_abs_time = 0.0f64;

    for row in rows(data, grid, step) {
        for p in row.chunks_exact(step) {
            let i = index;
            index += 1;
            let [x, y, z] = position.xyz(p);
            if !(x.is_finite() && y.is_finite() && z.is_finite()) {
                continue;
            }
            if let Some(slot) = xyz.get_mut(kept) {
                *slot = [x, y, z];
            }
            if let (Some(plan), Some(slot)) = (intensity_plan, intensity.get_mut(kept)) {
                *slot = read_f32(plan, p);
            }
            if let (Some(plan), Some(slot)) = (ring_plan, ring.get_mut(kept)) {
                *slot = ring_index(plan, p)
                    .ok_or_else(|| bad_value(ctx, layout.ring.as_ref(), i, plan.read(p), true))?;
            }
            if let (Some(conv), Some(slot)) = (time, time_offset.get_mut(kept)) {
                let value = conv.field.read(p);
                max_abs_time = max_abs_time.max(value.abs());
                let offset = conv.offset_secs(value) as f32;
                if !offset.is_finite() {
                    return Err(bad_value(ctx, layout.time(), i, value, false));
                }
                *slot = offset;
            }
            if let (Some(plan), Some(slot)) = (label_plan, label.get_mut(kept)) {
                *slot = plan.read(p).map_err(|value| {
                    bad_label(ctx.frame_id, ctx.stamp, &plan.field.name, i, value)
                })?;
            }
            if let Some(slot) = indices.get_mut(kept) {
                // A message holds fewer than 2^32 points of at least one byte each
                // (MCAP messages and CDR sequences count in u32).
                *slot = i as u32;
            }
            kept += 1;
        }
    }

    xyz.truncate(kept);
    intensity.truncate(kept);
    ring.truncate(kept);
    time_offset.truncate(kept);
    label.truncate(kept);
    indices.truncate(kept);
    Ok(Points {
        xyz,
        intensity,
        ring: ring_plan.map(|_| ring),
        time_offset: time.map(|_| time_offset),
        label: label_plan.map(|_| label),
        kept_indices: kept_indices.then_some(indices),
        dropped: index - kept,
        max_abs_time,
    })
}

/// A ring column the plain loop reads: little-endian FLOAT32 (nuScenes) or UINT16
/// (velodyne, PCL), at this offset.
#[derive(Debug, Clone, Copy)]
enum PlainRing {
    Float32(usize),
    Uint16(usize),
}

/// The offsets of a layout the plain loop reads: little-endian FLOAT32 `x`, `y`, `z`
/// and intensity (if any), a [`PlainRing`] (if any), a little-endian FLOAT32, FLOAT64 or
/// UINT32 time with its conversion (if any: velodyne's and PCL's `time`, Ouster's and
/// Livox's nanoseconds, Hesai's absolute seconds), and nothing else to convert (no
/// label or message indices).
#[derive(Debug, Clone, Copy)]
struct Plain {
    xyz: [usize; 3],
    intensity: Option<usize>,
    ring: Option<PlainRing>,
    time: Option<TimeConversion>,
}

impl Plain {
    /// The plain offsets of `layout` with `attributes`, when it is one.
    fn of(layout: &PointLayout, attributes: &Attributes<'_>) -> Option<Plain> {
        let f32_le = |plan: FieldPlan| {
            (plan.numeric == NumericType::Float32 && plan.endianness == Endianness::Little)
                .then_some(plan.offset)
        };
        if attributes.label.is_some() || attributes.kept_indices {
            return None;
        }
        let time = match attributes.time {
            None => None,
            Some(conversion) => {
                time_kind(conversion.field)?;
                Some(conversion)
            }
        };
        let [x, y, z] = layout.xyz;
        let xyz = [f32_le(x)?, f32_le(y)?, f32_le(z)?];
        let intensity = match attributes.intensity {
            Some(plan) => Some(f32_le(plan)?),
            None => None,
        };
        let ring = match attributes.ring {
            None => None,
            Some(plan) if plan.endianness != Endianness::Little => return None,
            Some(plan) => Some(match plan.numeric {
                NumericType::Float32 => PlainRing::Float32(plan.offset),
                NumericType::Uint16 => PlainRing::Uint16(plan.offset),
                _ => return None,
            }),
        };
        Some(Plain {
            xyz,
            intensity,
            ring,
            time,
        })
    }
}

/// The ring index of a FLOAT32 `v` as [`ring_index`] finds it, and whether it is one,
/// computed without branches: the plain loop reads it for every point, kept or not.
#[inline(always)]
fn float32_ring(v: f32) -> (u16, bool) {
    const TWO_23: f32 = 8_388_608.0;
    let shifted = v + TWO_23;
    let ok = (0.0..=65_535.0).contains(&v) & (shifted - TWO_23 == v);
    (shifted.to_bits() as u16, ok)
}

/// Ring kinds of [`fill_plain_as`] (a const parameter, so that each has its own loop).
const NO_RING: u8 = 0;
const FLOAT32_RING: u8 = 1;
const UINT16_RING: u8 = 2;

/// Time kinds of [`fill_plain_as`], by the field's type.
const NO_TIME: u8 = 0;
const FLOAT32_TIME: u8 = 1;
const FLOAT64_TIME: u8 = 2;
const UINT32_TIME: u8 = 3;

/// The time kind the plain loop reads `field` as: a little-endian FLOAT32, FLOAT64 or
/// UINT32; `None` for any other.
fn time_kind(field: FieldPlan) -> Option<u8> {
    if field.endianness != Endianness::Little {
        return None;
    }
    match field.numeric {
        NumericType::Float32 => Some(FLOAT32_TIME),
        NumericType::Float64 => Some(FLOAT64_TIME),
        NumericType::Uint32 => Some(UINT32_TIME),
        _ => None,
    }
}

/// [`fill`] for a [`Plain`] layout (the usual FLOAT32 clouds: nuScenes, KITTI) in one
/// loop without a branch per point: each point is written at the next kept slot, and
/// the slot is kept when its coordinates are finite, so clouds with scattered
/// non-finite points cost no mispredictions. `None` when a kept point's ring is not a
/// ring index or its time not finite: the caller then runs [`fill`], which names it.
///
/// It exists because the general loop branches per point on its per-field options and
/// on the ring's early exit, and the usual layouts (x, y, z, intensity, ring, all
/// FLOAT32) need none of those branches.
fn fill_plain(
    data: &[u8],
    grid: Grid,
    step: usize,
    capacity: usize,
    plain: Plain,
) -> Option<Points> {
    let args = (data, grid, step, capacity, plain);
    match plain.time.map(|conversion| time_kind(conversion.field)) {
        None => fill_plain_timed::<NO_TIME>(args),
        Some(Some(FLOAT32_TIME)) => fill_plain_timed::<FLOAT32_TIME>(args),
        Some(Some(FLOAT64_TIME)) => fill_plain_timed::<FLOAT64_TIME>(args),
        Some(Some(UINT32_TIME)) => fill_plain_timed::<UINT32_TIME>(args),
        // `Plain::of` admits no other time field.
        Some(_) => None,
    }
}

/// [`fill_plain`] with a time column of kind `TIME`.
fn fill_plain_timed<const TIME: u8>(args: PlainArgs<'_>) -> Option<Points> {
    let plain = args.4;
    match (plain.intensity.is_some(), plain.ring) {
        (true, None) => fill_plain_as::<true, NO_RING, TIME>(args),
        (true, Some(PlainRing::Float32(_))) => fill_plain_as::<true, FLOAT32_RING, TIME>(args),
        (true, Some(PlainRing::Uint16(_))) => fill_plain_as::<true, UINT16_RING, TIME>(args),
        (false, None) => fill_plain_as::<false, NO_RING, TIME>(args),
        (false, Some(PlainRing::Float32(_))) => fill_plain_as::<false, FLOAT32_RING, TIME>(args),
        (false, Some(PlainRing::Uint16(_))) => fill_plain_as::<false, UINT16_RING, TIME>(args),
    }
}

/// What [`fill_plain`] reads: the data, its grid, the point step, the number of points
/// and the offsets.
type PlainArgs<'a> = (&'a [u8], Grid, usize, usize, Plain);

/// [`fill_plain`] for one combination of fields: with an intensity when `INTENSITY`, a
/// ring of kind `RING`, a time column of kind `TIME`.
fn fill_plain_as<const INTENSITY: bool, const RING: u8, const TIME: u8>(
    (data, grid, step, capacity, plain): PlainArgs<'_>,
) -> Option<Points> {
    let intensity_at = plain.intensity.unwrap_or(0);
    let ring_at = match plain.ring {
        Some(PlainRing::Float32(offset) | PlainRing::Uint16(offset)) => offset,
        None => 0,
    };
    let ring_width = if RING == UINT16_RING { 2 } else { 4 };
    let time_width = if TIME == FLOAT64_TIME { 8 } else { 4 };
    // Every read below lies within its point, checked here once instead of at each read
    // (a layout whose fields overrun the point step takes the general loop).
    let fits = |offset: usize, width: usize| offset + width <= step;
    let within = plain.xyz.iter().all(|&o| fits(o, 4))
        && (!INTENSITY || fits(intensity_at, 4))
        && (RING == NO_RING || fits(ring_at, ring_width))
        && (TIME == NO_TIME || plain.time.is_some_and(|c| fits(c.field.offset, time_width)));
    if !within {
        return None;
    }
    // Called below only with one point (`step` bytes) and an offset checked above.
    #[allow(unsafe_code)]
    let f32_at = |p: &[u8], offset: usize| {
        // SAFETY: `offset + 4 <= step == p.len()` (`within`).
        f32::from_le_bytes(unsafe { bytes_at::<4>(p, offset) })
    };
    let mut xyz = vec![[0f32; 3]; capacity];
    let mut intensity = vec![0f32; capacity];
    let mut ring = vec![0u16; if RING == NO_RING { 0 } else { capacity }];
    let conversion = plain.time;
    let time_at = conversion.map_or(0, |c| c.field.offset);
    let mut time = vec![0f32; if TIME == NO_TIME { 0 } else { capacity }];
    let mut max_abs_time = 0f64;
    let mut rings_ok = true;
    let mut times_ok = true;
    let mut kept = 0usize;
    let mut index = 0usize;
    for row in rows(data, grid, step) {
        for p in row.chunks_exact(step) {
            if index == capacity {
                break;
            }
            index += 1;
            let position = plain.xyz.map(|offset| f32_at(p, offset));
            let finite = position.iter().all(|v| v.is_finite());
            // `kept` < `index` <= `capacity`: every slot exists.
            xyz[kept] = position;
            if INTENSITY {
                intensity[kept] = f32_at(p, intensity_at);
            }
            if RING == FLOAT32_RING {
                let (value, ok) = float32_ring(f32_at(p, ring_at));
                ring[kept] = value;
                rings_ok &= ok | !finite;
            } else if RING == UINT16_RING {
                // SAFETY: `ring_at + 2 <= step == p.len()` (`within`).
                #[allow(unsafe_code)]
                let bytes = unsafe { bytes_at::<2>(p, ring_at) };
                ring[kept] = u16::from_le_bytes(bytes);
            }
            if let (true, Some(conversion)) = (TIME != NO_TIME, conversion) {
                // The value as `FieldPlan::read` widens it, converted as the general
                // loop converts it.
                #[allow(unsafe_code)]
                let value = match TIME {
                    FLOAT32_TIME => f64::from(f32_at(p, time_at)),
                    // SAFETY: `time_at + 8 <= step == p.len()` (`within`).
                    FLOAT64_TIME => f64::from_le_bytes(unsafe { bytes_at::<8>(p, time_at) }),
                    // SAFETY: `time_at + 4 <= step == p.len()` (`within`).
                    _ => f64::from(u32::from_le_bytes(unsafe { bytes_at::<4>(p, time_at) })),
                };
                let offset = conversion.offset_secs(value) as f32;
                time[kept] = offset;
                times_ok &= offset.is_finite() | !finite;
                let magnitude = if finite { value.abs() } else { 0.0 };
                max_abs_time = max_abs_time.max(magnitude);
            }
            kept += usize::from(finite);
        }
    }
    if !(rings_ok && times_ok) {
        return None;
    }
    xyz.truncate(kept);
    intensity.truncate(kept);
    ring.truncate(kept);
    time.truncate(kept);
    Some(Points {
        xyz,
        intensity,
        ring: plain.ring.map(|_| ring),
        time_offset: plain.time.map(|_| time),
        label: None,
        kept_indices: None,
        dropped: index - kept,
        max_abs_time,
    })
}

/// The `N` bytes at `offset` of `point`, without a bounds check ([`fill_plain_as`]
/// checks every field of the layout against the point step once per sweep).
///
/// # Safety
/// `offset + N <= point.len()`.
#[inline(always)]
#[allow(unsafe_code)]
unsafe fn bytes_at<const N: usize>(point: &[u8], offset: usize) -> [u8; N] {
    debug_assert!(offset + N <= point.len());
    // SAFETY: the caller guarantees `offset + N <= point.len()`; the read is unaligned.
    unsafe {
        point
            .as_ptr()
            .add(offset)
            .cast::<[u8; N]>()
            .read_unaligned()
    }
}

/// The field's value when it is the usual little-endian FLOAT32, read without the round
/// trip through `f64`; `None` for any other type.
#[inline(always)]
fn le_f32(plan: FieldPlan, point: &[u8]) -> Option<f32> {
    (plan.numeric == NumericType::Float32 && plan.endianness == Endianness::Little)
        .then(|| f32::from_le_bytes(array::<4>(point, plan.offset)))
}

/// The field's value as `f32`: `plan.read(point) as f32` (the same value, read directly
/// for a little-endian FLOAT32).
#[inline(always)]
fn read_f32(plan: FieldPlan, point: &[u8]) -> f32 {
    le_f32(plan, point).unwrap_or_else(|| plan.read(point) as f32)
}

/// The ring index of `point`: its value when that is an integer in `0..=65535`, else
/// `None`.
///
/// Any type goes through `f64` and a saturating cast (NaN gives 0): the value is a ring
/// index exactly when it survives the round trip. The usual little-endian FLOAT32 ring
/// stays in `f32` (which holds every `u16` exactly): in range, `v + 2²³` is `v` rounded
/// to an integer plus 2²³, so `v` is an integer when removing 2²³ gives it back, and the
/// integer is the sum's low mantissa bits. Same answer, without the two conversions and
/// the saturating cast (half the per-point loop's time on such clouds).
#[inline(always)]
fn ring_index(plan: FieldPlan, point: &[u8]) -> Option<u16> {
    if let Some(v) = le_f32(plan, point) {
        const TWO_23: f32 = 8_388_608.0;
        let shifted = v + TWO_23;
        let integer = (0.0..=65_535.0).contains(&v) && shifted - TWO_23 == v;
        return integer.then_some(shifted.to_bits() as u16);
    }
    let value = plan.read(point);
    let index = value as u16;
    (f64::from(index) == value).then_some(index)
}

/// The error for a ring (`ring` true) or time value that cannot be converted.
#[cold]
fn bad_value(
    ctx: &Ctx<'_>,
    field: Option<&NamedField>,
    index: usize,
    value: f64,
    ring: bool,
) -> PointsError {
    let frame_id = ctx.frame_id.to_string();
    let stamp = ctx.stamp;
    let field = field.map_or_else(String::new, |f| f.name.clone());
    if ring {
        PointsError::BadRing {
            frame_id,
            stamp,
            field,
            index,
            value,
        }
    } else {
        PointsError::BadTime {
            frame_id,
            stamp,
            field,
            index,
            value,
        }
    }
}

/// Applies `layout` to every point of `data` (laid out as `grid`, already checked);
/// with `kept_indices`, records the message index of each kept point.
///
/// A float time field under inference is first read as relative seconds (velodyne, the
/// common case) while its largest magnitude is tracked; only when that shows absolute
/// values is the time column read again, with the inferred unit and the stamp
/// subtracted. The decision thus rests on the kept points only, and costs no extra pass
/// over relative clouds.
pub(super) fn decode_core(
    ctx: &Ctx<'_>,
    layout: &PointLayout,
    data: &[u8],
    grid: Grid,
    kept_indices: bool,
) -> Result<DecodedCloud, PointsError> {
    // A validated layout has a field inside every point, so this is at least 1.
    let step = layout.point_step.max(1);
    let capacity = grid.rows.saturating_mul(grid.width).min(data.len() / step);
    let [px, py, pz] = layout.xyz;
    let float32 = [px, py, pz]
        .iter()
        .all(|f| f.numeric == NumericType::Float32);
    let offsets = [px.offset, py.offset, pz.offset];
    let run = |attributes: Attributes<'_>| match (float32, px.endianness) {
        (true, Endianness::Little) => {
            let position = Float32Xyz::<false>(offsets);
            fill(ctx, layout, data, grid, capacity, position, attributes)
        }
        (true, Endianness::Big) => {
            let position = Float32Xyz::<true>(offsets);
            fill(ctx, layout, data, grid, capacity, position, attributes)
        }
        (false, _) => fill(
            ctx,
            layout,
            data,
            grid,
            capacity,
            AnyXyz(layout.xyz),
            attributes,
        ),
    };

    let (first_unit, first_reference) = match layout.time.as_ref().map(|t| t.rule) {
        Some(TimeRule::Fixed(unit, reference)) => (unit, reference),
        _ => (TimeUnit::Seconds, TimeReference::RelativeToStamp),
    };
    let time_conversion = |unit, reference| {
        layout
            .time
            .as_ref()
            .map(|t| TimeConversion::new(t.field.plan, unit, reference, ctx.stamp))
    };
    let attributes = Attributes {
        intensity: layout.intensity.as_ref().map(|f| f.plan),
        ring: layout.ring.as_ref().map(|f| f.plan),
        time: time_conversion(first_unit, first_reference),
        label: layout.label.as_ref(),
        kept_indices,
    };
    let plain = Plain::of(layout, &attributes)
        .and_then(|plain| fill_plain(data, grid, step, capacity, plain));
    let mut points = match plain {
        Some(points) => points,
        None => run(attributes)?,
    };

    let time_field = match &layout.time {
        None => None,
        Some(plan) => {
            let (unit, reference) = match plan.rule {
                TimeRule::Fixed(unit, reference) => (unit, reference),
                TimeRule::ByMagnitude => magnitude_rule(points.max_abs_time),
            };
            if (unit, reference) != (first_unit, first_reference) {
                points.time_offset = run(Attributes {
                    intensity: None,
                    ring: None,
                    time: time_conversion(unit, reference),
                    label: None,
                    kept_indices: false,
                })?
                .time_offset;
            }
            Some(TimeFieldSpec {
                name: plan.field.name.clone(),
                unit,
                reference,
            })
        }
    };

    Ok(DecodedCloud {
        cloud: PointCloud {
            stamp: ctx.stamp,
            frame_id: ctx.frame_id.to_string(),
            xyz: points.xyz,
            intensity: points.intensity,
            ring: points.ring,
            time_offset_secs: points.time_offset,
            label: points.label,
        },
        dropped_non_finite: points.dropped,
        kept_indices: points.kept_indices,
        has_intensity: layout.intensity.is_some(),
        time_field,
    })
}

#[cfg(test)]
mod ring_tests {
    use super::*;

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
}

#[cfg(test)]
mod plain_tests {
    use super::*;
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
                let (data, grid) =
                    cloud_timed(&mut rng, layout, shape, nan_every, None, Some(field));
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
}
