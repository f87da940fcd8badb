//! [`Scale`]: how small a decoded colour image may be, and the [`ScaledImage`] that
//! remembers the size of the stored image.

use superflow_schemas::sensor::Image;

/// How small a decoded colour image may be. A JPEG can decode at 1/2 or 1/4 of its size
/// in the DCT domain, which costs a fraction of a full decode; a sample that resizes to
/// 448×224 anyway asks for [`Scale::AtLeast`] that size. PNG, raw images and class maps
/// ([`Target::Mono`](super::target::Target::Mono)) always decode at full size.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Hash, Default)]
pub enum Scale {
    /// Every pixel.
    #[default]
    Full,
    /// The smallest of 1/4, 1/2 and full size that is at least `width × height`.
    AtLeast {
        /// Smallest acceptable width.
        width: u32,
        /// Smallest acceptable height.
        height: u32,
    },
}

/// A decoded image and the size of the image it was decoded from (different from the
/// image's own size when a JPEG decoded at a reduced [`Scale`]).
#[derive(Debug, Clone, PartialEq)]
pub struct ScaledImage {
    /// The pixels.
    pub image: Image,
    /// Width and height of the stored image.
    pub native: (u32, u32),
}
