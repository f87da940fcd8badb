//! The branch-free per-point loop ([`fill_plain`]) for the usual little-endian layouts
//! (FLOAT32 coordinates and intensity, a FLOAT32 or UINT16 ring, a FLOAT32, FLOAT64 or
//! UINT32 time); it gives the general loop's result, or `None` to hand the cloud to it.

use super::columns::{Attributes, Points};
use crate::decode::points::field::{Endianness, FieldPlan, NumericType};
use crate::decode::points::grid::{Grid, rows};
use crate::decode::points::layout::PointLayout;
use crate::decode::points::time::TimeConversion;

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
pub(super) struct Plain {
    xyz: [usize; 3],
    intensity: Option<usize>,
    ring: Option<PlainRing>,
    time: Option<TimeConversion>,
}

impl Plain {
    /// The plain offsets of `layout` with `attributes`, when it is one.
    pub(super) fn of(layout: &PointLayout, attributes: &Attributes<'_>) -> Option<Plain> {
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
///
/// [`ring_index`]: super::general::ring_index
#[inline(always)]
pub(super) fn float32_ring(v: f32) -> (u16, bool) {
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
///
/// [`fill`]: super::general::fill
pub(super) fn fill_plain(
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
