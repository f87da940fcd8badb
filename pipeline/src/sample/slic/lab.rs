//! SLIC's pre-processing, as scikit-image does it: the image stretched to `[0, 1]`,
//! converted to CIELAB (sRGB gamma, D65 white), and each Lab plane smoothed by a
//! separable Gaussian with SciPy's `reflect` borders.

/// Gaussian kernels are truncated at this many standard deviations (SciPy's default).
const GAUSS_TRUNCATE: f32 = 4.0;

/// CIELAB planes of the (smoothed) image, and scratch for making them.
#[derive(Debug, Default)]
pub(super) struct Lab {
    /// Lightness.
    pub l: Vec<f32>,
    /// Green–red.
    pub a: Vec<f32>,
    /// Blue–yellow.
    pub b: Vec<f32>,
    /// The planes between the row and the column passes of the smoothing.
    scratch: Vec<f32>,
    /// A row of a plane with its reflected borders.
    pad: Vec<f32>,
}

/// [`Lab::compute`] into a new `Lab`.
#[cfg(test)]
pub(super) fn smoothed_lab(rgb: &[u8], width: usize, height: usize, sigma: f32) -> Lab {
    let mut lab = Lab::default();
    lab.compute(rgb, width, height, sigma);
    lab
}

impl Lab {
    /// scikit-image's pre-processing of the RGB8 image `rgb` (`width × height`): the
    /// image is stretched to `[0, 1]` by its global minimum and maximum (`image -= min;
    /// image /= max` over all channels; a no-op for images spanning 0..255), converted
    /// to CIELAB, and each Lab plane is smoothed by a Gaussian of `sigma` pixels (0: not
    /// at all).
    #[inline(always)]
    pub(super) fn compute(&mut self, rgb: &[u8], width: usize, height: usize, sigma: f32) {
        let n = width * height;
        // Every value is written below: no need to clear.
        for plane in [&mut self.l, &mut self.a, &mut self.b] {
            plane.resize(n, 0.0);
        }
        to_lab(rgb, self);
        if sigma > 0.0 {
            let kernel = gaussian_half_kernel(sigma);
            self.scratch.resize(n, 0.0);
            let (scratch, pad) = (&mut self.scratch, &mut self.pad);
            for plane in [&mut self.l, &mut self.a, &mut self.b] {
                blur_rows(plane, scratch, width, &kernel, pad);
                blur_columns(scratch, plane, width, height, &kernel);
            }
        }
    }
}

/// The stretched image `rgb` in CIELAB, into `lab`'s planes (of its size).
#[inline(always)]
fn to_lab(rgb: &[u8], lab: &mut Lab) {
    let lo = rgb.iter().copied().min().unwrap_or(0);
    let hi = rgb.iter().copied().max().unwrap_or(0);
    // sRGB-encoded byte → linear, after the stretch.
    let mut linear = [0f32; 256];
    for (v, lin) in linear.iter_mut().enumerate() {
        let c = if hi > lo {
            (v as f64 - f64::from(lo)) / f64::from(hi - lo)
        } else {
            0.0
        };
        *lin = if c > 0.04045 {
            ((c + 0.055) / 1.055).powf(2.4) as f32
        } else {
            (c / 12.92) as f32
        };
    }

    // sRGB (D65) → XYZ normalised by the D65 white (0.95047, 1, 1.08883), kept in the
    // planes for the moment.
    for (((px, x), y), z) in rgb
        .chunks_exact(3)
        .zip(&mut lab.l)
        .zip(&mut lab.a)
        .zip(&mut lab.b)
    {
        let (r, g, b) = (
            linear[usize::from(px[0])],
            linear[usize::from(px[1])],
            linear[usize::from(px[2])],
        );
        *x = (0.412453 * r + 0.357580 * g + 0.180423 * b) * (1.0 / 0.95047);
        *y = 0.212671 * r + 0.715160 * g + 0.072169 * b;
        *z = (0.019334 * r + 0.119193 * g + 0.950227 * b) * (1.0 / 1.08883);
    }
    // XYZ → CIELAB.
    for ((l, a), b) in lab.l.iter_mut().zip(&mut lab.a).zip(&mut lab.b) {
        let (fx, fy, fz) = (lab_f(*l), lab_f(*a), lab_f(*b));
        *l = 116.0 * fy - 16.0;
        *a = 500.0 * (fx - fy);
        *b = 200.0 * (fy - fz);
    }
}

/// CIELAB's `f(t)` as scikit-image has it: `∛t` above 0.008856, `7.787 t + 16/116` below
/// (`t ≥ 0`). The cube root is a bit-level estimate refined by two Halley steps (within an
/// ulp or two of `f32::cbrt`), written so that a loop over it vectorises.
#[inline(always)]
fn lab_f(t: f32) -> f32 {
    let t = t.max(0.0);
    // Estimate: divide the exponent by three (the classic `bits / 3 + magic`).
    let mut y = f32::from_bits(t.to_bits() / 3 + 0x2a51_37a0);
    for _ in 0..2 {
        let y3 = y * y * y;
        y *= (y3 + 2.0 * t) / (2.0 * y3 + t);
    }
    if t > 0.008856 {
        y
    } else {
        7.787 * t + 16.0 / 116.0
    }
}

/// The normalised Gaussian of `sigma` truncated at 4 σ (SciPy's `gaussian_filter1d`),
/// from its centre outwards: `k[0]` is the centre tap, `k[j]` the taps at `±j`.
fn gaussian_half_kernel(sigma: f32) -> Vec<f32> {
    let radius = (GAUSS_TRUNCATE * sigma + 0.5) as usize;
    let sigma = f64::from(sigma);
    let taps: Vec<f64> = (0..=radius)
        .map(|j| (-0.5 * (j as f64 / sigma).powi(2)).exp())
        .collect();
    let total = taps.first().copied().unwrap_or(1.0) + 2.0 * taps.iter().skip(1).sum::<f64>();
    taps.iter().map(|t| (t / total) as f32).collect()
}

/// SciPy's `reflect` border: index `i` of an infinite `d c b a | a b c d | d c b a` line
/// over `len > 0` samples.
fn reflect(i: isize, len: usize) -> usize {
    let len = len as isize;
    let m = i.rem_euclid(2 * len);
    (if m < len { m } else { 2 * len - 1 - m }) as usize
}

/// Outputs of a convolution computed together, kept in registers over the taps.
const BLOCK: usize = 16;

/// Convolves every row of `src` with the symmetric `kernel` into `dst`.
#[inline(always)]
fn blur_rows(src: &[f32], dst: &mut [f32], width: usize, kernel: &[f32], pad: &mut Vec<f32>) {
    let radius = kernel.len() - 1;
    let index: Vec<usize> = (0..width + 2 * radius)
        .map(|i| reflect(i as isize - radius as isize, width))
        .collect();
    pad.resize(index.len(), 0.0);
    for (src, dst) in src.chunks_exact(width).zip(dst.chunks_exact_mut(width)) {
        // The row itself, then its reflected borders.
        pad[radius..radius + width].copy_from_slice(src);
        let borders = (0..radius).chain(radius + width..width + 2 * radius);
        for i in borders {
            pad[i] = src[index[i]];
        }
        // Output x reads pad[x..=x + 2 radius]; tap j pairs pad[x + radius ∓ j].
        let taps = |x: usize, j: usize| (&pad[x + radius - j..], &pad[x + radius + j..]);
        let mut blocks = dst.chunks_exact_mut(BLOCK);
        for (b, out) in (&mut blocks).enumerate() {
            convolve_block(out, kernel, |j| {
                let (a, b) = taps(b * BLOCK, j);
                (&a[..BLOCK], &b[..BLOCK])
            });
        }
        let done = width - width % BLOCK;
        for (x, out) in blocks.into_remainder().iter_mut().enumerate() {
            convolve_one(out, kernel, |j| taps(done + x, j));
        }
    }
}

/// Convolves every column of `src` with the symmetric `kernel` into `dst`.
#[inline(always)]
fn blur_columns(src: &[f32], dst: &mut [f32], width: usize, height: usize, kernel: &[f32]) {
    let row = |y: usize| &src[y * width..(y + 1) * width];
    let mut rows = Vec::with_capacity(kernel.len());
    for (y, dst) in dst.chunks_exact_mut(width).enumerate() {
        // Tap j pairs the rows above and below.
        rows.clear();
        rows.extend((0..kernel.len()).map(|j| {
            (
                row(reflect(y as isize - j as isize, height)),
                row(reflect((y + j) as isize, height)),
            )
        }));
        let mut blocks = dst.chunks_exact_mut(BLOCK);
        for (b, out) in (&mut blocks).enumerate() {
            let x = b * BLOCK;
            convolve_block(out, kernel, |j| {
                let (a, b) = rows[j];
                (&a[x..x + BLOCK], &b[x..x + BLOCK])
            });
        }
        let done = width - width % BLOCK;
        for (x, out) in blocks.into_remainder().iter_mut().enumerate() {
            convolve_one(out, kernel, |j| {
                let (a, b) = rows[j];
                (&a[done + x..], &b[done + x..])
            });
        }
    }
}

/// One block of outputs of a symmetric convolution, `tap(j)` giving the samples at
/// `∓ j` (`tap(0)`: the centre): `k0 p + k1 (a1 + b1) + k2 (a2 + b2) + …`, added in
/// that order.
#[inline(always)]
fn convolve_block<'a>(
    out: &mut [f32],
    kernel: &[f32],
    tap: impl Fn(usize) -> (&'a [f32], &'a [f32]),
) {
    let k0 = kernel.first().copied().unwrap_or(1.0);
    let (centre, _) = tap(0);
    let centre = &centre[..BLOCK];
    let mut acc = [0f32; BLOCK];
    for (a, &c) in acc.iter_mut().zip(centre) {
        *a = k0 * c;
    }
    for (j, &k) in kernel.iter().enumerate().skip(1) {
        let (a, b) = tap(j);
        let (a, b) = (&a[..BLOCK], &b[..BLOCK]);
        for i in 0..BLOCK {
            acc[i] += k * (a[i] + b[i]);
        }
    }
    out.copy_from_slice(&acc);
}

/// One output of a symmetric convolution, as [`convolve_block`] computes it.
#[inline(always)]
fn convolve_one<'a>(out: &mut f32, kernel: &[f32], tap: impl Fn(usize) -> (&'a [f32], &'a [f32])) {
    let k0 = kernel.first().copied().unwrap_or(1.0);
    *out = k0 * tap(0).0[0];
    for (j, &k) in kernel.iter().enumerate().skip(1) {
        let (a, b) = tap(j);
        *out += k * (a[0] + b[0]);
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn slic_reflect_and_kernel() {
        let idx: Vec<usize> = (-5..9).map(|i| reflect(i, 4)).collect();
        assert_eq!(idx, [3, 3, 2, 1, 0, 0, 1, 2, 3, 3, 2, 1, 0, 0]);
        assert!((-3..4).all(|i| reflect(i, 1) == 0));
        let k = gaussian_half_kernel(3.0);
        assert_eq!(k.len(), 13);
        let total = k[0] + 2.0 * k[1..].iter().sum::<f32>();
        assert!((total - 1.0).abs() < 1e-6);
    }

    #[test]
    fn slic_lab_f_is_close_to_the_cube_root() {
        let mut worst = 0f64;
        for i in 0..=100_000 {
            let t = i as f32 / 100_000.0;
            let exact = if f64::from(t) > 0.008856 {
                f64::from(t).cbrt()
            } else {
                7.787 * f64::from(t) + 16.0 / 116.0
            };
            worst = worst.max((f64::from(lab_f(t)) - exact).abs());
        }
        assert!(worst < 3e-7, "worst error {worst}");
    }

    #[test]
    fn slic_lab_matches_reference_values() {
        // scikit-image rgb2lab of pure colours (no smoothing); black and white are in the
        // image, so its [0, 1] stretch changes nothing.
        let cases: [([u8; 3], [f32; 3]); 5] = [
            ([255, 255, 255], [100.0, 0.0, 0.0]),
            ([0, 0, 0], [0.0, 0.0, 0.0]),
            ([255, 0, 0], [53.24, 80.09, 67.20]),
            ([0, 0, 255], [32.30, 79.19, -107.86]),
            ([128, 128, 128], [53.59, 0.0, 0.0]),
        ];
        let rgb: Vec<u8> = cases.iter().flat_map(|(rgb, _)| *rgb).collect();
        let lab = smoothed_lab(&rgb, cases.len(), 1, 0.0);
        for (i, (rgb, expected)) in cases.iter().enumerate() {
            let got = [lab.l[i], lab.a[i], lab.b[i]];
            for (g, e) in got.iter().zip(expected) {
                assert!((g - e).abs() < 0.01, "{rgb:?}: {got:?} vs {expected:?}");
            }
        }
        // The stretch: a dull image spans black to white after it.
        let lab = smoothed_lab(&[100, 100, 100, 150, 150, 150], 2, 1, 0.0);
        assert!(lab.l[0].abs() < 1e-3 && (lab.l[1] - 100.0).abs() < 1e-3);
        // A constant image is black.
        let lab = smoothed_lab(&[90; 6], 2, 1, 0.0);
        assert!(lab.l[0].abs() < 1e-3 && lab.l[1].abs() < 1e-3);
    }
}
