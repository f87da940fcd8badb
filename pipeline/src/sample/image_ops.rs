//! Image resizing for samples: bilinear for colour (half-pixel centres, like
//! `torch.nn.functional.interpolate(mode="bilinear", align_corners=False)` and OpenCV's
//! `INTER_LINEAR`, no antialiasing), nearest for label maps, horizontal flips, and the
//! mapping of a raw-image pixel to its resized (row, col).

#[cfg(target_arch = "x86_64")]
use super::simd::has_avx512;

/// Where output index `i` samples the input, for `n_in → n_out` with half-pixel
/// centres: the two input indices and the weight of the second.
fn linear_taps(n_in: usize, n_out: usize) -> Vec<(usize, usize, f32)> {
    let scale = n_in as f64 / n_out as f64;
    (0..n_out)
        .map(|i| {
            let src = ((i as f64 + 0.5) * scale - 0.5).max(0.0);
            let i0 = (src.floor() as usize).min(n_in - 1);
            let i1 = (i0 + 1).min(n_in - 1);
            (i0, i1, (src - i0 as f64) as f32)
        })
        .collect()
}

/// Bilinear resize of an interleaved `channels`-channel u8 image (`data.len() ==
/// channels·width·height`) to `out_width × out_height`, rounding to nearest.
///
/// Each output row blends its two source rows in `f32` (`a + (b − a)·wy`), then each
/// pixel blends its two source columns the same way (`+ 0.5`, truncated). Colour pixels
/// blend as four lanes at once (the fourth is the next pixel's first channel, ignored),
/// and the whole resize also exists compiled with AVX2, chosen at run time: the same IEEE
/// operations in the same order, so every copy gives the same bytes.
pub fn resize_bilinear(
    data: &[u8],
    width: usize,
    height: usize,
    channels: usize,
    out_width: usize,
    out_height: usize,
) -> Vec<u8> {
    resize_bilinear_mirrored(
        data,
        [width, height, channels],
        [out_width, out_height],
        false,
    )
}

/// [`resize_bilinear`] of `[width, height, channels]` to `[out_width, out_height]`,
/// mirrored left to right when `mirrored`: output column `x` takes the taps of column
/// `out_width − 1 − x`, so the bytes are those of the resize followed by
/// [`flip_horizontal`], without the second pass over the image.
pub fn resize_bilinear_mirrored(
    data: &[u8],
    [width, height, channels]: [usize; 3],
    [out_width, out_height]: [usize; 2],
    mirrored: bool,
) -> Vec<u8> {
    let size = Size {
        dims: [width, height, out_width, out_height],
        mirrored,
    };
    match channels {
        1 => resize_bilinear_dispatch::<1>(data, size),
        3 => resize_bilinear_dispatch::<3>(data, size),
        4 => resize_bilinear_dispatch::<4>(data, size),
        _ => vec![0u8; out_width * out_height * channels],
    }
}

/// Input and output sizes of a resize (`[width, height, out_width, out_height]`), and
/// whether the output is mirrored.
#[derive(Debug, Clone, Copy)]
struct Size {
    dims: [usize; 4],
    mirrored: bool,
}

#[allow(unsafe_code)]
fn resize_bilinear_dispatch<const C: usize>(data: &[u8], size: Size) -> Vec<u8> {
    #[cfg(target_arch = "x86_64")]
    if has_avx512() {
        // SAFETY: the CPU runs AVX-512 F and BW (checked just above), the only
        // requirement of calling a function compiled with them enabled.
        return unsafe { resize_bilinear_avx512::<C>(data, size) };
    }
    #[cfg(target_arch = "x86_64")]
    if crate::sample::simd::has_avx2() {
        // SAFETY: the CPU runs AVX2 (checked just above), the only requirement of calling
        // a function compiled with it enabled.
        return unsafe { resize_bilinear_avx2::<C>(data, size) };
    }
    resize_bilinear_n::<C>(data, size)
}

/// [`resize_bilinear_n`] compiled with AVX2 enabled (not FMA: no contraction); colour
/// rows take their horizontal taps two pixels to a vector ([`horizontal_rgb_avx2`]).
#[cfg(target_arch = "x86_64")]
#[target_feature(enable = "avx2")]
fn resize_bilinear_avx2<const C: usize>(data: &[u8], size: Size) -> Vec<u8> {
    if C == 3 {
        return resize_bilinear_with::<C>(data, size, |blended, xs, out| {
            horizontal_rgb_avx2(blended, xs, out)
        });
    }
    resize_bilinear_n::<C>(data, size)
}

/// [`resize_bilinear_avx2`] compiled with AVX-512 enabled: the vertical blend and the
/// truncation to bytes run sixteen lanes at a time (the same IEEE operations in the
/// same order, no contraction: the same bytes), twice AVX2's eight: half the
/// instructions for those two passes.
#[cfg(target_arch = "x86_64")]
#[target_feature(enable = "avx512f,avx512bw,avx2")]
fn resize_bilinear_avx512<const C: usize>(data: &[u8], size: Size) -> Vec<u8> {
    if C == 3 {
        return resize_bilinear_with::<C>(data, size, |blended, xs, out| {
            horizontal_rgb_avx512(blended, xs, out)
        });
    }
    resize_bilinear_n::<C>(data, size)
}

/// [`horizontal_rgb_avx2`] four output pixels to a 16-lane vector: each quarter holds a
/// pixel's three channels and a spare lane, blended with the same operations in the same
/// order (the same floats); the spare lanes are squeezed out and the twelve floats
/// stored under a mask. Pixels after the last group of four go one at a time.
///
/// `blended` holds the row's `3·width` floats and four spare ones, `out` the output
/// row's `3·xs.len()` floats and four spare ones, and every tap is below `width`.
#[cfg(target_arch = "x86_64")]
#[target_feature(enable = "avx512f,avx512bw,avx2")]
#[allow(unsafe_code)]
fn horizontal_rgb_avx512(blended: &[f32], xs: &HorizontalTaps, out: &mut [f32]) {
    use std::arch::x86_64::{
        __m128, __m512, _mm_loadu_ps, _mm512_add_ps, _mm512_castps128_ps512, _mm512_insertf32x4,
        _mm512_loadu_ps, _mm512_mask_storeu_ps, _mm512_mul_ps, _mm512_permutexvar_ps,
        _mm512_set1_ps, _mm512_setr_epi32, _mm512_sub_ps,
    };
    let quads = xs.first.len() / 4;
    // Every read below ends by `blended[3·tap + 4]`, every write by `out[12·quads]`,
    // and the weights by `pair_weights[16·quads]`: checked once here, not per pixel.
    if blended.len() < xs.last as usize + 4
        || out.len() < 12 * quads + 4
        || xs.pair_weights.len() < 16 * quads
    {
        return horizontal_taps::<3>(blended, xs, out);
    }
    let half = _mm512_set1_ps(0.5);
    let squeeze = _mm512_setr_epi32(0, 1, 2, 4, 5, 6, 8, 9, 10, 12, 13, 14, 15, 15, 15, 15);
    let load = |at: u32| -> __m128 {
        // SAFETY: `at + 4 <= blended.len()` for every tap (checked above).
        unsafe { _mm_loadu_ps(blended.as_ptr().add(at as usize)) }
    };
    let gather = |taps: &[u32]| -> __m512 {
        let v = _mm512_castps128_ps512(load(taps[0]));
        let v = _mm512_insertf32x4::<1>(v, load(taps[1]));
        let v = _mm512_insertf32x4::<2>(v, load(taps[2]));
        _mm512_insertf32x4::<3>(v, load(taps[3]))
    };
    for q in 0..quads {
        let pixels = 4 * q..4 * q + 4;
        let p0 = gather(&xs.first[pixels.clone()]);
        let p1 = gather(&xs.second[pixels]);
        // SAFETY: `pair_weights` holds 8 floats per pair, 16 per group of four pixels.
        let w = unsafe { _mm512_loadu_ps(xs.pair_weights.as_ptr().add(16 * q)) };
        let v = _mm512_add_ps(
            _mm512_add_ps(p0, _mm512_mul_ps(_mm512_sub_ps(p1, p0), w)),
            half,
        );
        let v = _mm512_permutexvar_ps(squeeze, v);
        // SAFETY: the twelve lanes stored end at `12·q + 12 <= 12·quads <= out.len()`.
        unsafe { _mm512_mask_storeu_ps(out.as_mut_ptr().add(12 * q), 0x0FFF, v) };
    }
    for x in 4 * quads..xs.first.len() {
        horizontal_pixel::<3>(blended, xs, x, out);
    }
}

/// The horizontal taps of one colour row, two output pixels to an 8-lane vector: each
/// half holds a pixel's three channels and a spare lane, blended as in
/// [`horizontal_taps`] (`p0 + (p1 − p0)·wx + 0.5`, the same operations in the same order,
/// so the same floats), then the two spare lanes are squeezed out and the six floats
/// stored together (the two lanes after them are overwritten by the next pair).
///
/// `blended` holds the row's `3·width` floats and four spare ones, `out` the output
/// row's `3·xs.len()` floats and four spare ones, and every tap is below `width`.
#[cfg(target_arch = "x86_64")]
#[target_feature(enable = "avx2")]
#[allow(unsafe_code)]
fn horizontal_rgb_avx2(blended: &[f32], xs: &HorizontalTaps, out: &mut [f32]) {
    use std::arch::x86_64::{
        __m128, _mm_loadu_ps, _mm256_add_ps, _mm256_loadu_ps, _mm256_mul_ps,
        _mm256_permutevar8x32_ps, _mm256_set_m128, _mm256_set1_ps, _mm256_setr_epi32,
        _mm256_storeu_ps, _mm256_sub_ps,
    };
    let pairs = xs.first.len() / 2;
    // Every read below ends by `blended[3·tap + 4]` and every write by
    // `out[6·pairs + 2]`: checked once here, not per pixel.
    if blended.len() < xs.last as usize + 4 || out.len() < 6 * pairs + 2 {
        return horizontal_taps::<3>(blended, xs, out);
    }
    let half = _mm256_set1_ps(0.5);
    let squeeze = _mm256_setr_epi32(0, 1, 2, 4, 5, 6, 7, 7);
    let load = |at: u32| -> __m128 {
        // SAFETY: `at + 4 <= blended.len()` for every tap (checked above).
        unsafe { _mm_loadu_ps(blended.as_ptr().add(at as usize)) }
    };
    for p in 0..pairs {
        let (a, b) = (2 * p, 2 * p + 1);
        let p0 = _mm256_set_m128(load(xs.first[b]), load(xs.first[a]));
        let p1 = _mm256_set_m128(load(xs.second[b]), load(xs.second[a]));
        // SAFETY: `weights` holds 8 floats per pair of output pixels.
        let w = unsafe { _mm256_loadu_ps(xs.pair_weights.as_ptr().add(8 * p)) };
        let v = _mm256_add_ps(
            _mm256_add_ps(p0, _mm256_mul_ps(_mm256_sub_ps(p1, p0), w)),
            half,
        );
        let v = _mm256_permutevar8x32_ps(v, squeeze);
        // SAFETY: `6·p + 8 <= 6·pairs + 2 <= out.len()` (checked above).
        unsafe { _mm256_storeu_ps(out.as_mut_ptr().add(6 * p), v) };
    }
    if xs.first.len() % 2 == 1 {
        let x = xs.first.len() - 1;
        horizontal_pixel::<3>(blended, xs, x, out);
    }
}

/// The horizontal taps of an output row, as offsets into a blended row of floats.
struct HorizontalTaps {
    /// Offset of each output pixel's first source pixel (`C·x0`).
    first: Vec<u32>,
    /// Offset of its second source pixel (`C·x1`).
    second: Vec<u32>,
    /// Weight of the second source pixel.
    weights: Vec<f32>,
    /// The weights two pixels to eight lanes (four of each), for the vector passes.
    pair_weights: Vec<f32>,
    /// The largest offset of either source pixel.
    last: u32,
}

impl HorizontalTaps {
    /// The taps of `width → out_width` for `channels`-channel rows, in reverse order when
    /// `mirrored`.
    fn new(width: usize, out_width: usize, channels: usize, mirrored: bool) -> Self {
        let mut taps = linear_taps(width, out_width);
        if mirrored {
            taps.reverse();
        }
        let offset = |x: usize| (x * channels) as u32;
        let weights: Vec<f32> = taps.iter().map(|t| t.2).collect();
        // A pixel's second source pixel is never before its first.
        let last = taps.iter().map(|t| offset(t.1)).max().unwrap_or(0);
        Self {
            last,
            first: taps.iter().map(|t| offset(t.0)).collect(),
            second: taps.iter().map(|t| offset(t.1)).collect(),
            pair_weights: weights
                .chunks_exact(2)
                .flat_map(|w| [w[0], w[0], w[0], w[0], w[1], w[1], w[1], w[1]])
                .collect(),
            weights,
        }
    }
}

/// Output pixel `x` of a row: its four lanes (the fourth is the next pixel's first
/// channel, overwritten by it) from the blended row into `out`.
#[inline(always)]
fn horizontal_pixel<const C: usize>(
    blended: &[f32],
    xs: &HorizontalTaps,
    x: usize,
    out: &mut [f32],
) {
    let (x0, x1, wx) = (xs.first[x] as usize, xs.second[x] as usize, xs.weights[x]);
    let p0: [f32; 4] = blended[x0..][..4].try_into().unwrap_or([0.0; 4]);
    let p1: [f32; 4] = blended[x1..][..4].try_into().unwrap_or([0.0; 4]);
    let mut v = [0f32; 4];
    for k in 0..4 {
        v[k] = p0[k] + (p1[k] - p0[k]) * wx + 0.5;
    }
    out[x * C..][..4].copy_from_slice(&v);
}

/// The horizontal taps of one row of `C ≥ 2` channels, pixel by pixel.
///
/// Every pixel stores all four lanes (the fourth is the next pixel's first channel,
/// which overwrites it), so the four lanes stay one vector; the truncation to bytes then
/// runs over the whole row in full vector lanes (done per pixel, packing four lanes into
/// four bytes cost more than the blend).
#[inline(always)]
fn horizontal_taps<const C: usize>(blended: &[f32], xs: &HorizontalTaps, out: &mut [f32]) {
    for x in 0..xs.first.len() {
        horizontal_pixel::<C>(blended, xs, x, out);
    }
}

#[inline(always)]
fn resize_bilinear_n<const C: usize>(data: &[u8], size: Size) -> Vec<u8> {
    resize_bilinear_with::<C>(data, size, horizontal_taps::<C>)
}

/// The resize with `horizontal` taking the horizontal taps of each colour row.
#[inline(always)]
fn resize_bilinear_with<const C: usize>(
    data: &[u8],
    size: Size,
    horizontal: impl Fn(&[f32], &HorizontalTaps, &mut [f32]),
) -> Vec<u8> {
    let [width, height, out_width, out_height] = size.dims;
    if width == 0 || height == 0 || out_width == 0 || data.len() < width * height * C {
        return vec![0u8; out_width * out_height * C];
    }
    // Filled row by row (a zeroed buffer would be written twice).
    let mut out = Vec::with_capacity(out_width * out_height * C);
    let xs = HorizontalTaps::new(width, out_width, C, size.mirrored);
    let ys = linear_taps(height, out_height);
    let stride = width * C;
    // Vertical blend of the two source rows into f32, then horizontal taps. Four spare
    // lanes let every pixel read four floats.
    let mut blended = vec![0f32; stride + 4];
    // One output row before truncation, with room for the last pixel's fourth lane.
    let mut horizontal_row = vec![0f32; out_width * C + 4];
    for &(y0, y1, wy) in &ys {
        let (r0, r1) = (
            &data[y0 * stride..][..stride],
            &data[y1 * stride..][..stride],
        );
        for ((b, a), c) in blended[..stride].iter_mut().zip(r0).zip(r1) {
            let a = f32::from(*a);
            *b = a + (f32::from(*c) - a) * wy;
        }
        if C == 1 {
            out.extend((0..out_width).map(|x| {
                let (x0, x1, wx) = (xs.first[x] as usize, xs.second[x] as usize, xs.weights[x]);
                let (p0, p1) = (blended[x0], blended[x1]);
                (p0 + (p1 - p0) * wx + 0.5) as u8
            }));
            continue;
        }
        horizontal(&blended, &xs, &mut horizontal_row);
        out.extend(
            horizontal_row[..out_width * C]
                .iter()
                .map(|&t| truncate_to_u8(t)),
        );
    }
    out
}

/// `t as u8` for `t` in `0.0..=255.5` (a blend of bytes plus one half), in plain float
/// arithmetic that stays in vector lanes (`as` saturates lane by lane): `t + 2²³` is `t`
/// rounded to an integer (the spacing of floats there is 1) plus 2²³, one less if that
/// rounded up, and its low mantissa byte is the integer.
#[inline(always)]
fn truncate_to_u8(t: f32) -> u8 {
    const TWO_23: f32 = 8_388_608.0;
    let shifted = t + TWO_23;
    let floor = if shifted - TWO_23 > t {
        shifted - 1.0
    } else {
        shifted
    };
    floor.to_bits() as u8
}

/// The input index nearest to the centre of output index `i` (`n_in → n_out`).
fn nearest_tap(i: usize, n_in: usize, n_out: usize) -> usize {
    (((i as f64 + 0.5) * n_in as f64 / n_out as f64) as usize).min(n_in - 1)
}

/// Nearest-neighbour resize of a single-channel map (labels must not be blended) to
/// `out_width × out_height`, widened to `U`, and mirrored left to right when `mirrored`
/// (the same values as resizing, flipping with [`flip_horizontal`] and widening, in one
/// pass).
pub fn resize_nearest<T: Copy, U: From<T> + Default + Clone>(
    data: &[T],
    [width, height]: [usize; 2],
    [out_width, out_height]: [usize; 2],
    mirrored: bool,
) -> Vec<U> {
    if width == 0 || height == 0 || data.len() < width * height {
        return vec![U::default(); out_width * out_height];
    }
    let mut xs: Vec<usize> = (0..out_width)
        .map(|x| nearest_tap(x, width, out_width))
        .collect();
    if mirrored {
        xs.reverse();
    }
    let mut out = Vec::with_capacity(out_width * out_height);
    for y in 0..out_height {
        let row = &data[nearest_tap(y, height, out_height) * width..][..width];
        // Every tap is below `width` already; the `min` says so to the compiler, which
        // then drops the bounds check from each pixel.
        out.extend(xs.iter().map(|&x| U::from(row[x.min(width - 1)])));
    }
    out
}

/// Mirrors an interleaved image left to right, in place.
pub fn flip_horizontal<T>(data: &mut [T], width: usize, channels: usize) {
    let stride = width * channels;
    if stride == 0 {
        return;
    }
    for row in data.chunks_exact_mut(stride) {
        match channels {
            1 => row.reverse(),
            3 => row.as_chunks_mut::<3>().0.reverse(),
            _ => {
                for x in 0..width / 2 {
                    for c in 0..channels {
                        row.swap(x * channels + c, (width - 1 - x) * channels + c);
                    }
                }
            }
        }
    }
}

/// The resized `(row, col)` of raw pixel `(u, v)` (OpenCV convention: pixel centres at
/// integers) when a `width × height` image becomes `out_width × out_height`; the
/// column is mirrored when the resized image is flipped.
pub fn resized_pixel(
    u: f32,
    v: f32,
    (width, height): (u32, u32),
    (out_width, out_height): (u32, u32),
    flipped: bool,
) -> (u16, u16) {
    // The floor of the scaled position, clamped to the image: clamping first and
    // truncating after (`as`) gives the same for every value, NaN included, without
    // libm's `floor` (x86-64 has no floor instruction before SSE4.1).
    let scale = |p: f32, n_in: u32, n_out: u32| {
        let x = (f64::from(p) + 0.5) * f64::from(n_out) / f64::from(n_in);
        x.clamp(0.0, f64::from(n_out.max(1) - 1)) as u16
    };
    let row = scale(v, height, out_height);
    let col = scale(u, width, out_width);
    let col = if flipped {
        (out_width.max(1) - 1) as u16 - col
    } else {
        col
    };
    (row, col)
}

#[cfg(test)]
mod tests {
    use super::*;

    /// Direct evaluation of the half-pixel bilinear formula, one output pixel at a time.
    fn reference(data: &[u8], w: usize, h: usize, ow: usize, oh: usize) -> Vec<u8> {
        let mut out = Vec::new();
        for y in 0..oh {
            for x in 0..ow {
                let sx = ((x as f64 + 0.5) * w as f64 / ow as f64 - 0.5).max(0.0);
                let sy = ((y as f64 + 0.5) * h as f64 / oh as f64 - 0.5).max(0.0);
                let (x0, y0) = (sx.floor() as usize, sy.floor() as usize);
                let (x1, y1) = ((x0 + 1).min(w - 1), (y0 + 1).min(h - 1));
                let (fx, fy) = (sx - x0 as f64, sy - y0 as f64);
                let p = |xx: usize, yy: usize| f64::from(data[yy * w + xx]);
                let v = p(x0, y0) * (1.0 - fx) * (1.0 - fy)
                    + p(x1, y0) * fx * (1.0 - fy)
                    + p(x0, y1) * (1.0 - fx) * fy
                    + p(x1, y1) * fx * fy;
                out.push(v.round() as u8);
            }
        }
        out
    }

    #[test]
    fn resized_pixels_are_the_clamped_floor() {
        let floored = |p: f32, n_in: u32, n_out: u32| {
            let x = ((f64::from(p) + 0.5) * f64::from(n_out) / f64::from(n_in)).floor();
            x.clamp(0.0, f64::from(n_out.max(1) - 1)) as u16
        };
        let mut values = vec![f32::NAN, f32::INFINITY, f32::NEG_INFINITY, -0.5, -0.7, -1.5];
        values.extend((-400..4000).map(|i| i as f32 * 0.437));
        values.extend((0..1600).map(|i| i as f32 - 0.5));
        for (size, out) in [
            ((1600, 900), (448, 224)),
            ((800, 450), (448, 224)),
            ((7, 5), (1, 1)),
        ] {
            for &u in &values {
                for flipped in [false, true] {
                    let (row, col) = resized_pixel(u, u * 0.6, size, out, flipped);
                    let want_col = floored(u, size.0, out.0);
                    let want_col = if flipped {
                        out.0 as u16 - 1 - want_col
                    } else {
                        want_col
                    };
                    assert_eq!(
                        (row, col),
                        (floored(u * 0.6, size.1, out.1), want_col),
                        "{u}"
                    );
                }
            }
        }
    }

    #[test]
    fn bilinear_matches_the_formula() {
        let (w, h) = (37, 23);
        let data: Vec<u8> = (0..w * h).map(|i| ((i * 97 + i / 7) % 251) as u8).collect();
        for (ow, oh) in [(16, 9), (74, 46), (37, 23), (50, 11)] {
            let got = resize_bilinear(&data, w, h, 1, ow, oh);
            let want = reference(&data, w, h, ow, oh);
            let worst = got
                .iter()
                .zip(&want)
                .map(|(a, b)| (i16::from(*a) - i16::from(*b)).abs())
                .max()
                .unwrap();
            assert!(worst <= 1, "{ow}x{oh}: off by {worst}");
        }
        // Same size is the identity; channels stay apart.
        let rgb: Vec<u8> = (0..6 * 4 * 3).map(|i| i as u8).collect();
        assert_eq!(resize_bilinear(&rgb, 6, 4, 3, 6, 4), rgb);
        // Downscaling 2x of a 2-px checker averages.
        let checker = [0u8, 200, 0, 200];
        assert_eq!(resize_bilinear(&checker, 4, 1, 1, 2, 1), [100, 100]);
    }

    /// The resize as first written (one channel at a time, one pixel at a time): the
    /// vectorized copies must give exactly its bytes.
    fn scalar_resize(data: &[u8], size: [usize; 4], channels: usize) -> Vec<u8> {
        let [w, h, ow, oh] = size;
        let (xs, ys) = (linear_taps(w, ow), linear_taps(h, oh));
        let mut out = Vec::new();
        for &(y0, y1, wy) in &ys {
            let blend = |x: usize, k: usize| {
                let a = f32::from(data[(y0 * w + x) * channels + k]);
                a + (f32::from(data[(y1 * w + x) * channels + k]) - a) * wy
            };
            for &(x0, x1, wx) in &xs {
                for k in 0..channels {
                    let (p0, p1) = (blend(x0, k), blend(x1, k));
                    out.push((p0 + (p1 - p0) * wx + 0.5) as u8);
                }
            }
        }
        out
    }

    #[test]
    fn truncation_in_lanes_is_as_u8_over_its_whole_range() {
        // Every float from 2^-10 to 255.5 (151 million), and a few below.
        let (lo, hi) = (2f32.powi(-10).to_bits(), 255.5f32.to_bits());
        for bits in lo..=hi {
            let t = f32::from_bits(bits);
            assert_eq!(truncate_to_u8(t), t as u8, "{t}");
        }
        for t in [
            0.0f32,
            -0.0,
            1e-30,
            0.5,
            0.999_999_94,
            1.0,
            254.999_98,
            255.0,
            255.5,
        ] {
            assert_eq!(truncate_to_u8(t), t as u8, "{t}");
        }
    }

    #[test]
    fn every_compiled_copy_gives_the_scalar_bytes() {
        let mut rng = crate::test_rng::TestRng(0x9e37_79b9_7f4a_7c15);
        let mut byte = move || (rng.next() >> 56) as u8;
        for (size, channels) in [
            ([800, 450, 448, 224], 3),
            ([1600, 900, 448, 224], 3),
            ([37, 23, 74, 46], 3),
            ([37, 23, 16, 9], 4),
            ([5, 3, 1, 1], 3),
            ([1, 1, 3, 2], 3),
            ([61, 17, 29, 40], 1),
        ] {
            let [w, h, ow, oh] = size;
            let data: Vec<u8> = (0..w * h * channels).map(|_| byte()).collect();
            let want = scalar_resize(&data, size, channels);
            assert_eq!(
                resize_bilinear(&data, w, h, channels, ow, oh),
                want,
                "{size:?}"
            );
            let inline = |mirrored| {
                let size = Size {
                    dims: size,
                    mirrored,
                };
                match channels {
                    1 => resize_bilinear_n::<1>(&data, size),
                    3 => resize_bilinear_n::<3>(&data, size),
                    _ => resize_bilinear_n::<4>(&data, size),
                }
            };
            assert_eq!(inline(false), want, "{size:?}, baseline copy");
            #[cfg(target_arch = "x86_64")]
            #[allow(unsafe_code)]
            for mirrored in [false, true] {
                let sized = Size {
                    dims: size,
                    mirrored,
                };
                // SAFETY: each copy is called below only where the CPU has its features.
                let copies = |avx512: bool| unsafe {
                    match (channels, avx512) {
                        (1, false) => resize_bilinear_avx2::<1>(&data, sized),
                        (3, false) => resize_bilinear_avx2::<3>(&data, sized),
                        (_, false) => resize_bilinear_avx2::<4>(&data, sized),
                        (1, true) => resize_bilinear_avx512::<1>(&data, sized),
                        (3, true) => resize_bilinear_avx512::<3>(&data, sized),
                        (_, true) => resize_bilinear_avx512::<4>(&data, sized),
                    }
                };
                let expected = if mirrored {
                    let mut flipped = want.clone();
                    flip_horizontal(&mut flipped, ow, channels);
                    flipped
                } else {
                    want.clone()
                };
                if crate::sample::simd::has_avx2() {
                    assert_eq!(copies(false), expected, "{size:?} {mirrored}, AVX2 copy");
                }
                if has_avx512() {
                    assert_eq!(copies(true), expected, "{size:?} {mirrored}, AVX-512 copy");
                }
            }
            // Mirrored: the same bytes as resizing, then flipping.
            let mut flipped = want.clone();
            flip_horizontal(&mut flipped, ow, channels);
            let mirrored = resize_bilinear_mirrored(&data, [w, h, channels], [ow, oh], true);
            assert_eq!(mirrored, flipped, "{size:?}, mirrored");
            assert_eq!(inline(true), flipped, "{size:?}, mirrored baseline copy");
        }
    }

    #[test]
    fn nearest_keeps_labels_and_flip_mirrors() {
        let labels: Vec<u8> = (0..4 * 2).collect();
        let up: Vec<u32> = resize_nearest(&labels, [4, 2], [8, 4], false);
        assert_eq!(&up[..8], &[0, 0, 1, 1, 2, 2, 3, 3]);
        assert_eq!(&up[16..24], &[4, 4, 5, 5, 6, 6, 7, 7]);
        // Mirrored in the same pass: resized, flipped and widened.
        let mirrored: Vec<u32> = resize_nearest(&labels, [4, 2], [8, 4], true);
        let mut flipped = up.clone();
        flip_horizontal(&mut flipped, 8, 1);
        assert_eq!(mirrored, flipped);
        assert_eq!(&mirrored[..8], &[3, 3, 2, 2, 1, 1, 0, 0]);
        let mut img = vec![1u8, 2, 3, 4, 5, 6, 7, 8, 9];
        flip_horizontal(&mut img, 3, 1);
        assert_eq!(img, [3, 2, 1, 6, 5, 4, 9, 8, 7]);
        let mut rgb = vec![1u8, 1, 1, 2, 2, 2];
        flip_horizontal(&mut rgb, 2, 3);
        assert_eq!(rgb, [2, 2, 2, 1, 1, 1]);
    }

    #[test]
    fn raw_pixels_map_into_the_resized_grid() {
        // 480x270 -> 448x224: the centre maps to the centre, corners to corners.
        let size = (480, 270);
        let out = (448, 224);
        assert_eq!(resized_pixel(239.5, 134.5, size, out, false), (112, 224));
        assert_eq!(resized_pixel(0.2, 0.3, size, out, false), (0, 0));
        assert_eq!(resized_pixel(478.9, 268.9, size, out, false), (223, 447));
        assert_eq!(resized_pixel(0.2, 0.3, size, out, true), (0, 447));
        // A pixel lands in the same place as the nearest-resized label map says.
        let labels: Vec<u32> = (0..480 * 270).collect();
        let small: Vec<u32> = resize_nearest(&labels, [480, 270], [448, 224], false);
        for (u, v) in [(10.0f32, 20.0f32), (300.0, 100.0), (479.0, 269.0)] {
            let (r, c) = resized_pixel(u, v, size, out, false);
            let src = small[r as usize * 448 + c as usize];
            let (su, sv) = (src % 480, src / 480);
            assert!((su as f32 - u).abs() <= 1.5 && (sv as f32 - v).abs() <= 1.5);
        }
    }
}
