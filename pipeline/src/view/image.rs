//! Camera images as `foxglove.CompressedImage` (PNG) on `/superflow/<camera>/<what>`.

use super::writer::{ViewError, ViewWriter};
use foxglove::messages::CompressedImage;
use superflow_schemas::Stamp;

/// The topic `/superflow/<camera>/<what>`, the camera's name as one topic level (every
/// character but ASCII letters, digits, `_` and `-` as `_`).
pub fn camera_topic(camera: &str, what: &str) -> String {
    let level: String = camera
        .trim_matches('/')
        .chars()
        .map(|c| {
            if c.is_ascii_alphanumeric() || c == '_' || c == '-' {
                c
            } else {
                '_'
            }
        })
        .collect();
    format!("/superflow/{level}/{what}")
}

impl ViewWriter {
    /// Writes `rgb` (`width × height × 3`) as a PNG image of `camera` in `frame_id` on
    /// [`camera_topic`]`(camera, what)`, logged and stamped at `stamp`.
    pub fn write_png(
        &mut self,
        camera: &str,
        what: &str,
        frame_id: &str,
        stamp: Stamp,
        (width, height): (u32, u32),
        rgb: &[u8],
    ) -> Result<(), ViewError> {
        let mut png = Vec::new();
        let mut encoder = png::Encoder::new(&mut png, width, height);
        encoder.set_color(png::ColorType::Rgb);
        encoder.set_depth(png::BitDepth::Eight);
        encoder.set_compression(png::Compression::Fast);
        encoder
            .write_header()
            .and_then(|mut w| w.write_image_data(rgb).and_then(|()| w.finish()))
            .map_err(|source| ViewError::Png {
                path: self.path().to_path_buf(),
                camera: camera.to_string(),
                stamp,
                source,
            })?;
        let image = CompressedImage {
            timestamp: Some(self.timestamp(stamp)?),
            frame_id: frame_id.to_string(),
            data: png.into(),
            format: "png".into(),
        };
        self.write(&camera_topic(camera, what), stamp, &image)
    }
}
