//! Principal components of per-point features, for colouring: a covariance-based fit of
//! the top three components (the `d × d` covariance of up to [`MAX_FIT_ROWS`] evenly
//! strided rows, its symmetric eigendecomposition), each component's 1st–99th percentile
//! mapped to 0–255, as the SuperFlow paper pictures its features. Also the cosine
//! similarity of every point's feature to one point's.

use nalgebra::{DMatrix, SymmetricEigen};

/// The most rows the covariance is fitted on (evenly strided beyond): a drive's keyframes
/// hold a few hundred thousand points, and three components are stable long before.
pub const MAX_FIT_ROWS: usize = 200_000;

/// The top three principal components of a set of features, with the colour range of
/// each.
#[derive(Debug, Clone, PartialEq)]
pub struct Pca {
    /// Feature width.
    pub dim: usize,
    /// The mean feature.
    pub mean: Vec<f32>,
    /// The components, unit length, by decreasing variance; each signed so that its
    /// largest entry in magnitude is positive (the same fit gives the same colours).
    pub components: [Vec<f32>; 3],
    /// The variance along each component.
    pub variances: [f64; 3],
    /// The features' whole variance (the covariance's trace): what the components'
    /// shares are of.
    pub total_variance: f64,
    /// The projections' 1st and 99th percentiles: 0 and 255 of each colour channel.
    pub ranges: [(f32, f32); 3],
}

/// Why a fit could not be made.
#[derive(Debug, Clone, PartialEq, Eq, thiserror::Error)]
pub enum PcaError {
    /// Too few rows or too narrow features for three components.
    #[error("{rows} features of width {dim}: three principal components need at least 3 of each")]
    TooSmall {
        /// Rows given.
        rows: usize,
        /// Their width.
        dim: usize,
    },
    /// `features.len()` is not a multiple of `dim`.
    #[error("{len} values are not rows of width {dim}")]
    Ragged {
        /// Values given.
        len: usize,
        /// The width.
        dim: usize,
    },
}

impl Pca {
    /// Fits the top three components of `features` (rows of width `dim`, row-major).
    pub fn fit(features: &[f32], dim: usize) -> Result<Self, PcaError> {
        if dim == 0 || !features.len().is_multiple_of(dim) {
            return Err(PcaError::Ragged {
                len: features.len(),
                dim,
            });
        }
        let rows = features.len() / dim;
        if rows < 3 || dim < 3 {
            return Err(PcaError::TooSmall { rows, dim });
        }
        let step = rows.div_ceil(MAX_FIT_ROWS);
        let fit_rows: Vec<&[f32]> = features.chunks_exact(dim).step_by(step).collect();
        let n = fit_rows.len() as f64;
        let mut mean = vec![0f64; dim];
        for row in &fit_rows {
            for (m, v) in mean.iter_mut().zip(*row) {
                *m += f64::from(*v);
            }
        }
        mean.iter_mut().for_each(|m| *m /= n);
        let mut cov = DMatrix::<f64>::zeros(dim, dim);
        let mut centred = vec![0f64; dim];
        for row in &fit_rows {
            for ((c, v), m) in centred.iter_mut().zip(*row).zip(&mean) {
                *c = f64::from(*v) - m;
            }
            for i in 0..dim {
                let ci = centred[i];
                for j in i..dim {
                    cov[(i, j)] += ci * centred[j];
                }
            }
        }
        for i in 0..dim {
            for j in i..dim {
                let v = cov[(i, j)] / (n - 1.0).max(1.0);
                cov[(i, j)] = v;
                cov[(j, i)] = v;
            }
        }
        let total_variance = cov.trace();
        let eigen = SymmetricEigen::new(cov);
        let mut order: Vec<usize> = (0..dim).collect();
        order.sort_by(|&a, &b| eigen.eigenvalues[b].total_cmp(&eigen.eigenvalues[a]));
        let component = |k: usize| -> Vec<f32> {
            let v = eigen.eigenvectors.column(order[k]);
            let largest = v
                .iter()
                .copied()
                .fold(0f64, |a, x| if x.abs() > a.abs() { x } else { a });
            let sign = if largest < 0.0 { -1.0 } else { 1.0 };
            v.iter().map(|x| (sign * x) as f32).collect()
        };
        let mut pca = Pca {
            dim,
            mean: mean.iter().map(|&m| m as f32).collect(),
            components: [component(0), component(1), component(2)],
            variances: [0, 1, 2].map(|k| eigen.eigenvalues[order[k]].max(0.0)),
            total_variance,
            ranges: [(0.0, 1.0); 3],
        };
        let projected: Vec<[f32; 3]> = fit_rows.iter().map(|r| pca.project(r)).collect();
        for k in 0..3 {
            let mut values: Vec<f32> = projected.iter().map(|p| p[k]).collect();
            values.sort_by(f32::total_cmp);
            let at = |q: f64| values[((values.len() - 1) as f64 * q).round() as usize];
            let (lo, hi) = (at(0.01), at(0.99));
            pca.ranges[k] = if hi > lo { (lo, hi) } else { (lo, lo + 1.0) };
        }
        Ok(pca)
    }

    /// The coordinates of `row` along the three components.
    pub fn project(&self, row: &[f32]) -> [f32; 3] {
        self.components.each_ref().map(|c| {
            row.iter()
                .zip(&self.mean)
                .zip(c)
                .map(|((x, m), w)| (x - m) * w)
                .sum()
        })
    }

    /// The colour of `row`: each component's coordinate, its range mapped to 0–255
    /// (clamped), as red, green and blue.
    pub fn colour(&self, row: &[f32]) -> [u8; 3] {
        self.colour_of(self.project(row))
    }

    /// The colour of coordinates `p` along the three components (what
    /// [`project`](Self::project) gives).
    pub fn colour_of(&self, p: [f32; 3]) -> [u8; 3] {
        [0, 1, 2].map(|k| {
            let (lo, hi) = self.ranges[k];
            ((p[k] - lo) / (hi - lo) * 255.0).clamp(0.0, 255.0).round() as u8
        })
    }
}

/// The cosine similarity of every row of `features` (width `dim`) to `query`; 0 for a
/// row or query of zero length.
pub fn cosine_similarity(features: &[f32], dim: usize, query: &[f32]) -> Vec<f32> {
    let norm = |r: &[f32]| {
        r.iter()
            .map(|x| f64::from(*x) * f64::from(*x))
            .sum::<f64>()
            .sqrt()
    };
    let q = norm(query);
    features
        .chunks_exact(dim)
        .map(|row| {
            let d = norm(row) * q;
            if d == 0.0 {
                return 0.0;
            }
            let dot: f64 = row
                .iter()
                .zip(query)
                .map(|(a, b)| f64::from(*a) * f64::from(*b))
                .sum();
            (dot / d) as f32
        })
        .collect()
}

#[cfg(test)]
mod tests {
    use super::*;

    /// Deterministic normal-ish noise (sum of uniforms).
    fn noise(state: &mut u64) -> f32 {
        let mut s = 0.0;
        for _ in 0..4 {
            *state = state
                .wrapping_mul(6_364_136_223_846_793_005)
                .wrapping_add(1_442_695_040_888_963_407);
            s += (*state >> 40) as f32 / (1u64 << 24) as f32 - 0.5;
        }
        s
    }

    /// Two clusters 6 σ apart along a direction spread over every feature: the first
    /// component's colour (red) tells them apart for every point.
    #[test]
    fn the_colours_separate_two_clusters() {
        let dim = 16;
        let direction: Vec<f32> = (0..dim)
            .map(|i| if i % 3 == 0 { -1.0 } else { 0.5 })
            .collect();
        let mut state = 7;
        let mut features = Vec::new();
        let mut cluster = Vec::new();
        for i in 0..2000 {
            let side = if i % 2 == 0 { 1.5 } else { -1.5 };
            cluster.push(i % 2 == 0);
            for d in &direction {
                features.push(side * d + 0.3 * noise(&mut state));
            }
        }
        let pca = Pca::fit(&features, dim).unwrap();
        let red: Vec<u8> = features
            .chunks_exact(dim)
            .map(|r| pca.colour(r)[0])
            .collect();
        let range = |side: bool| {
            let values = red
                .iter()
                .zip(&cluster)
                .filter(|(_, c)| **c == side)
                .map(|(r, _)| *r);
            (values.clone().min().unwrap(), values.max().unwrap())
        };
        let ((min_a, max_a), (min_b, max_b)) = (range(true), range(false));
        assert!(
            max_a < min_b || max_b < min_a,
            "{min_a}..{max_a} and {min_b}..{max_b}"
        );
        // The first component is the clusters' direction.
        let n: f32 = direction.iter().map(|x| x * x).sum::<f32>().sqrt();
        let cos: f32 = pca.components[0]
            .iter()
            .zip(&direction)
            .map(|(a, b)| a * b / n)
            .sum();
        assert!(cos.abs() > 0.99, "{cos}");
        assert!(pca.variances[0] > 10.0 * pca.variances[1]);
        assert!(pca.variances.iter().sum::<f64>() <= pca.total_variance * (1.0 + 1e-9));
        // The same fit, the same colours.
        assert_eq!(Pca::fit(&features, dim).unwrap(), pca);
    }

    #[test]
    fn similarity_is_one_at_the_query_and_follows_the_angle() {
        let features = [
            1.0, 0.0, 0.0, 0.0, 2.0, 0.0, -3.0, 0.0, 0.0, 1.0, 1.0, 0.0, 0.0, 0.0, 0.0,
        ];
        let sim = cosine_similarity(&features, 3, &features[..3]);
        assert_eq!(sim.len(), 5);
        assert!((sim[0] - 1.0).abs() < 1e-7);
        assert!(sim[1].abs() < 1e-7);
        assert!((sim[2] + 1.0).abs() < 1e-7);
        assert!((sim[3] - std::f32::consts::FRAC_1_SQRT_2).abs() < 1e-6);
        assert_eq!(sim[4], 0.0);
    }

    #[test]
    fn a_fit_needs_three_rows_of_three() {
        assert!(matches!(
            Pca::fit(&[0.0; 6], 3),
            Err(PcaError::TooSmall { rows: 2, dim: 3 })
        ));
        assert!(matches!(
            Pca::fit(&[0.0; 7], 3),
            Err(PcaError::Ragged { .. })
        ));
    }
}
