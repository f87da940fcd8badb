//! [`Codec`]: the compression codecs the decoder supports, named by format strings,
//! magic bytes and errors.

use std::fmt;

/// A compression codec the decoder supports.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Hash)]
pub enum Codec {
    /// JPEG (JFIF/EXIF), baseline or progressive.
    Jpeg,
    /// PNG.
    Png,
}

impl fmt::Display for Codec {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        f.write_str(match self {
            Codec::Jpeg => "JPEG",
            Codec::Png => "PNG",
        })
    }
}
