//! Tests of SLIC: scikit-image golden labels, edge adherence, determinism, degenerate sizes.

use super::*;
use std::time::Instant;

const W: usize = 448;
const H: usize = 224;

/// Deterministic hash noise in `-amp..=amp`.
fn noise(i: usize, c: usize, amp: i32) -> i32 {
    let mut h = (i as u64 * 3 + c as u64 + 1).wrapping_mul(0x9E37_79B9_7F4A_7C15);
    h ^= h >> 29;
    h = h.wrapping_mul(0xBF58_476D_1CE4_E5B9);
    h ^= h >> 32;
    (h % (2 * amp as u64 + 1)) as i32 - amp
}

const COLOURS: [[u8; 3]; 13] = [
    [220, 40, 40],
    [40, 200, 60],
    [40, 60, 220],
    [230, 220, 50],
    [200, 60, 200],
    [50, 200, 210],
    [250, 250, 250],
    [20, 20, 20],
    [240, 140, 30],
    [120, 60, 20],
    [130, 130, 130],
    [110, 180, 120],
    [150, 100, 250],
];

/// A W×H image of `cols × rows` flat blocks of distinct colours and a diagonal stripe
/// (`|x − 2y| < 24`), with ±8 noise: the true region of each pixel and the RGB8 image.
fn blocks(cols: usize, rows: usize) -> (Vec<u32>, Vec<u8>) {
    let mut regions = vec![0u32; W * H];
    let mut rgb = vec![0u8; 3 * W * H];
    for y in 0..H {
        for x in 0..W {
            let i = y * W + x;
            let region = if (x as i64 - 2 * y as i64).abs() < 24 {
                12
            } else {
                x * cols / W + cols * (y * rows / H)
            };
            regions[i] = region as u32;
            for c in 0..3 {
                let v = i32::from(COLOURS[region][c]) + noise(i, c, 8);
                rgb[3 * i + c] = v.clamp(0, 255) as u8;
            }
        }
    }
    (regions, rgb)
}

/// A `width × height` patchwork of 11×9 cells of pseudo-random colours, ±12 noise.
fn patchwork(width: usize, height: usize) -> Vec<u8> {
    let mut rgb = vec![0u8; 3 * width * height];
    for y in 0..height {
        for x in 0..width {
            let (i, cell) = (y * width + x, (y / 9) * 1000 + x / 11);
            for c in 0..3 {
                let base = 128 + noise(cell + 7, c, 110);
                rgb[3 * i + c] = (base + noise(i, c, 12)).clamp(0, 255) as u8;
            }
        }
    }
    rgb
}

/// FNV-1a over the labels' little-endian bytes.
fn fnv(labels: &[u32]) -> u64 {
    let mut h = 0xcbf2_9ce4_8422_2325u64;
    for b in labels.iter().flat_map(|l| l.to_le_bytes()) {
        h = (h ^ u64::from(b)).wrapping_mul(0x0000_0100_0000_01b3);
    }
    h
}

/// Pixels whose right or lower neighbour has another value.
fn boundaries(map: &[u32], width: usize, height: usize) -> Vec<bool> {
    let mut out = vec![false; map.len()];
    for y in 0..height {
        for x in 0..width {
            let i = y * width + x;
            out[i] = (x + 1 < width && map[i + 1] != map[i])
                || (y + 1 < height && map[i + width] != map[i]);
        }
    }
    out
}

/// Asserts dense labels in raster order of first appearance and 4-connected segments.
fn check_dense_and_connected(seg: &Segmentation, width: usize, height: usize) {
    assert_eq!(seg.labels.len(), width * height);
    let count = seg.count as usize;
    let mut next = 0;
    let mut size = vec![0usize; count];
    for &l in &seg.labels {
        let l = l as usize;
        assert!(l < count, "label {l} >= count {count}");
        if size[l] == 0 {
            assert_eq!(l, next, "labels not in raster order of first appearance");
            next += 1;
        }
        size[l] += 1;
    }
    assert_eq!(next, count, "labels are not dense");
    // A flood fill from each segment's first pixel reaches all of it.
    let mut reached = vec![false; seg.labels.len()];
    let mut stack = Vec::new();
    for start in 0..seg.labels.len() {
        if reached[start] {
            continue;
        }
        let l = seg.labels[start];
        let mut filled = 0;
        reached[start] = true;
        stack.push(start);
        while let Some(p) = stack.pop() {
            filled += 1;
            let (y, x) = (p / width, p % width);
            let neighbours = [
                (x + 1 < width).then(|| p + 1),
                (x > 0).then(|| p - 1),
                (y + 1 < height).then(|| p + width),
                (y > 0).then(|| p - width),
            ];
            for q in neighbours.into_iter().flatten() {
                if !reached[q] && seg.labels[q] == l {
                    reached[q] = true;
                    stack.push(q);
                }
            }
        }
        assert_eq!(filled, size[l as usize], "segment {l} is not 4-connected");
    }
}

#[test]
fn slic_params_default_validate_and_deserialize() {
    let p = SlicParams::default();
    assert_eq!(
        (p.n_segments, p.compactness, p.sigma, p.max_iterations),
        (150, 6.0, 3.0, 10)
    );
    assert_eq!(p.min_size_factor, 0.5);
    p.validate().unwrap();
    SlicParams {
        n_segments: super::MAX_SEGMENTS,
        ..p
    }
    .validate()
    .unwrap();
    for bad in [
        SlicParams { n_segments: 0, ..p },
        SlicParams {
            n_segments: super::MAX_SEGMENTS + 1,
            ..p
        },
        SlicParams {
            max_iterations: 0,
            ..p
        },
        SlicParams {
            compactness: 0.0,
            ..p
        },
        SlicParams {
            compactness: f32::NAN,
            ..p
        },
        SlicParams { sigma: -1.0, ..p },
        SlicParams {
            sigma: f32::INFINITY,
            ..p
        },
        SlicParams {
            min_size_factor: 3.0,
            ..p
        },
    ] {
        assert!(bad.validate().is_err(), "{bad:?}");
    }
    let q: SlicParams = serde_json::from_str(r#"{"n_segments": 100}"#).unwrap();
    assert_eq!(
        q,
        SlicParams {
            n_segments: 100,
            ..p
        }
    );
    assert!(serde_json::from_str::<SlicParams>(r#"{"segments": 100}"#).is_err());
}

#[test]
fn slic_regular_grid_matches_scikit_image() {
    // 224×448, 150 segments: step √(100352/150) = 25.87 → start 12, step 26.
    assert_eq!(regular_grid(224, 448, 150), [(12, 26), (12, 26)]);
    assert_eq!(regular_grid(448, 224, 150), [(12, 26), (12, 26)]);
    // Fewer pixels than points: every pixel is a centre.
    assert_eq!(regular_grid(1, 1, 150), [(0, 1), (0, 1)]);
    assert_eq!(regular_grid(10, 10, 150), [(0, 1), (0, 1)]);
    // A thin strip: one row of centres.
    assert_eq!(regular_grid(3, 500, 150), [(1, 3), (1, 3)]);
    assert_eq!(regular_grid(500, 3, 150), [(1, 3), (1, 3)]);
    assert_eq!(nearest_on_grid(10, 1, 3, 3), [0, 0, 0, 1, 1, 1, 2, 2, 2, 2]);
    assert_eq!(nearest_on_grid(7, 1, 4, 2), [0, 0, 0, 0, 1, 1, 1]);
}
/// The golden cases: name, width, height, image, parameters.
fn golden_cases() -> Vec<(&'static str, usize, usize, Vec<u8>, SlicParams)> {
    let p = SlicParams::default();
    vec![
        ("blocks 4x3", W, H, blocks(4, 3).1, p),
        ("blocks 2x2", W, H, blocks(2, 2).1, p),
        ("constant", W, H, vec![90; 3 * W * H], p),
        (
            "patchwork 97x61",
            97,
            61,
            patchwork(97, 61),
            SlicParams {
                n_segments: 40,
                compactness: 10.0,
                sigma: 1.5,
                max_iterations: 10,
                min_size_factor: 0.3,
            },
        ),
        ("patchwork 61x97", 61, 97, patchwork(61, 97), p),
        ("patchwork 3x500", 500, 3, patchwork(500, 3), p),
    ]
}

/// scikit-image 0.26's labels for [`golden_cases`] (count, FNV-1a of the labels),
/// from `skimage.segmentation.slic(rgb, n_segments, compactness, sigma,
/// max_num_iter=max_iterations, min_size_factor=…, start_label=0)` (its defaults
/// otherwise) on the same images written out as raw RGB8.
const GOLDEN: [(u32, u64); 6] = [
    (85, 0x3a43_2130_7660_46fd),
    (103, 0x6f2b_5db1_c22c_cc6b),
    (153, 0x49f8_cef2_27ce_afc9),
    (55, 0x93a7_4440_2c1d_9330),
    (153, 0x942a_0b97_4fc6_34d5),
    (167, 0xe19c_116c_0b8b_7b18),
];

#[test]
fn slic_matches_scikit_image_exactly() {
    for ((name, w, h, rgb, params), (count, hash)) in golden_cases().into_iter().zip(GOLDEN) {
        let seg = slic(&rgb, w, h, &params);
        check_dense_and_connected(&seg, w, h);
        assert_eq!(
            (seg.count, fnv(&seg.labels)),
            (count, hash),
            "{name}: labels differ from scikit-image's"
        );
    }
}

#[test]
#[allow(unsafe_code)]
fn slic_baseline_and_avx2_copies_agree() {
    // `slic` runs the widest copy the CPU has; `slic_inline` is the baseline one, and
    // every copy the CPU can run is compared with it.
    let (_, street) = blocks(3, 2);
    let mut cases = golden_cases();
    cases.push(("blocks 3x2", W, H, street, SlicParams::default()));
    for (name, w, h, rgb, params) in cases {
        let baseline = slic_inline(&rgb, w, h, &params);
        assert_eq!(slic(&rgb, w, h, &params), baseline, "{name}");
        #[cfg(target_arch = "x86_64")]
        {
            if crate::sample::simd::has_avx2() {
                // SAFETY: the CPU runs AVX2.
                let avx2 = unsafe { super::slic_avx2(&rgb, w, h, &params) };
                assert_eq!(avx2, baseline, "{name}: AVX2 copy");
            }
            if crate::sample::simd::has_avx512() {
                // SAFETY: the CPU runs AVX-512 F and BW.
                let avx512 = unsafe { super::slic_avx512(&rgb, w, h, &params) };
                assert_eq!(avx512, baseline, "{name}: AVX-512 copy");
            }
        }
    }
}

#[test]
fn slic_follows_edges_of_synthetic_image() {
    let (regions, rgb) = blocks(2, 2);
    let seg = slic(&rgb, W, H, &SlicParams::default());
    check_dense_and_connected(&seg, W, H);
    let count = seg.count;
    println!("slic: {count} segments on 2x2 blocks + stripe, {W}x{H} (asked 150)");
    assert!(
        (98..=202).contains(&count),
        "{count} segments, not within 35 % of 150"
    );

    // Boundary recall: true edge pixels with a segment boundary within `tol` px.
    let truth = boundaries(&regions, W, H);
    let found = boundaries(&seg.labels, W, H);
    let recall = |tol: usize| {
        let (mut edges, mut recalled) = (0usize, 0usize);
        for y in 0..H {
            for x in 0..W {
                if truth[y * W + x] {
                    edges += 1;
                    let near = (y.saturating_sub(tol)..(y + tol + 1).min(H)).any(|yy| {
                        (x.saturating_sub(tol)..(x + tol + 1).min(W)).any(|xx| found[yy * W + xx])
                    });
                    recalled += usize::from(near);
                }
            }
        }
        recalled as f64 / edges as f64
    };
    // Undersegmentation: the share of each segment's pixels in its majority region.
    let mut hist = vec![[0usize; 13]; count as usize];
    for (&l, &r) in seg.labels.iter().zip(&regions) {
        hist[l as usize][r as usize] += 1;
    }
    let purity = hist
        .iter()
        .map(|h| *h.iter().max().unwrap() as f64 / h.iter().sum::<usize>() as f64)
        .sum::<f64>()
        / f64::from(count);
    let (r2, r3) = (recall(2), recall(3));
    println!("slic: boundary recall {r2:.3} within 2 px, {r3:.3} within 3 px; purity {purity:.4}");
    // scikit-image gives the same numbers: σ = 3 smoothing and compactness 6 leave thin
    // segments along the edges that the connectivity step merges into one side, so
    // boundaries sit up to 3 px off the true edges.
    assert!(r3 >= 0.90, "boundary recall {r3} within 3 px");
    assert!(purity >= 0.95, "purity {purity}");
}

#[test]
fn slic_is_deterministic_and_timed() {
    let (_, rgb) = blocks(4, 3);
    let params = SlicParams::default();
    let first = slic(&rgb, W, H, &params);
    check_dense_and_connected(&first, W, H);
    let runs = if cfg!(debug_assertions) { 2 } else { 20 };
    let t = Instant::now();
    for _ in 0..runs {
        assert_eq!(slic(&rgb, W, H, &params), first);
    }
    let ms = t.elapsed().as_secs_f64() * 1e3 / f64::from(runs);
    println!(
        "slic: {ms:.2} ms per {W}x{H} image ({} segments; 4x3 blocks + stripe)",
        first.count
    );
}

#[test]
fn slic_constant_image_is_a_grid() {
    let seg = slic(&vec![90u8; 3 * W * H], W, H, &SlicParams::default());
    check_dense_and_connected(&seg, W, H);
    // The 9 × 17 cells of scikit-image's regular_grid, each about a 26-px square.
    assert_eq!(seg.count, 153);
    let mut boxes = vec![[usize::MAX, usize::MAX, 0, 0]; seg.count as usize];
    let mut sizes = vec![0usize; seg.count as usize];
    for y in 0..H {
        for x in 0..W {
            let l = seg.labels[y * W + x] as usize;
            let b = &mut boxes[l];
            *b = [b[0].min(y), b[1].min(x), b[2].max(y), b[3].max(x)];
            sizes[l] += 1;
        }
    }
    for (b, &size) in boxes.iter().zip(&sizes) {
        let (h, w) = (b[2] - b[0] + 1, b[3] - b[1] + 1);
        assert!(h <= 32 && w <= 32, "box {h}x{w}");
        assert!(size * 10 >= h * w * 9, "size {size} in a {h}x{w} box");
    }
}

#[test]
fn slic_degenerate_sizes_do_not_panic() {
    let p = SlicParams::default();
    let empty = slic(&[], 0, 0, &p);
    assert_eq!((empty.labels.len(), empty.count), (0, 0));
    assert_eq!(slic(&[], 0, 10, &p).count, 0);
    assert_eq!(slic(&[], 10, 0, &p).count, 0);
    let one = slic(&[1, 2, 3], 1, 1, &p);
    assert_eq!(
        one,
        Segmentation {
            labels: vec![0],
            count: 1
        }
    );
    let sizes = [
        (3, 500),
        (500, 3),
        (1, 700),
        (700, 1),
        (2, 2),
        (13, 9),
        (20, 20),
    ];
    for (w, h) in sizes {
        let rgb = patchwork(w, h);
        for params in [
            p,
            SlicParams { n_segments: 1, ..p },
            SlicParams {
                n_segments: u32::MAX,
                max_iterations: 2,
                ..p
            },
            SlicParams {
                n_segments: 0,
                compactness: f32::NAN,
                sigma: f32::INFINITY,
                max_iterations: 0,
                min_size_factor: f32::NAN,
            },
            SlicParams {
                compactness: 0.0,
                sigma: 0.0,
                min_size_factor: 2.9,
                ..p
            },
        ] {
            let seg = slic(&rgb, w, h, &params);
            assert!(seg.count >= 1, "{w}x{h} {params:?}");
            check_dense_and_connected(&seg, w, h);
        }
    }
}

/// Camera images of the sample drives, resized as samples have them (448×224 by default):
/// `(width, height, rgb)`.
fn drive_images() -> Vec<(usize, usize, Vec<u8>)> {
    use crate::drive::{Dataset, IngestConfig};
    use crate::sample::recipe::SuperpixelSource;
    use crate::sample::{SampleBuilder, SampleConfig};
    let mut images = Vec::new();
    for name in ["street_foxglove", "street_ros2"] {
        let path = superflow_recordings::sample_drive_path(name);
        let dataset = Dataset::open(&[path], &IngestConfig::default()).expect("drive");
        let config = SampleConfig {
            superpixels: SuperpixelSource::Channel,
            ..SampleConfig::default()
        };
        let (w, h) = (config.image_width as usize, config.image_height as usize);
        let builder = SampleBuilder::new(&dataset, config).expect("builder");
        let keyframes = builder.plan().keyframes.len() as u64;
        for i in 0..4 {
            let sample = builder.build(0, (i * 5) % keyframes).expect("sample");
            for frame in &sample.frames {
                images.extend(frame.images.iter().map(|im| (w, h, im.rgb.clone())));
            }
        }
    }
    images
}

/// Time per image on the sample drives' camera images (`cargo test --release -p
/// superflow-pipeline --lib slic_timing_on_drive_images -- --ignored --nocapture`, best
/// pinned to one core: `taskset -c 1`).
#[test]
#[ignore]
fn slic_timing_on_drive_images() {
    let images = drive_images();
    let params = SlicParams::default();
    let mut ms = Vec::new();
    for _ in 0..3 {
        for (w, h, rgb) in &images {
            let t = Instant::now();
            let seg = slic(rgb, *w, *h, &params);
            ms.push(t.elapsed().as_secs_f64() * 1e3);
            assert!(seg.count > 0);
        }
    }
    ms.sort_by(f64::total_cmp);
    let (w, h, _) = &images[0];
    println!(
        "slic: {} images {w}x{h}, median {:.2} ms, fastest {:.2} ms",
        images.len(),
        ms[ms.len() / 2],
        ms[0]
    );
}
