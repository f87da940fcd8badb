//! Position embeddings for another patch grid than the trained one: the bicubic resize of
//! Hugging Face's `Dinov2Embeddings.interpolate_pos_encoding`, as a separable pair of
//! `[output, input]` weight matrices.

use super::network::DinoVit;
use burn::tensor::{Device, Tensor, TensorData};

impl DinoVit {
    /// The position embeddings for a patch grid: the trained ones when `grid` is
    /// `config.pos_grid`, else their patch part resized bicubically as Hugging Face's
    /// `Dinov2Embeddings.interpolate_pos_encoding` does (see [`resize_matrix`]), the class
    /// position kept.
    ///
    /// # Shapes
    ///
    /// - output: `[1 + rows·cols, dim]`
    pub(super) fn position_embeddings(&self, grid: [usize; 2]) -> Tensor<2> {
        let pos = self.pos_embed.val();
        if grid == self.config.pos_grid {
            return pos;
        }
        let [rows, cols] = grid;
        let [trained_rows, trained_cols] = self.config.pos_grid;
        let dim = self.config.dim;
        let device = pos.device();

        let cls = pos.clone().narrow(0, 0, 1); // [1, dim]
        // Bicubic resize is separable: along the columns, then along the rows.
        let by_cols = resize_matrix(trained_cols, cols, &device); // [cols, trained_cols]
        let by_rows = resize_matrix(trained_rows, rows, &device); // [rows, trained_rows]
        let patch = pos
            .narrow(0, 1, trained_rows * trained_cols)
            .reshape([trained_rows, trained_cols, dim])
            .swap_dims(0, 1)
            .reshape([trained_cols, trained_rows * dim]);
        let patch = by_cols
            .matmul(patch) // [cols, trained_rows·dim]
            .reshape([cols, trained_rows, dim])
            .swap_dims(0, 1)
            .reshape([trained_rows, cols * dim]);
        let patch = by_rows
            .matmul(patch) // [rows, cols·dim]
            .reshape([rows * cols, dim]);
        Tensor::cat(vec![cls, patch], 0)
    }
}

/// The `[output, input]` matrix that resizes a length-`input` signal to length `output` as
/// PyTorch's `interpolate(size=…, mode="bicubic", align_corners=False)` does without
/// antialiasing — the call in Hugging Face's `Dinov2Embeddings.interpolate_pos_encoding`
/// (transformers 5; see `trainer/reference/make_vit_fixture.py`).
fn resize_matrix(input: usize, output: usize, device: &Device) -> Tensor<2> {
    Tensor::from_data(
        TensorData::new(bicubic_weights(input, output), [output, input]),
        device,
    )
}

/// Row-major `[output, input]` weights of [`resize_matrix`], in f32 like PyTorch's CPU kernel
/// for f32 tensors. Output sample `o` sits at source position `s = (o + ½)·input/output − ½`
/// (not clamped at 0) and takes the inputs `⌊s⌋ − 1 ..= ⌊s⌋ + 2`, clamped to the borders (edge
/// replication), weighted by Keys' cubic convolution kernel with a = −0.75.
fn bicubic_weights(input: usize, output: usize) -> Vec<f32> {
    const A: f32 = -0.75;
    // The kernel for distances |x| ≤ 1 and 1 < |x| < 2.
    let near = |x: f32| ((A + 2.0) * x - (A + 3.0)) * x * x + 1.0;
    let far = |x: f32| ((A * x - 5.0 * A) * x + 8.0 * A) * x - 4.0 * A;

    let scale = input as f32 / output as f32;
    let last = input as i64 - 1;
    let mut weights = vec![0.0; output * input];
    for (o, row) in weights.chunks_exact_mut(input).enumerate() {
        let source = scale * (o as f32 + 0.5) - 0.5;
        // PyTorch's guard: the base tap stays inside and the fraction in [0, 1].
        let base = (source.floor() as i64).min(last);
        let t = (source - base as f32).clamp(0.0, 1.0);
        let taps = [far(1.0 + t), near(t), near(1.0 - t), far(2.0 - t)];
        for (offset, weight) in (-1..=2).zip(taps) {
            row[(base + offset).clamp(0, last) as usize] += weight;
        }
    }
    weights
}

#[cfg(test)]
mod tests {
    use super::*;
    use std::path::Path;

    /// The position embeddings equal the ones transformers added (`pos_embed` in
    /// `tests/fixtures/vit.json`), on the trained grid and on a resized one.
    #[test]
    fn position_embeddings_match_transformers() {
        let fixtures = Path::new(env!("CARGO_MANIFEST_DIR")).join("tests/fixtures");
        let json = std::fs::read_to_string(fixtures.join("vit.json")).expect("reading vit.json");
        let fixture: serde_json::Value = serde_json::from_str(&json).expect("parsing vit.json");
        let vit =
            DinoVit::load_safetensors(&fixtures.join("tiny_dinov2.safetensors"), &Device::flex())
                .expect("loading the fixture checkpoint");
        let cases = fixture["cases"].as_array().expect("a list of cases");
        for case in cases {
            let grid: [usize; 2] =
                serde_json::from_value(case["grid"].clone()).expect("a [rows, cols] grid");
            let expected: Vec<f32> =
                serde_json::from_value(case["pos_embed"].clone()).expect("a list of floats");
            let actual = vit
                .position_embeddings(grid)
                .into_data()
                .try_into_vec::<f32>()
                .expect("f32 values");
            assert_eq!(actual.len(), expected.len(), "grid {grid:?}");
            let diff = actual
                .iter()
                .zip(&expected)
                .map(|(a, e)| (a - e).abs())
                .fold(0.0, f32::max);
            assert!(
                diff < 1e-6,
                "grid {grid:?}: position embeddings differ by {diff}"
            );
        }
    }

    /// Every output is an affine combination of the inputs (a constant stays constant), and
    /// resizing to the same length is the identity.
    #[test]
    fn bicubic_weights_are_affine_and_identity_at_equal_size() {
        for (input, output) in [
            (4, 3),
            (4, 6),
            (4, 16),
            (37, 16),
            (37, 32),
            (37, 80),
            (1, 3),
        ] {
            let weights = bicubic_weights(input, output);
            for (o, row) in weights.chunks_exact(input).enumerate() {
                let sum: f32 = row.iter().sum();
                assert!(
                    (sum - 1.0).abs() < 1e-6,
                    "{input} → {output}, row {o}: sum {sum}"
                );
            }
        }
        let weights = bicubic_weights(5, 5);
        for (o, row) in weights.chunks_exact(5).enumerate() {
            for (i, &w) in row.iter().enumerate() {
                assert_eq!(w, f32::from(u8::from(i == o)), "5 → 5 at ({o}, {i})");
            }
        }
    }
}
