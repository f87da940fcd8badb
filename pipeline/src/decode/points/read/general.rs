//! The general per-point loop ([`fill`]): any layout, any field types and byte orders,
//! labels and message indices; it names the first point whose ring or time cannot be
//! converted.

use super::columns::{Attributes, Points};
use crate::decode::context::Ctx;
use crate::decode::points::error::PointsError;
use crate::decode::points::field::{Endianness, FieldPlan, NamedField, NumericType, array};
use crate::decode::points::grid::{Grid, rows};
use crate::decode::points::label::bad_label;
use crate::decode::points::layout::PointLayout;

/// Reads the position of a point. Implemented once for any layout ([`AnyXyz`]) and once,
/// without a type dispatch per point, for the usual FLOAT32 coordinates ([`Float32Xyz`]).
pub(super) trait XyzReader: Copy {
    fn xyz(self, point: &[u8]) -> [f32; 3];
}

/// FLOAT32 `x`, `y`, `z` at these offsets, big-endian when `BIG`.
#[derive(Debug, Clone, Copy)]
pub(super) struct Float32Xyz<const BIG: bool>(pub(super) [usize; 3]);

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
pub(super) struct AnyXyz(pub(super) [FieldPlan; 3]);

impl XyzReader for AnyXyz {
    #[inline(always)]
    fn xyz(self, point: &[u8]) -> [f32; 3] {
        self.0.map(|f| f.read(point) as f32)
    }
}

/// The per-point loop: reads every point of `data` (laid out as `grid`), drops the
/// non-finite ones and converts the attributes of the others.
#[inline(always)]
pub(super) fn fill<X: XyzReader>(
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
pub(super) fn ring_index(plan: FieldPlan, point: &[u8]) -> Option<u16> {
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
