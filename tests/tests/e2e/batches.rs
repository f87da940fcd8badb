//! Samples assembled into one batch (the wire format of `schemas/BATCH_FORMAT.md`) read
//! back through the batch reader: every section holds what the samples hold, with
//! global rows that point at the right points, pixels and voxels, and every section is
//! the one the section table (`superflow_schemas::batch::sections`) declares; a batch of
//! three rigs (6, 2 and 1 cameras, two image sizes and LiDARs) carries each sample's own
//! cameras and nothing else.

#![allow(clippy::unwrap_used, clippy::expect_used)] // tests fail loudly on purpose

use superflow_pipeline::batch::{BatchPlan, BatchShape};
use superflow_pipeline::drive::{Dataset, IngestConfig};
use superflow_pipeline::sample::{KernelMaps, Sample, SampleBuilder, SampleConfig};
use superflow_recordings::Dialect;
use superflow_schemas::batch::{BatchMeta, BatchView, Section};
use superflow_tests::{fleet_drives, sample_dataset, sample_drive};

#[test]
fn a_batch_holds_its_samples_with_global_rows() {
    let ds = sample_dataset(&sample_drive(Dialect::Ros2).unwrap()).unwrap();
    let config = SampleConfig::default();
    let builder = SampleBuilder::new(&ds, config.clone()).unwrap();
    let samples: Vec<_> = (0..3).map(|i| builder.build(0, i).unwrap()).collect();
    check_batch(&samples);
}

/// A 6-camera drive, a 2-camera one and a 1-camera one in one batch: every sample has
/// `min(3, its rig's cameras)` camera slots, and its images are its own.
#[test]
fn a_batch_of_three_rigs_holds_each_samples_own_cameras() {
    let ds = Dataset::open(&fleet_drives().unwrap(), &IngestConfig::default()).unwrap();
    let rigs: Vec<usize> = ds.drives.iter().map(|d| d.cameras.len()).collect();
    assert_eq!(rigs, [6, 2, 1]);
    let builder = SampleBuilder::new(&ds, SampleConfig::default()).unwrap();
    // Two keyframes of each drive, in drive order.
    let keyframes = &builder.plan().keyframes;
    let samples: Vec<Sample> = (0..3u32)
        .flat_map(|d| {
            let first = keyframes.iter().position(|k| k.drive == d).unwrap();
            [first, first + 1]
        })
        .enumerate()
        .map(|(i, k)| builder.build_keyframe(k, 0, i as u64).unwrap())
        .collect();
    let cameras: Vec<usize> = samples.iter().map(|s| s.cameras.len()).collect();
    assert_eq!(cameras, [3, 3, 2, 2, 1, 1]);
    check_batch(&samples);
}

/// Writes `samples` as one batch and checks every section against them.
fn check_batch(samples: &[Sample]) {
    let shape = BatchShape {
        height: 224,
        width: 448,
        levels: 5,
        maps: KernelMaps::Unet,
    };
    let plan = BatchPlan::new(samples, shape).unwrap();
    let layout = plan.layout();
    let mut storage = vec![0u64; layout.payload_len().div_ceil(8)];
    let payload: &mut [u8] = bytemuck::cast_slice_mut(&mut storage);
    plan.write(samples, payload).unwrap();
    // Bit-identical when written again.
    let first = payload.to_vec();
    plan.write(samples, payload).unwrap();
    assert!(first == payload);
    // Into a freshly zeroed loan (the service's path): the same bytes.
    let mut zeroed = vec![0u64; layout.payload_len().div_ceil(8)];
    let zeroed_bytes: &mut [u8] = bytemuck::cast_slice_mut(&mut zeroed);
    plan.write_zeroed(samples, zeroed_bytes).unwrap();
    assert!(first[..] == zeroed_bytes[..first.len()]);
    let meta = BatchMeta {
        run: "batch-test".into(),
        epoch: 0,
        step: 0,
        seed: 0,
        sequence: 0,
        created_unix_nanos: 0,
        sample_count: samples.len() as u32,
        flags: 0,
    };
    let header = layout.header(&meta).unwrap();
    let view = BatchView::new(&header, payload).unwrap();
    let (b, f, c) = (samples.len(), 3usize, 4usize);
    // Each sample's camera slots, and the first image row of each.
    let first_slot: Vec<usize> = std::iter::once(0)
        .chain(samples.iter().scan(0, |sum, s| {
            *sum += s.cameras.len();
            Some(*sum)
        }))
        .collect();
    let slots = first_slot[b];

    let ids = view.get::<u64>("sample_ids").unwrap();
    for (i, s) in samples.iter().enumerate() {
        assert_eq!(
            &ids.data[i * 5..i * 5 + 5],
            &[
                s.id.epoch,
                s.id.index,
                u64::from(s.id.keyframe),
                u64::from(s.id.drive),
                u64::from(s.id.sweep)
            ]
        );
    }
    let sample_cameras = view.get::<u32>("sample_cameras").unwrap();
    let as_u32: Vec<u32> = first_slot.iter().map(|&v| v as u32).collect();
    assert_eq!(sample_cameras.data, &as_u32[..]);
    let camera_ids = view.get::<u32>("camera_ids").unwrap();
    let expected_ids: Vec<u32> = samples
        .iter()
        .flat_map(|s| s.camera_indices.iter().copied())
        .collect();
    assert_eq!(camera_ids.data, &expected_ids[..]);
    let image_stamps = view.get::<i64>("image_stamps").unwrap();
    assert_eq!(image_stamps.data.len(), f * slots);
    let points = view.get::<f32>("points").unwrap();
    let point_clouds = view.get::<u32>("point_clouds").unwrap();
    assert_eq!(point_clouds.data.len(), b * c + 1);
    let images = view.get::<u8>("images").unwrap();
    assert_eq!(images.shape(), &[f * slots, 224, 448, 3]);
    let superpixels = view.get::<u16>("superpixels").unwrap();
    let pairing_point = view.get::<u32>("pairing_point").unwrap();
    let pairing_image = view.get::<u32>("pairing_image").unwrap();
    let pairing_pixel = view.get::<u16>("pairing_pixel").unwrap();
    let pairing_sp = view.get::<u32>("pairing_superpixel").unwrap();
    let pairing_clouds = view.get::<u32>("pairing_clouds").unwrap();
    let p2v = view.get::<u32>("point_to_voxel").unwrap();
    let l0 = view.get::<i32>("l0_coords").unwrap();
    for (bi, s) in samples.iter().enumerate() {
        let k = s.cameras.len();
        // Every image row of the sample is one of its own camera images, in frame then
        // slot order.
        for (fi, frame) in s.frames.iter().enumerate() {
            assert_eq!(frame.images.len(), k);
            for (slot, img) in frame.images.iter().enumerate() {
                let row = f * first_slot[bi] + fi * k + slot;
                assert_eq!(image_stamps.data[row], img.stamp.nanos());
                let px = 224 * 448 * 3;
                assert!(images.data[row * px..(row + 1) * px] == img.rgb[..]);
            }
        }
        let clouds: Vec<_> = s
            .frames
            .iter()
            .map(|fr| &fr.cloud)
            .chain([&s.dense])
            .collect();
        for (ci, cloud) in clouds.iter().enumerate() {
            let g = bi * c + ci;
            let p0 = point_clouds.data[g] as usize;
            assert_eq!(point_clouds.data[g + 1] as usize - p0, cloud.xyz.len());
            for (i, p) in cloud.xyz.iter().enumerate().step_by(53) {
                assert_eq!(&points.data[(p0 + i) * 4..(p0 + i) * 4 + 3], p);
                // The point's voxel row holds its cell, tagged with its cloud.
                let v = p2v.data[p0 + i] as usize;
                let cell = cloud.voxels.coords[cloud.voxels.point_to_voxel[i] as usize];
                assert_eq!(
                    &l0.data[v * 4..v * 4 + 4],
                    &[g as i32, cell[0], cell[1], cell[2]]
                );
            }
            let q0 = pairing_clouds.data[g] as usize;
            assert_eq!(
                pairing_clouds.data[g + 1] as usize - q0,
                cloud.pairings.len()
            );
            let frame = if ci == f { s.key_frame } else { ci };
            for (j, p) in cloud.pairings.iter().enumerate().step_by(17) {
                let row = q0 + j;
                assert_eq!(pairing_point.data[row] as usize, p0 + p.point as usize);
                let image = pairing_image.data[row] as usize;
                assert_eq!(
                    image,
                    f * first_slot[bi] + frame * k + usize::from(p.camera)
                );
                let [r, col] = [pairing_pixel.data[row * 2], pairing_pixel.data[row * 2 + 1]];
                assert_eq!((r, col), (p.row, p.col));
                // The superpixel of the pairing is the id map's value at its pixel.
                let id = superpixels.data[(image * 224 + r as usize) * 448 + col as usize];
                assert_eq!(u32::from(id), pairing_sp.data[row]);
                let img = &s.frames[frame].images[usize::from(p.camera)];
                let px = (usize::from(r) * 448 + usize::from(col)) * 3;
                assert_eq!(
                    &images.data[image * 224 * 448 * 3 + px..][..3],
                    &img.rgb[px..px + 3]
                );
            }
        }
    }
    // Neighbour maps: every pair joins cells of one cloud that differ by the offset.
    for l in 0..5 {
        let coords = view.get::<i32>(&format!("l{l}_coords")).unwrap();
        let nbr = view.get::<u32>(&format!("l{l}_nbr")).unwrap();
        let starts = view.get::<u32>(&format!("l{l}_nbr_starts")).unwrap();
        let cell = |r: u32| &coords.data[r as usize * 4..r as usize * 4 + 4];
        for kern in 0..27usize {
            let o = [
                kern as i32 / 9 - 1,
                (kern as i32 / 3) % 3 - 1,
                kern as i32 % 3 - 1,
            ];
            for e in starts.data[kern]..starts.data[kern + 1] {
                let (i, out) = (nbr.data[e as usize * 2], nbr.data[e as usize * 2 + 1]);
                let (a, z) = (cell(i), cell(out));
                assert_eq!(a[0], z[0]);
                assert_eq!([a[1] - z[1], a[2] - z[2], a[3] - z[3]], o);
            }
        }
        // Centre offset: identity on every row.
        assert_eq!(
            (starts.data[14] - starts.data[13]) as usize,
            coords.shape()[0]
        );
        if l < 4 {
            let down = view.get::<u32>(&format!("l{l}_down")).unwrap();
            let coarse = view.get::<i32>(&format!("l{}_coords", l + 1)).unwrap();
            assert_eq!(down.shape(), &[coords.shape()[0], 2]);
            for pair in down.data.chunks_exact(2).step_by(11) {
                let fine = cell(pair[0]);
                let parent = &coarse.data[pair[1] as usize * 4..pair[1] as usize * 4 + 4];
                assert_eq!(fine[0], parent[0]);
                for d in 1..4 {
                    assert_eq!(fine[d].div_euclid(2), parent[d]);
                }
            }
        }
    }
    // Every section is one of the table's, in the table's order, with its dtype and rank.
    let names: Vec<&str> = view.section_names().collect();
    let table: Vec<String> = Section::in_order(5)
        .map(|s| s.name().into_owned())
        .collect();
    assert_eq!(names, table);
    for section in Section::in_order(5) {
        let (dtype, shape) = view.describe(&section.name()).unwrap();
        assert_eq!(dtype, section.spec().dtype, "{}", section.name());
        section.check_shape(shape).unwrap();
    }
    eprintln!(
        "batch of {b} samples: {} sections, {:.1} MB",
        view.section_names().count(),
        layout.payload_len() as f64 / 1e6
    );
}

#[test]
fn a_superpixel_id_beyond_16_bits_is_an_error_not_a_wrap() {
    let ds = sample_dataset(&sample_drive(Dialect::Foxglove).unwrap()).unwrap();
    let config = SampleConfig::default();
    let builder = SampleBuilder::new(&ds, config.clone()).unwrap();
    let mut samples = vec![builder.build(0, 0).unwrap()];
    let shape = BatchShape::of(&config);
    let plan = BatchPlan::new(&samples, shape).unwrap();
    let mut payload = vec![0u8; plan.layout().payload_len()];
    plan.write(&samples, &mut payload).unwrap();
    let image = &mut samples[0].frames[1].images[0];
    image.superpixels[17] = 65_536 + 3;
    let camera = image.camera.clone();
    let e = plan.write(&samples, &mut payload).unwrap_err().to_string();
    assert!(e.contains("superpixels"), "{e}");
    assert!(e.contains("65539") && e.contains(&camera), "{e}");
}

/// `kernel_maps = "none"` (for a 3D network that builds its own maps): the same samples,
/// every section byte for byte what the default recipe's batch holds, level 0's voxels
/// included, and no map (the payload is the default one cut before `l0_nbr`); a batch
/// planned with maps from samples built without them is refused, not written short.
#[test]
fn a_recipe_without_kernel_maps_sends_the_same_batch_less_its_maps() {
    let ds = sample_dataset(&sample_drive(Dialect::Foxglove).unwrap()).unwrap();
    let with = SampleConfig::default();
    let without = SampleConfig {
        kernel_maps: KernelMaps::None,
        ..with.clone()
    };
    let write = |config: &SampleConfig| {
        let builder = SampleBuilder::new(&ds, config.clone()).unwrap();
        let samples: Vec<Sample> = (0..2).map(|i| builder.build(1, i).unwrap()).collect();
        let plan = BatchPlan::new(&samples, BatchShape::of(config)).unwrap();
        let mut payload = vec![0u8; plan.layout().payload_len()];
        plan.write(&samples, &mut payload).unwrap();
        let meta = BatchMeta {
            run: "maps-test".into(),
            sample_count: samples.len() as u32,
            ..BatchMeta::default()
        };
        (plan.layout().header(&meta).unwrap(), payload, samples)
    };
    let (full_header, full_bytes, _) = write(&with);
    let (bare_header, bare_bytes, bare_samples) = write(&without);
    assert!(
        bare_samples.iter().all(
            |s| s.dense.levels.is_empty() && s.frames.iter().all(|f| f.cloud.levels.is_empty())
        )
    );
    let full = BatchView::new(&full_header, &full_bytes).unwrap();
    let bare = BatchView::new(&bare_header, &bare_bytes).unwrap();
    let names: Vec<&str> = bare.section_names().collect();
    let expected: Vec<String> = Section::in_order_unmapped()
        .map(|s| s.name().into_owned())
        .collect();
    assert_eq!(names, expected);
    assert_eq!(names[names.len() - 2..], ["l0_coords", "l0_clouds"]);
    for name in names {
        assert!(
            full.bytes(name).unwrap() == bare.bytes(name).unwrap(),
            "section {name} differs"
        );
    }
    // The maps' sections come last, so the whole payload is the default one cut short.
    let (full_len, bare_len) = (full_bytes.len(), bare_bytes.len());
    assert!(bare_len < full_len);
    assert!(full_bytes[..bare_len] == bare_bytes[..]);
    eprintln!("2 samples: {full_len} bytes with the maps, {bare_len} without");

    let builder = SampleBuilder::new(&ds, without).unwrap();
    let samples = vec![builder.build(0, 0).unwrap()];
    let e = BatchPlan::new(&samples, BatchShape::of(&with))
        .unwrap_err()
        .to_string();
    assert!(e.contains("no level 0"), "{e}");
}
