//! [`decode_core`]: a layout applied to every point of a checked grid, by the plain loop
//! where the layout allows it and the general loop otherwise, with a float time field's
//! unit resolved by the magnitude of its values.

use superflow_schemas::sensor::PointCloud;

use super::columns::Attributes;
use super::general::{AnyXyz, Float32Xyz, fill};
use super::plain::{Plain, fill_plain};
use crate::decode::context::Ctx;
use crate::decode::points::cloud::DecodedCloud;
use crate::decode::points::error::PointsError;
use crate::decode::points::field::{Endianness, NumericType};
use crate::decode::points::grid::Grid;
use crate::decode::points::layout::PointLayout;
use crate::decode::points::time::{
    TimeConversion, TimeFieldSpec, TimeReference, TimeRule, TimeUnit, magnitude_rule,
};

/// Applies `layout` to every point of `data` (laid out as `grid`, already checked);
/// with `kept_indices`, records the message index of each kept point.
///
/// A float time field under inference is first read as relative seconds (velodyne, the
/// common case) while its largest magnitude is tracked; only when that shows absolute
/// values is the time column read again, with the inferred unit and the stamp
/// subtracted. The decision thus rests on the kept points only, and costs no extra pass
/// over relative clouds.
pub(in crate::decode::points) fn decode_core(
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
