//! [`Target`]: what the caller wants out of an image, a camera image or class ids kept
//! exactly.

/// What the caller wants out of an image.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Hash, Default)]
pub enum Target {
    /// A camera image as `Rgb8`; single-channel sources are replicated to three channels.
    #[default]
    Rgb,
    /// `Mono8` with the stored values kept exactly (class ids of a semantic map, or grey
    /// levels); colour or 16-bit sources are an error, never converted.
    Mono,
}
