//! [`imagenet_normalize`]: camera images as the network takes them.

use burn::tensor::Tensor;

/// Per-channel (RGB) mean of ImageNet, on the 0..1 scale.
const IMAGENET_MEAN: [f32; 3] = [0.485, 0.456, 0.406];
/// Per-channel (RGB) standard deviation of ImageNet, on the 0..1 scale.
const IMAGENET_STD: [f32; 3] = [0.229, 0.224, 0.225];

/// ImageNet normalization of RGB images, moved to channels-first: `(x / 255 − mean) / std`
/// with mean (0.485, 0.456, 0.406) and std (0.229, 0.224, 0.225).
///
/// # Shapes
///
/// - images: `[I, H, W, 3]`, RGB values in 0..=255
/// - output: `[I, 3, H, W]`
///
/// # Panics
///
/// Panics if the last axis is not 3.
pub fn imagenet_normalize(images: Tensor<4>) -> Tensor<4> {
    let [.., channels] = images.dims();
    assert_eq!(
        channels, 3,
        "imagenet_normalize: images must be [I, H, W, 3]"
    );
    let device = images.device();
    let mean = Tensor::<1>::from_floats(IMAGENET_MEAN, &device).reshape([1, 3, 1, 1]);
    let std = Tensor::<1>::from_floats(IMAGENET_STD, &device).reshape([1, 3, 1, 1]);
    (images.permute([0, 3, 1, 2]).div_scalar(255.0) - mean) / std
}
