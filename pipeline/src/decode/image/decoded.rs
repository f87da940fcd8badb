//! [`Decoded`]: the pixels a codec or a raw layout produced, before they become the
//! sensor model's [`Image`](superflow_schemas::sensor::Image).

use superflow_schemas::sensor::PixelFormat;

/// Decoded pixels before they become an [`Image`](superflow_schemas::sensor::Image).
#[derive(Debug)]
pub(super) struct Decoded {
    /// Width in pixels.
    pub(super) width: u32,
    /// Height in pixels.
    pub(super) height: u32,
    /// Size of the stored image (`(width, height)` unless a JPEG decoded at a reduced
    /// scale).
    pub(super) native: (u32, u32),
    /// `Rgb8` or `Mono8`.
    pub(super) format: PixelFormat,
    /// Tightly packed rows.
    pub(super) data: Vec<u8>,
}
