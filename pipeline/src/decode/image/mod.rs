//! Camera images (and per-pixel class maps) as recorders write them, decoded into the
//! sensor model's [`Image`] (`Rgb8` or `Mono8`, tightly packed, row-major).
//!
//! # Messages
//!
//! | message | entry point | fields read |
//! |---|---|---|
//! | ROS 2 `sensor_msgs/msg/CompressedImage` | [`decode_ros2_compressed`] | `header`, `format`, `data` |
//! | ROS 2 `sensor_msgs/msg/Image` | [`decode_ros2_raw`] | `header`, `width`, `height`, `encoding`, `step`, `data` |
//! | `foxglove.CompressedImage` | [`decode_foxglove_compressed`] | `timestamp`, `frame_id`, `format`, `data` |
//! | `foxglove.RawImage` | [`decode_foxglove_raw`] | `timestamp`, `frame_id`, `width`, `height`, `encoding`, `step`, `data` |
//!
//! # Compressed formats (`format`)
//!
//! | `format` | decoded as |
//! |---|---|
//! | `jpeg`, `jpg`, `image/jpeg` | JPEG (libjpeg-turbo; bit-exact with Pillow and `djpeg`, also at a reduced [`Scale`]): YCbCr and grey → RGB; a grey JPEG → `Mono8` for [`Target::Mono`]; CMYK is an error |
//! | `png`, `image/png` | PNG (`png` crate): grey 1/2/4/8/16-bit, grey+alpha, RGB, RGBA (8/16-bit), palette 1/2/4/8-bit; alpha and `tRNS` are dropped |
//! | `<src>; jpeg compressed bgr8`, `<src>; png compressed bgr8` / `bgr16` / `bgra8` / `bgra16` (image_transport) | as JPEG/PNG, channel order as stored (see below) |
//! | `<src>; jpeg compressed rgb8`, `<src>; png compressed rgb8` (any target starting with `rgb`) | as JPEG/PNG, then red and blue swapped (see below) |
//! | `<src>; jpeg compressed ` / `<src>; png compressed ` (mono sources: no target) | as JPEG/PNG |
//! | `<src>; compressedDepth …` | error [`ImageError::CompressedDepth`] (a quantized depth map, not a camera image) |
//! | `webp`, `avif`, `qoi`, anything else | error [`ImageError::UnsupportedFormat`] |
//! | `""` | by magic bytes |
//!
//! The magic bytes win over the format string: data starting with `FF D8` is decoded as
//! JPEG and data starting with `89 50 4E 47` as PNG whatever `format` says (empty and
//! wrong format strings occur in real recordings). Only when that decode fails and
//! `format` names the other codec is the other codec tried; when both fail the error
//! ([`ImageError::FormatMismatch`]) reports the disagreement and both failures.
//!
//! ## image_transport channel order
//!
//! `compressed_image_transport` converts a colour image to a `bgr8` (`bgr16`, `bgra8`)
//! OpenCV `Mat` and passes it to `cv::imencode`. OpenCV's encoders treat a 3-channel
//! `Mat` as BGR and write **standard** files: the JPEG encoder converts BGR to YCbCr, and
//! the PNG encoder calls `png_set_bgr`, so the PNG's samples are in RGB order (OpenCV
//! `modules/imgcodecs/src/grfmt_png.cpp`, `PngEncoder::write`). A normal decoder therefore
//! returns correct colours for a `… compressed bgr8` payload and no swap is applied, for
//! JPEG and PNG alike. A target starting with `rgb` (`… compressed rgb8`, written by
//! older publishers) means an RGB `Mat` was handed to `cv::imencode`, which stored it
//! channel-swapped; red and blue are swapped back. This is exactly what
//! image_transport's own `CompressedSubscriber` does (it reverts only `compressed bgr`
//! payloads to BGR and treats every other payload as RGB).
//!
//! # Raw encodings (`encoding`, as ROS 2 and `foxglove.RawImage` write them)
//!
//! | `encoding` | read as |
//! |---|---|
//! | `rgb8` | 3 bytes, red first |
//! | `bgr8`, `8UC3` | 3 bytes, blue first (`8UC3` follows cv_bridge/OpenCV, whose 3-channel `Mat`s are BGR) |
//! | `rgba8` | 4 bytes, red first, alpha dropped |
//! | `bgra8`, `8UC4` | 4 bytes, blue first, alpha dropped (`8UC4` as OpenCV's BGRA) |
//! | `mono8`, `8UC1` | 1 byte (`8UC1` is a single-channel 8-bit `Mat`: grey levels or ids) |
//! | `mono16`, `16UC1`, `16SC1`, `32FC1`, `rgb16`, … | error [`ImageError::UnsupportedEncoding`] (more than 8 bits per channel) |
//! | `bayer_*` | error [`ImageError::UnsupportedEncoding`] (mosaic; debayer upstream) |
//! | `yuv422`, `uyvy`, `yuyv`, `nv21`, … | error [`ImageError::UnsupportedEncoding`] |
//!
//! Encodings are matched case-insensitively. `step` is the byte length of a row and may
//! exceed `width × channels` (row padding, skipped); `step = 0` (an unset protobuf field)
//! means tightly packed rows. `data` must hold `step × height` bytes; the padding of the
//! last row may be omitted. `is_bigendian` does not matter for 8-bit samples.
//!
//! # Targets
//!
//! [`Target::Rgb`] (the default, for camera images) gives `Rgb8`: colour is converted to
//! RGB order, single-channel data is replicated to three channels, 16-bit PNG samples
//! keep their high byte and 1/2/4-bit grey is scaled to `0..=255`.
//!
//! [`Target::Mono`] ("keep ids", for class maps and grey cameras) gives `Mono8` with the
//! stored values untouched: `mono8`/`8UC1` raw data, 8-bit grey (or grey+alpha) PNGs,
//! 1/2/4-bit grey PNGs (raw values, not scaled), palette PNGs (the palette **indices**,
//! as in Pascal VOC style class maps) and grey JPEGs. Anything that would need a colour
//! conversion or a bit-depth reduction (RGB/BGR data, colour JPEGs, 16-bit PNGs) is an
//! error ([`ImageError::NotMono`]) rather than a silent corruption of the ids.
//!
//! # Errors and limits
//!
//! Every error names the frame id and stamp of the message (the caller adds file and
//! topic). Decoding never panics on malformed input: sizes are checked before anything is
//! allocated, images whose decoded size (or PNG sample buffer) would exceed
//! [`MAX_IMAGE_BYTES`] are rejected, truncated JPEG and PNG data are errors (a JPEG
//! without an end-of-image marker after its scan data counts as truncated), and a panic
//! inside a third-party codec is caught and reported as [`ImageError::Corrupt`].
//!
//! [`Image`]: superflow_schemas::sensor::Image

pub mod buffers;
mod checks;
mod codec;
mod decoded;
mod dialect;
mod error;
mod format;
mod jpeg;
mod png;
mod png_grey;
mod raw;
mod scale;
mod target;
#[cfg(test)]
mod tests;

pub use checks::MAX_IMAGE_BYTES;
pub use codec::Codec;
pub use dialect::{
    decode_foxglove_compressed, decode_foxglove_compressed_scaled, decode_foxglove_raw,
    decode_ros2_compressed, decode_ros2_compressed_scaled, decode_ros2_raw,
};
pub use error::{ImageError, Rejection};
pub use scale::{Scale, ScaledImage};
pub use target::Target;
