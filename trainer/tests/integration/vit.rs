//! The DINOv2 backbone (`superflow_trainer::vit`) against Hugging Face transformers' outputs
//! (`tests/fixtures/vit.json`, written by `reference/make_vit_fixture.py`), plus checkpoint
//! loading under both naming schemes and in half precision, errors that name the file and
//! the tensor, seeded init and output shapes.

use std::path::{Path, PathBuf};

use burn::tensor::{Device, Tensor, TensorData, bf16, f16};
use clap::ValueEnum as _;
use safetensors::Dtype;
use serde::Deserialize;
use superflow_trainer::vit::{DinoVit, VitConfig, VitPreset, imagenet_normalize};

/// `tests/fixtures/vit.json`, the parts the tests use.
#[derive(Debug, Deserialize)]
struct Fixture {
    config: FixtureConfig,
    cases: Vec<FixtureCase>,
}

#[derive(Debug, Deserialize)]
struct FixtureConfig {
    hidden_size: usize,
    num_layers: usize,
    num_heads: usize,
    mlp_hidden: usize,
    patch_size: usize,
    pos_grid: [usize; 2],
    layer_norm_eps: f64,
}

#[derive(Debug, Deserialize)]
struct FixtureCase {
    name: String,
    height: usize,
    width: usize,
    grid: [usize; 2],
    /// u8 RGB, `[height, width, 3]` row-major.
    image: Vec<u8>,
    /// Expected class token `[D]` (transformers, float64).
    cls_token: Vec<f32>,
    /// Expected patch tokens `[rows·cols, D]`, row-major.
    patch_tokens: Vec<f32>,
}

fn fixture_path(name: &str) -> PathBuf {
    Path::new(env!("CARGO_MANIFEST_DIR"))
        .join("tests/fixtures")
        .join(name)
}

fn read_fixture() -> Fixture {
    let text = std::fs::read_to_string(fixture_path("vit.json")).expect("reading vit.json");
    serde_json::from_str(&text).expect("parsing vit.json")
}

/// A tensor to write: name, shape, values.
type Entry = (String, Vec<usize>, Vec<f32>);

/// A fresh directory for one test's files.
fn scratch_dir(test: &str) -> PathBuf {
    let dir = Path::new(env!("CARGO_TARGET_TMPDIR")).join(format!("vit-{test}"));
    let _ = std::fs::remove_dir_all(&dir);
    std::fs::create_dir_all(&dir).expect("creating the scratch directory");
    dir
}

/// Writes `entries` as a safetensors file in `dtype` (F32, F16 or BF16).
fn write_safetensors(path: &Path, entries: &[Entry], dtype: Dtype) {
    let bytes: Vec<Vec<u8>> = entries
        .iter()
        .map(|(_, _, values)| match dtype {
            Dtype::F32 => values.iter().flat_map(|v| v.to_le_bytes()).collect(),
            Dtype::F16 => values
                .iter()
                .flat_map(|&v| f16::from_f32(v).to_le_bytes())
                .collect(),
            Dtype::BF16 => values
                .iter()
                .flat_map(|&v| bf16::from_f32(v).to_le_bytes())
                .collect(),
            other => panic!("unsupported test dtype {other:?}"),
        })
        .collect();
    let views = entries.iter().zip(&bytes).map(|((name, shape, _), data)| {
        let view = safetensors::tensor::TensorView::new(dtype, shape.clone(), data)
            .expect("the data matches the shape");
        (name.clone(), view)
    });
    let file = safetensors::serialize(views, None).expect("serializing the tensors");
    std::fs::write(path, file).expect("writing the safetensors file");
}

/// Deterministic pseudo-random values in [-scale, scale).
fn values(count: usize, seed: &mut u64, scale: f32) -> Vec<f32> {
    (0..count)
        .map(|_| {
            *seed = seed
                .wrapping_mul(6_364_136_223_846_793_005)
                .wrapping_add(1_442_695_040_888_963_407);
            ((*seed >> 40) as f32 / (1u64 << 24) as f32 * 2.0 - 1.0) * scale
        })
        .collect()
}

/// A checkpoint of `config`'s shape in the torch-hub (facebookresearch/dinov2) naming, with
/// every tensor random (LayerNorm scales and LayerScales around 1).
fn torch_hub_checkpoint(config: &VitConfig, seed: u64) -> Vec<Entry> {
    let VitConfig {
        dim,
        depth,
        mlp_hidden: hidden,
        patch,
        pos_grid: [rows, cols],
        ..
    } = *config;
    let mut seed = seed;
    let mut entries = Vec::new();
    let mut add = |name: String, shape: Vec<usize>, offset: f32| {
        let mut data = values(shape.iter().product(), &mut seed, 0.1);
        data.iter_mut().for_each(|v| *v += offset);
        entries.push((name, shape, data));
    };
    add("cls_token".into(), vec![1, 1, dim], 0.0);
    add("mask_token".into(), vec![1, dim], 0.0);
    add("pos_embed".into(), vec![1, 1 + rows * cols, dim], 0.0);
    add(
        "patch_embed.proj.weight".into(),
        vec![dim, 3, patch, patch],
        0.0,
    );
    add("patch_embed.proj.bias".into(), vec![dim], 0.0);
    for i in 0..depth {
        let b = format!("blocks.{i}.");
        add(format!("{b}norm1.weight"), vec![dim], 1.0);
        add(format!("{b}norm1.bias"), vec![dim], 0.0);
        add(format!("{b}attn.qkv.weight"), vec![3 * dim, dim], 0.0);
        add(format!("{b}attn.qkv.bias"), vec![3 * dim], 0.0);
        add(format!("{b}attn.proj.weight"), vec![dim, dim], 0.0);
        add(format!("{b}attn.proj.bias"), vec![dim], 0.0);
        add(format!("{b}ls1.gamma"), vec![dim], 1.0);
        add(format!("{b}norm2.weight"), vec![dim], 1.0);
        add(format!("{b}norm2.bias"), vec![dim], 0.0);
        add(format!("{b}mlp.fc1.weight"), vec![hidden, dim], 0.0);
        add(format!("{b}mlp.fc1.bias"), vec![hidden], 0.0);
        add(format!("{b}mlp.fc2.weight"), vec![dim, hidden], 0.0);
        add(format!("{b}mlp.fc2.bias"), vec![dim], 0.0);
        add(format!("{b}ls2.gamma"), vec![dim], 1.0);
    }
    add("norm.weight".into(), vec![dim], 1.0);
    add("norm.bias".into(), vec![dim], 0.0);
    entries
}

/// The same weights under Hugging Face `Dinov2Model` names (q, k, v split), behind `prefix`.
fn hugging_face_checkpoint(torch_hub: &[Entry], prefix: &str) -> Vec<Entry> {
    let mut entries = Vec::new();
    for (name, shape, data) in torch_hub {
        let renamed = match name.as_str() {
            "cls_token" => "embeddings.cls_token".to_owned(),
            "mask_token" => "embeddings.mask_token".to_owned(),
            "pos_embed" => "embeddings.position_embeddings".to_owned(),
            "patch_embed.proj.weight" => "embeddings.patch_embeddings.projection.weight".to_owned(),
            "patch_embed.proj.bias" => "embeddings.patch_embeddings.projection.bias".to_owned(),
            "norm.weight" => "layernorm.weight".to_owned(),
            "norm.bias" => "layernorm.bias".to_owned(),
            block => {
                let rest = block.strip_prefix("blocks.").expect("a block tensor");
                let (index, local) = rest.split_once('.').expect("blocks.{i}.name");
                let layer = format!("encoder.layer.{index}.");
                if let Some(kind) = local.strip_prefix("attn.qkv.") {
                    let part_len = data.len() / 3;
                    for (part, chunk) in ["query", "key", "value"].iter().zip(data.chunks(part_len))
                    {
                        let mut part_shape = shape.clone();
                        part_shape[0] /= 3;
                        entries.push((
                            format!("{prefix}{layer}attention.attention.{part}.{kind}"),
                            part_shape,
                            chunk.to_vec(),
                        ));
                    }
                    continue;
                }
                let local = match local {
                    "attn.proj.weight" => "attention.output.dense.weight",
                    "attn.proj.bias" => "attention.output.dense.bias",
                    "ls1.gamma" => "layer_scale1.lambda1",
                    "ls2.gamma" => "layer_scale2.lambda1",
                    same => same,
                };
                format!("{layer}{local}")
            }
        };
        entries.push((format!("{prefix}{renamed}"), shape.clone(), data.clone()));
    }
    entries
}

/// Values of a tensor, flat.
fn flat<const D: usize>(tensor: Tensor<D>) -> Vec<f32> {
    tensor
        .into_data()
        .try_into_vec::<f32>()
        .expect("an f32 tensor")
}

fn max_abs_diff(a: &[f32], b: &[f32]) -> f32 {
    assert_eq!(a.len(), b.len());
    a.iter()
        .zip(b)
        .map(|(x, y)| (x - y).abs())
        .fold(0.0, f32::max)
}

/// Deterministic ImageNet-normalized images `[count, 3, height, width]`.
fn test_images(count: usize, height: usize, width: usize, device: &Device) -> Tensor<4> {
    let mut seed = 7;
    let rgb: Vec<f32> = values(count * height * width * 3, &mut seed, 127.5)
        .into_iter()
        .map(|v| v + 127.5)
        .collect();
    imagenet_normalize(Tensor::from_data(
        TensorData::new(rgb, [count, height, width, 3]),
        device,
    ))
}

fn load_error(path: &Path) -> String {
    let error =
        DinoVit::load_safetensors(path, &Device::flex()).expect_err("the checkpoint is broken");
    format!("{error:#}")
}

#[test]
fn fixture_checkpoints_reproduce_transformers() {
    let device = Device::flex();
    let fixture = read_fixture();
    let c = &fixture.config;
    let expected_config = VitConfig {
        dim: c.hidden_size,
        depth: c.num_layers,
        heads: c.num_heads,
        mlp_hidden: c.mlp_hidden,
        patch: c.patch_size,
        pos_grid: c.pos_grid,
        eps: c.layer_norm_eps,
    };
    assert_eq!(
        expected_config,
        VitConfig::preset(VitPreset::Tiny),
        "the tiny preset is the fixture's"
    );

    for file in ["tiny_dinov2_hf.safetensors", "tiny_dinov2.safetensors"] {
        let vit =
            DinoVit::load_safetensors(&fixture_path(file), &device).expect("loading the fixture");
        assert_eq!(vit.config(), &expected_config, "{file}: inferred config");
        for case in &fixture.cases {
            let [rows, cols] = case.grid;
            let dim = expected_config.dim;
            let rgb: Vec<f32> = case.image.iter().map(|&v| f32::from(v)).collect();
            let images = imagenet_normalize(Tensor::from_data(
                TensorData::new(rgb, [1, case.height, case.width, 3]),
                &device,
            ));

            let tokens = flat(vit.forward_tokens(images.clone()));
            let (cls, patches) = tokens.split_at(dim);
            let features = vit.forward(images);
            assert_eq!(features.dims(), [1, dim, rows, cols]);
            // The feature map is the patch tokens, channels first.
            let map = flat(features);
            let as_tokens: Vec<f32> = (0..rows * cols)
                .flat_map(|patch| (0..dim).map(move |d| (patch, d)))
                .map(|(patch, d)| map[d * rows * cols + patch])
                .collect();
            assert_eq!(
                as_tokens, patches,
                "{file} {}: forward = forward_tokens",
                case.name
            );

            let scale = case.patch_tokens.iter().fold(0.0f32, |m, v| m.max(v.abs()));
            let patch_diff = max_abs_diff(patches, &case.patch_tokens);
            let cls_diff = max_abs_diff(cls, &case.cls_token);
            println!(
                "{file} {}: max |diff| patch tokens {patch_diff:.2e}, cls token {cls_diff:.2e} \
                 (token scale {scale:.2})",
                case.name
            );
            let tolerance = 1e-4 * scale;
            assert!(
                patch_diff <= tolerance,
                "{file} {}: patch tokens differ by {patch_diff}",
                case.name
            );
            assert!(
                cls_diff <= tolerance,
                "{file} {}: cls token differs by {cls_diff}",
                case.name
            );
        }
    }
}

#[test]
fn both_namings_prefixes_and_half_dtypes_load_the_same_network() {
    let device = Device::flex();
    let config = VitConfig::preset(VitPreset::Tiny);
    let dir = scratch_dir("namings");
    let hub = torch_hub_checkpoint(&config, 1);
    let hub_path = dir.join("hub.safetensors");
    write_safetensors(&hub_path, &hub, Dtype::F32);
    let hf_path = dir.join("hf.safetensors");
    write_safetensors(
        &hf_path,
        &hugging_face_checkpoint(&hub, "backbone."),
        Dtype::F32,
    );

    let from_hub = DinoVit::load_safetensors(&hub_path, &device).expect("loading hub names");
    let from_hf = DinoVit::load_safetensors(&hf_path, &device).expect("loading HF names");
    assert_eq!(from_hub.config(), &config, "inferred config");
    assert_eq!(from_hf.config(), &config, "inferred config");

    // Native grid (4×4 patches) and a resized one (3×5).
    for [height, width] in [[56, 56], [42, 70]] {
        let images = test_images(2, height, width, &device);
        let hub_out = flat(from_hub.forward(images.clone()));
        let hf_out = flat(from_hf.forward(images.clone()));
        assert_eq!(
            hub_out, hf_out,
            "{height}×{width}: the namings load the same weights"
        );

        for dtype in [Dtype::F16, Dtype::BF16] {
            let path = dir.join(format!("hub-{dtype:?}.safetensors"));
            write_safetensors(&path, &hub, dtype);
            let half = DinoVit::load_safetensors(&path, &device).expect("loading half precision");
            let diff = max_abs_diff(&flat(half.forward(images.clone())), &hub_out);
            // Tokens are LayerNorm outputs (order 1); bf16 keeps 8 mantissa bits.
            assert!(diff < 0.1, "{dtype:?} weights differ by {diff} from f32");
        }
    }
}

#[test]
fn a_missing_tensor_is_named_with_the_file() {
    let config = VitConfig::preset(VitPreset::Tiny);
    let dir = scratch_dir("missing");
    let mut hub = torch_hub_checkpoint(&config, 2);
    hub.retain(|(name, _, _)| name != "blocks.1.mlp.fc2.bias");
    let path = dir.join("missing.safetensors");
    write_safetensors(&path, &hub, Dtype::F32);

    let message = load_error(&path);
    assert!(
        message.contains("missing tensor `blocks.1.mlp.fc2.bias`"),
        "{message}"
    );
    assert!(message.contains(&path.display().to_string()), "{message}");

    // Hugging Face names: a missing part of the split query/key/value, under a prefix.
    let mut hf = hugging_face_checkpoint(&torch_hub_checkpoint(&config, 2), "model.");
    let gone = "model.encoder.layer.0.attention.attention.key.weight";
    hf.retain(|(name, _, _)| name != gone);
    let path = dir.join("missing-hf.safetensors");
    write_safetensors(&path, &hf, Dtype::F32);
    let message = load_error(&path);
    assert!(
        message.contains(&format!("missing tensor `{gone}`")),
        "{message}"
    );
    assert!(message.contains(&path.display().to_string()), "{message}");
}

#[test]
fn a_wrong_shape_or_dtype_is_named_with_the_file() {
    let config = VitConfig::preset(VitPreset::Tiny);
    let dir = scratch_dir("shape");
    let mut hub = torch_hub_checkpoint(&config, 3);
    let entry = hub
        .iter_mut()
        .find(|(name, _, _)| name == "blocks.0.attn.proj.weight")
        .expect("the tensor exists");
    entry.1 = vec![config.dim, config.dim / 2];
    entry.2.truncate(config.dim * config.dim / 2);
    let path = dir.join("shape.safetensors");
    write_safetensors(&path, &hub, Dtype::F32);

    let message = load_error(&path);
    assert!(
        message
            .contains("tensor `blocks.0.attn.proj.weight` has shape [32, 16], expected [32, 32]"),
        "{message}"
    );
    assert!(message.contains(&path.display().to_string()), "{message}");

    // A dtype the loader does not convert: write one tensor as F64 by hand.
    let hub = torch_hub_checkpoint(&config, 3);
    let f64_bytes: Vec<Vec<u8>> = hub
        .iter()
        .map(|(name, _, values)| {
            if name == "norm.bias" {
                values
                    .iter()
                    .flat_map(|&v| f64::from(v).to_le_bytes())
                    .collect()
            } else {
                values.iter().flat_map(|v| v.to_le_bytes()).collect()
            }
        })
        .collect();
    let views = hub.iter().zip(&f64_bytes).map(|((name, shape, _), data)| {
        let dtype = if name == "norm.bias" {
            Dtype::F64
        } else {
            Dtype::F32
        };
        let view = safetensors::tensor::TensorView::new(dtype, shape.clone(), data)
            .expect("the data matches the shape");
        (name.clone(), view)
    });
    let path = dir.join("dtype.safetensors");
    std::fs::write(
        &path,
        safetensors::serialize(views, None).expect("serializing"),
    )
    .expect("writing");
    let message = load_error(&path);
    assert!(
        message.contains("tensor `norm.bias` has dtype F64"),
        "{message}"
    );
    assert!(message.contains(&path.display().to_string()), "{message}");
}

#[test]
fn register_and_swiglu_checkpoints_are_refused() {
    let config = VitConfig::preset(VitPreset::Tiny);
    let dir = scratch_dir("refused");

    let mut hub = torch_hub_checkpoint(&config, 4);
    hub.push((
        "register_tokens".into(),
        vec![1, 4, config.dim],
        vec![0.0; 4 * config.dim],
    ));
    let path = dir.join("reg.safetensors");
    write_safetensors(&path, &hub, Dtype::F32);
    let message = load_error(&path);
    assert!(
        message.contains("`register_tokens`") && message.contains("register tokens"),
        "{message}"
    );

    let mut hf = hugging_face_checkpoint(&torch_hub_checkpoint(&config, 4), "");
    hf.push((
        "encoder.layer.0.mlp.weights_in.weight".into(),
        vec![2 * config.mlp_hidden, config.dim],
        vec![0.0; 2 * config.mlp_hidden * config.dim],
    ));
    let path = dir.join("swiglu.safetensors");
    write_safetensors(&path, &hf, Dtype::F32);
    let message = load_error(&path);
    assert!(
        message.contains("SwiGLU") && message.contains(&path.display().to_string()),
        "{message}"
    );
}

#[test]
fn random_init_is_deterministic_per_seed() {
    let device = Device::flex();
    let config = VitConfig::preset(VitPreset::Tiny);
    let images = test_images(1, 28, 42, &device);
    let run = |seed| flat(DinoVit::random(&config, seed, &device).forward(images.clone()));
    let first = run(5);
    assert_eq!(first, run(5), "same seed, same network");
    assert_ne!(first, run(6), "another seed, another network");
}

#[test]
fn tiny_output_is_a_patch_feature_map() {
    let device = Device::flex();
    let vit = DinoVit::random(&VitConfig::preset(VitPreset::Tiny), 0, &device);
    let features = vit.forward(test_images(2, 224, 448, &device));
    assert_eq!(features.dims(), [2, 32, 16, 32]);
    assert!(flat(features).iter().all(|v| v.is_finite()));
}

#[test]
fn presets_parse_and_serialize_by_lowercase_name() {
    for preset in VitPreset::ALL {
        let name = preset.to_string();
        assert_eq!(VitPreset::from_str(&name, false), Ok(preset));
        assert_eq!(
            serde_json::to_string(&preset).expect("serializing"),
            format!("\"{name}\"")
        );
        assert_eq!(
            VitConfig::preset(preset).head_dim() * VitConfig::preset(preset).heads,
            VitConfig::preset(preset).dim
        );
    }
    assert!(VitPreset::from_str("huge", false).is_err());
    assert_eq!(VitConfig::preset(VitPreset::Small).dim, 384);
    assert_eq!(VitConfig::preset(VitPreset::Large).depth, 24);
}

/// Forward time of the tiny and Small presets on one 224×448 image on `Device::flex()`.
/// Run with `cargo test --release -p superflow-trainer --test integration vit:: -- --ignored --nocapture`.
#[test]
#[ignore = "a timing report, not a check; run in release"]
fn forward_timing() {
    let device = Device::flex();
    for preset in [VitPreset::Tiny, VitPreset::Small] {
        let vit = DinoVit::random(&VitConfig::preset(preset), 0, &device);
        let images = test_images(1, 224, 448, &device);
        let _ = flat(vit.forward(images.clone())); // warm-up
        let runs = 3;
        let start = std::time::Instant::now();
        for _ in 0..runs {
            let _ = flat(vit.forward(images.clone()));
        }
        let per_run = start.elapsed().as_secs_f64() / f64::from(runs);
        println!("{preset}: {:.1} ms per 224×448 image", per_run * 1e3);
    }
}
