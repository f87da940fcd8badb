//! The leaf types of a point layout: the element types of both numbering schemes
//! ([`NumericType`]), the byte order ([`Endianness`]), and how one field is read in a
//! point ([`FieldPlan`], [`NamedField`]).

/// Element type of a field, independent of the dialect's numbering.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Hash)]
pub enum NumericType {
    /// `i8`.
    Int8,
    /// `u8`.
    Uint8,
    /// `i16`.
    Int16,
    /// `u16`.
    Uint16,
    /// `i32`.
    Int32,
    /// `u32`.
    Uint32,
    /// `f32`.
    Float32,
    /// `f64`.
    Float64,
}

impl NumericType {
    /// Size of one element in bytes.
    pub const fn size(self) -> usize {
        match self {
            NumericType::Int8 | NumericType::Uint8 => 1,
            NumericType::Int16 | NumericType::Uint16 => 2,
            NumericType::Int32 | NumericType::Uint32 | NumericType::Float32 => 4,
            NumericType::Float64 => 8,
        }
    }

    /// Whether the type is a floating-point type.
    pub const fn is_float(self) -> bool {
        matches!(self, NumericType::Float32 | NumericType::Float64)
    }

    /// The type of a ROS `PointField.datatype` (INT8 = 1 ... FLOAT64 = 8).
    pub const fn from_ros2(datatype: u8) -> Option<Self> {
        Some(match datatype {
            1 => NumericType::Int8,
            2 => NumericType::Uint8,
            3 => NumericType::Int16,
            4 => NumericType::Uint16,
            5 => NumericType::Int32,
            6 => NumericType::Uint32,
            7 => NumericType::Float32,
            8 => NumericType::Float64,
            _ => return None,
        })
    }

    /// The type of a Foxglove `PackedElementField.type` (UINT8 = 1, INT8 = 2, ...,
    /// FLOAT64 = 8; 0 is UNKNOWN).
    pub const fn from_foxglove(numeric_type: i32) -> Option<Self> {
        Some(match numeric_type {
            1 => NumericType::Uint8,
            2 => NumericType::Int8,
            3 => NumericType::Uint16,
            4 => NumericType::Int16,
            5 => NumericType::Uint32,
            6 => NumericType::Int32,
            7 => NumericType::Float32,
            8 => NumericType::Float64,
            _ => return None,
        })
    }
}

/// Byte order of multi-byte values.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Hash)]
pub enum Endianness {
    /// Least significant byte first (Foxglove; ROS `is_bigendian = false`).
    Little,
    /// Most significant byte first (ROS `is_bigendian = true`).
    Big,
}

/// Where and how one field is read in a point.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Hash)]
pub struct FieldPlan {
    /// Byte offset in the point.
    pub offset: usize,
    /// Element type.
    pub numeric: NumericType,
    /// Byte order.
    pub endianness: Endianness,
}

impl FieldPlan {
    /// The field's value in `point` (the bytes of one point), widened to `f64` (exact for
    /// every type). Reads 0 if the field does not fit, which a validated
    /// [`PointLayout`](super::PointLayout) rules out.
    #[inline(always)]
    pub fn read(self, point: &[u8]) -> f64 {
        macro_rules! get {
            ($t:ty) => {{
                let bytes = array::<{ size_of::<$t>() }>(point, self.offset);
                match self.endianness {
                    Endianness::Little => <$t>::from_le_bytes(bytes),
                    Endianness::Big => <$t>::from_be_bytes(bytes),
                }
            }};
        }
        match self.numeric {
            NumericType::Int8 => f64::from(get!(i8)),
            NumericType::Uint8 => f64::from(get!(u8)),
            NumericType::Int16 => f64::from(get!(i16)),
            NumericType::Uint16 => f64::from(get!(u16)),
            NumericType::Int32 => f64::from(get!(i32)),
            NumericType::Uint32 => f64::from(get!(u32)),
            NumericType::Float32 => f64::from(get!(f32)),
            NumericType::Float64 => get!(f64),
        }
    }
}

/// `N` bytes of `point` at `offset`, zeros if they are not all there.
#[inline(always)]
pub(super) fn array<const N: usize>(point: &[u8], offset: usize) -> [u8; N] {
    point
        .get(offset..)
        .and_then(<[u8]>::first_chunk::<N>)
        .copied()
        .unwrap_or([0; N])
}

/// A used field: its name and how to read it.
#[derive(Debug, Clone, PartialEq, Eq, Hash)]
pub struct NamedField {
    /// The field's name in the message.
    pub name: String,
    /// Where and how to read it.
    pub plan: FieldPlan,
}
