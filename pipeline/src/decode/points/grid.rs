//! [`Grid`]: where the points of a message lie in its data, rows of points a row step
//! apart, as each dialect checks it against the data; [`rows`] walks it.

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
