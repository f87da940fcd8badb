//! SLIC computed once into a `<drive>.slic.mcap` sidecar (`superflow-pipeline
//! superpixels`): samples read the same labels SLIC gives — exactly for unflipped
//! images, mirrored for flipped ones — and a sidecar written for other settings is not
//! used.

#![allow(clippy::unwrap_used, clippy::expect_used)] // tests fail loudly on purpose

use superflow_pipeline::drive::{Dataset, IngestConfig};
use superflow_pipeline::sample::image_ops::flip_horizontal;
use superflow_pipeline::sample::recipe::SuperpixelSource;
use superflow_pipeline::sample::sidecar::{
    read_labels, sidecar_matches, sidecar_path, write_sidecar,
};
use superflow_pipeline::sample::slic::slic;
use superflow_pipeline::sample::{Sample, SampleBuilder, SampleConfig};
use superflow_recordings::Dialect;
use superflow_tests::sample_drive;

fn samples(dataset: &Dataset, config: &SampleConfig, n: u64) -> Vec<Sample> {
    let builder = SampleBuilder::new(dataset, config.clone()).unwrap();
    (0..n).map(|i| builder.build(0, i).unwrap()).collect()
}

/// An image's ids without the offset of the images before it in its frame.
fn local(ids: &[u32]) -> Vec<u32> {
    let first = ids.iter().min().copied().unwrap_or_default();
    ids.iter().map(|id| id - first).collect()
}

#[test]
fn samples_read_slic_from_the_sidecar_as_slic_would_give_it() {
    let drive = sample_drive(Dialect::Foxglove).unwrap();
    let dir = std::env::temp_dir().join(format!("superflow-slic-{}", std::process::id()));
    std::fs::create_dir_all(&dir).unwrap();
    let path = dir.join("street_foxglove.mcap");
    std::fs::copy(&drive.path, &path).unwrap();
    let config = SampleConfig {
        superpixels: SuperpixelSource::Slic,
        ..SampleConfig::default()
    };
    let inline = samples(
        &Dataset::open(std::slice::from_ref(&path), &IngestConfig::default()).unwrap(),
        &config,
        6,
    );

    // Written for other settings: found, not used (the samples stay the in-line ones).
    let other = SampleConfig {
        slic: superflow_pipeline::sample::slic::SlicParams {
            n_segments: 40,
            ..config.slic
        },
        ..config.clone()
    };
    let before = Dataset::open(std::slice::from_ref(&path), &IngestConfig::default()).unwrap();
    let sidecar = sidecar_path(&before.drives[0]).unwrap();
    assert_eq!(sidecar, dir.join("street_foxglove.slic.mcap"));
    let written = write_sidecar(&before.drives[0], &other, &sidecar, &|| {}).unwrap();
    let images: usize = before.drives[0]
        .cameras
        .iter()
        .map(|c| c.frames.len())
        .sum();
    assert_eq!(written.images, images);
    let dataset = Dataset::open(std::slice::from_ref(&path), &IngestConfig::default()).unwrap();
    assert!(dataset.drives[0].cameras.iter().all(|c| c.slic.is_some()));
    assert!(!sidecar_matches(&dataset.drives[0], &config));
    assert!(sidecar_matches(&dataset.drives[0], &other));
    let mismatched = samples(&dataset, &config, 6);
    for (a, b) in inline.iter().zip(&mismatched) {
        for (fa, fb) in a.frames.iter().zip(&b.frames) {
            assert_eq!(fa.num_superpixels, fb.num_superpixels);
            for (ia, ib) in fa.images.iter().zip(&fb.images) {
                assert_eq!(ia.superpixels, ib.superpixels);
            }
        }
    }

    // Written for this recipe: every image's labels come from the sidecar.
    write_sidecar(&dataset.drives[0], &config, &sidecar, &|| {}).unwrap();
    let dataset = Dataset::open(std::slice::from_ref(&path), &IngestConfig::default()).unwrap();
    assert!(sidecar_matches(&dataset.drives[0], &config));
    // `inspect` names each camera's SLIC channel.
    let report = superflow_pipeline::inspect::InspectReport::new(&dataset);
    for camera in &report.drives[0].cameras {
        let expected = format!("{}/superflow_slic", camera.image_topic);
        assert_eq!(camera.slic_topic.as_deref(), Some(expected.as_str()));
    }
    assert!(report.to_text().contains("SLIC superpixels /CAM_FRONT/"));
    let from_sidecar = samples(&dataset, &config, 6);
    let (w, h) = (config.image_width as usize, config.image_height as usize);
    let (mut flipped, mut unflipped) = (0, 0);
    for (a, b) in inline.iter().zip(&from_sidecar) {
        for (fa, fb) in a.frames.iter().zip(&b.frames) {
            for (ia, ib) in fa.images.iter().zip(&fb.images) {
                let same_image = (ia.stamp, ia.flipped, &ia.rgb) == (ib.stamp, ib.flipped, &ib.rgb);
                assert!(same_image, "{} at {:?}", ib.camera, ib.stamp);
                if ia.flipped {
                    // SLIC of the unflipped image, mirrored.
                    let mut rgb = ia.rgb.clone();
                    flip_horizontal(&mut rgb, w, 3);
                    let mut labels = slic(&rgb, w, h, &config.slic).labels;
                    flip_horizontal(&mut labels, w, 1);
                    assert!(
                        local(&ib.superpixels) == labels,
                        "{} at {:?}",
                        ib.camera,
                        ib.stamp
                    );
                    flipped += 1;
                } else {
                    let same = local(&ia.superpixels) == local(&ib.superpixels);
                    assert!(same, "{} at {:?}", ib.camera, ib.stamp);
                    unflipped += 1;
                }
            }
            if fa.images.iter().all(|i| !i.flipped) {
                assert_eq!(fa.num_superpixels, fb.num_superpixels);
            }
        }
    }
    assert!(
        flipped > 0 && unflipped > 0,
        "{flipped} flipped, {unflipped} not"
    );

    // A label map the recipe cannot use is named, not guessed at.
    let camera = &dataset.drives[0].cameras[0];
    let stream = camera.slic.as_ref().unwrap();
    let mut cache = superflow_pipeline::source::ChunkCache::new(2);
    let stamp = camera.frames[0].stamp;
    let e = read_labels(&dataset.drives[0], stream, stamp, (224, 112), &mut cache).unwrap_err();
    assert!(e.to_string().contains("448x224"), "{e}");
    let missing = superflow_schemas::Stamp::from_nanos(stamp.nanos() + 1);
    let e = read_labels(&dataset.drives[0], stream, missing, (448, 224), &mut cache).unwrap_err();
    assert!(e.to_string().contains("no precomputed"), "{e}");
    std::fs::remove_dir_all(&dir).unwrap();
}
