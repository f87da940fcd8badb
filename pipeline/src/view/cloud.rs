//! Point clouds as `foxglove.PointCloud`: packed little-endian fields, one column each.

use foxglove::messages::{
    PackedElementField, PointCloud, Timestamp, packed_element_field::NumericType,
};

/// One column of a cloud: its name and values, a point each.
#[derive(Debug, Clone, Copy)]
pub enum Column<'a> {
    /// `FLOAT32`.
    F32(&'a str, &'a [f32]),
    /// `UINT8`.
    U8(&'a str, &'a [u8]),
    /// `INT32`.
    I32(&'a str, &'a [i32]),
    /// `UINT32`.
    U32(&'a str, &'a [u32]),
}

impl Column<'_> {
    /// The field's name.
    pub fn name(&self) -> &str {
        match self {
            Column::F32(n, _) | Column::U8(n, _) | Column::I32(n, _) | Column::U32(n, _) => n,
        }
    }

    /// Its values.
    pub fn len(&self) -> usize {
        match self {
            Column::F32(_, v) => v.len(),
            Column::U8(_, v) => v.len(),
            Column::I32(_, v) => v.len(),
            Column::U32(_, v) => v.len(),
        }
    }

    /// Whether it has no values.
    pub fn is_empty(&self) -> bool {
        self.len() == 0
    }

    fn kind(&self) -> (NumericType, u32) {
        match self {
            Column::F32(..) => (NumericType::Float32, 4),
            Column::U8(..) => (NumericType::Uint8, 1),
            Column::I32(..) => (NumericType::Int32, 4),
            Column::U32(..) => (NumericType::Uint32, 4),
        }
    }

    fn put(&self, i: usize, out: &mut Vec<u8>) {
        match self {
            Column::F32(_, v) => out.extend_from_slice(&v[i].to_le_bytes()),
            Column::U8(_, v) => out.push(v[i]),
            Column::I32(_, v) => out.extend_from_slice(&v[i].to_le_bytes()),
            Column::U32(_, v) => out.extend_from_slice(&v[i].to_le_bytes()),
        }
    }
}

/// `xyz` and `columns` (each as long as `xyz`: the caller checks) packed as a Foxglove
/// point cloud in `frame_id`: `x`, `y`, `z` first, then the columns in order, each at an
/// offset aligned to its size.
pub fn point_cloud(
    ts: Timestamp,
    frame_id: &str,
    xyz: &[[f32; 3]],
    columns: &[Column<'_>],
) -> PointCloud {
    let mut fields = Vec::with_capacity(3 + columns.len());
    let mut offset = 0u32;
    for name in ["x", "y", "z"] {
        fields.push(PackedElementField {
            name: name.to_string(),
            offset,
            r#type: NumericType::Float32 as i32,
        });
        offset += 4;
    }
    let mut pads = Vec::with_capacity(columns.len());
    for column in columns {
        let (kind, size) = column.kind();
        let aligned = offset.next_multiple_of(size);
        pads.push((aligned - offset) as usize);
        fields.push(PackedElementField {
            name: column.name().to_string(),
            offset: aligned,
            r#type: kind as i32,
        });
        offset = aligned + size;
    }
    let stride = offset.next_multiple_of(4);
    let tail = (stride - offset) as usize;
    let mut data = Vec::with_capacity(xyz.len() * stride as usize);
    for (i, p) in xyz.iter().enumerate() {
        for c in p {
            data.extend_from_slice(&c.to_le_bytes());
        }
        for (column, pad) in columns.iter().zip(&pads) {
            data.extend(std::iter::repeat_n(0, *pad));
            column.put(i, &mut data);
        }
        data.extend(std::iter::repeat_n(0, tail));
    }
    PointCloud {
        timestamp: Some(ts),
        frame_id: frame_id.to_string(),
        pose: None,
        point_stride: stride,
        fields,
        data: data.into(),
    }
}

impl super::writer::ViewWriter {
    /// Writes `xyz` with `columns` as a point cloud on `topic` in `frame_id`, logged and
    /// stamped at `stamp`; a column of another length than `xyz` is an error.
    pub fn write_cloud(
        &mut self,
        topic: &str,
        stamp: superflow_schemas::Stamp,
        frame_id: &str,
        xyz: &[[f32; 3]],
        columns: &[Column<'_>],
    ) -> Result<(), super::writer::ViewError> {
        if let Some(c) = columns.iter().find(|c| c.len() != xyz.len()) {
            return Err(self.field_length(topic, c.name(), c.len(), xyz.len()));
        }
        let ts = self.timestamp(stamp)?;
        let cloud = point_cloud(ts, frame_id, xyz, columns);
        self.write(topic, stamp, &cloud)
    }
}
