//! The per-point loop: reads every point of a checked [`Grid`] with a [`PointLayout`],
//! drops the non-finite ones, converts ring and time, and resolves a float time field's
//! unit by the magnitude of its values.
//!
//! Bottom-up: `columns` (what a loop reads and fills), `general` (the loop for any
//! layout) and `plain` (the branch-free loop for the usual layouts, which must give the
//! general loop's result), then `apply` ([`decode_core`], which picks the loop).
//!
//! [`Grid`]: super::grid::Grid
//! [`PointLayout`]: super::layout::PointLayout

mod apply;
mod columns;
mod general;
mod plain;
#[cfg(test)]
mod tests;

pub(super) use apply::decode_core;
