//! Loading a DINOv2 checkpoint in safetensors format: the Hugging Face and torch-hub
//! tensor names ([`Naming`]) and the shape read off the tensors; what can be wrong with the
//! file is a [`WeightsError`].

use super::config::{VitConfig, VitPreset};
use super::error::WeightsError;
use super::network::DinoVit;
use super::weights::{BlockWeight, WeightKey, WeightSource};
use burn::tensor::{Device, bf16, f16};
use safetensors::{Dtype, SafeTensors};
use std::path::Path;

impl DinoVit {
    /// The frozen 2D network: DINOv2 weights from `image_weights`, else a random network
    /// of `preset` seeded from `seed` (meaningless features: tests and demos only).
    ///
    /// # Errors
    ///
    /// As [`load_safetensors`](Self::load_safetensors).
    pub fn frozen(
        image_weights: Option<&Path>,
        preset: VitPreset,
        seed: u64,
        device: &Device,
    ) -> Result<Self, WeightsError> {
        match image_weights {
            Some(path) => Self::load_safetensors(path, device),
            None => Ok(Self::random(
                &VitConfig::preset(preset),
                seed ^ 0x005e_ed0f_u64,
                device,
            )),
        }
    }

    /// Loads a DINOv2 checkpoint, inferring the shape from its tensors.
    ///
    /// Accepts the Hugging Face `Dinov2Model` names (`embeddings.cls_token`,
    /// `encoder.layer.{i}.attention.attention.query`, …) and the facebookresearch/dinov2
    /// torch-hub names (`cls_token`, `blocks.{i}.attn.qkv`, …), under any common prefix such as
    /// `backbone.`; tensors in f32, f16 or bf16 (computed in f32). Other tensors in the file
    /// (heads, `mask_token`) are ignored. The head count, which no tensor records, is taken to
    /// be a preset's when the width matches one and `dim / 64` otherwise.
    ///
    /// # Errors
    ///
    /// Fails, naming the file and the tensor, when a tensor is missing or has another shape or
    /// dtype, and refuses register-token (`*_reg`) and SwiGLU (ViT-g) checkpoints.
    pub fn load_safetensors(path: &Path, device: &Device) -> Result<Self, WeightsError> {
        let bytes = std::fs::read(path).map_err(|error| WeightsError::Read {
            path: path.to_path_buf(),
            error,
        })?;
        let file = SafeTensors::deserialize(&bytes).map_err(|error| WeightsError::Parse {
            path: path.to_path_buf(),
            error,
        })?;
        let mut checkpoint = Checkpoint::new(path, &file)?;
        let config = checkpoint.infer_config()?;
        Self::build(&config, device, &mut checkpoint)
    }
}

/// The two DINOv2 naming schemes.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
enum Naming {
    /// Hugging Face transformers' `Dinov2Model`.
    HuggingFace,
    /// facebookresearch/dinov2's torch-hub `DinoVisionTransformer`.
    TorchHub,
}

impl Naming {
    /// The class token's name, by which the scheme and the prefix are recognized.
    fn cls_token(self) -> &'static str {
        match self {
            Self::HuggingFace => "embeddings.cls_token",
            Self::TorchHub => "cls_token",
        }
    }

    /// The names (without prefix) holding `weight`: one, or for Hugging Face's separate
    /// query/key/value projections three, stacked along the first axis.
    fn names(self, weight: WeightKey) -> Vec<String> {
        use BlockWeight as B;
        let hf = self == Self::HuggingFace;
        let pick = |hugging_face: &str, torch_hub: &str| {
            if hf { hugging_face } else { torch_hub }.to_owned()
        };
        let name = match weight {
            WeightKey::ClsToken => self.cls_token().to_owned(),
            WeightKey::PosEmbed => pick("embeddings.position_embeddings", "pos_embed"),
            WeightKey::PatchWeight => pick(
                "embeddings.patch_embeddings.projection.weight",
                "patch_embed.proj.weight",
            ),
            WeightKey::PatchBias => pick(
                "embeddings.patch_embeddings.projection.bias",
                "patch_embed.proj.bias",
            ),
            WeightKey::NormWeight => pick("layernorm.weight", "norm.weight"),
            WeightKey::NormBias => pick("layernorm.bias", "norm.bias"),
            WeightKey::Block(index, weight) => {
                let block = self.block(index);
                let local = match weight {
                    B::QkvWeight | B::QkvBias if hf => {
                        let suffix = if weight == B::QkvWeight {
                            "weight"
                        } else {
                            "bias"
                        };
                        return ["query", "key", "value"]
                            .map(|part| format!("{block}attention.attention.{part}.{suffix}"))
                            .into();
                    }
                    B::Norm1Weight => "norm1.weight",
                    B::Norm1Bias => "norm1.bias",
                    B::QkvWeight => "attn.qkv.weight",
                    B::QkvBias => "attn.qkv.bias",
                    B::ProjWeight if hf => "attention.output.dense.weight",
                    B::ProjWeight => "attn.proj.weight",
                    B::ProjBias if hf => "attention.output.dense.bias",
                    B::ProjBias => "attn.proj.bias",
                    B::Ls1 if hf => "layer_scale1.lambda1",
                    B::Ls1 => "ls1.gamma",
                    B::Norm2Weight => "norm2.weight",
                    B::Norm2Bias => "norm2.bias",
                    B::Fc1Weight => "mlp.fc1.weight",
                    B::Fc1Bias => "mlp.fc1.bias",
                    B::Fc2Weight => "mlp.fc2.weight",
                    B::Fc2Bias => "mlp.fc2.bias",
                    B::Ls2 if hf => "layer_scale2.lambda1",
                    B::Ls2 => "ls2.gamma",
                };
                format!("{block}{local}")
            }
        };
        vec![name]
    }

    /// The prefix of block `index`'s names.
    fn block(self, index: usize) -> String {
        match self {
            Self::HuggingFace => format!("encoder.layer.{index}."),
            Self::TorchHub => format!("blocks.{index}."),
        }
    }

    /// Names whose presence marks an architecture this module does not implement, with why.
    fn unsupported(self) -> [(String, &'static str); 2] {
        let registers = "register tokens (a `*_reg` checkpoint) are not supported";
        let swiglu = "the SwiGLU MLP (ViT-g) is not supported";
        match self {
            Self::HuggingFace => [
                ("embeddings.register_tokens".to_owned(), registers),
                (format!("{}mlp.weights_in.weight", self.block(0)), swiglu),
            ],
            Self::TorchHub => [
                ("register_tokens".to_owned(), registers),
                (format!("{}mlp.w12.weight", self.block(0)), swiglu),
            ],
        }
    }
}

/// A parsed safetensors checkpoint with its naming scheme and prefix.
struct Checkpoint<'a> {
    path: &'a Path,
    file: &'a SafeTensors<'a>,
    naming: Naming,
    /// Prefix of every name, such as `backbone.` (often empty).
    prefix: String,
}

impl<'a> Checkpoint<'a> {
    /// Recognizes the naming scheme and prefix from the class token's name.
    fn new(path: &'a Path, file: &'a SafeTensors<'a>) -> Result<Self, WeightsError> {
        let mut found: Vec<(Naming, String)> = file
            .names()
            .into_iter()
            .filter_map(|name| {
                let naming = if name.ends_with(Naming::HuggingFace.cls_token()) {
                    Naming::HuggingFace
                } else {
                    Naming::TorchHub
                };
                let prefix = name.strip_suffix(naming.cls_token())?;
                (prefix.is_empty() || prefix.ends_with('.')).then(|| (naming, prefix.to_owned()))
            })
            .collect();
        let (naming, prefix) = match found.len() {
            1 => found.remove(0),
            0 => {
                return Err(WeightsError::NoClassToken {
                    path: path.to_path_buf(),
                    tensors: file.len(),
                });
            }
            _ => {
                return Err(WeightsError::SeveralClassTokens {
                    path: path.to_path_buf(),
                    names: found
                        .iter()
                        .map(|(naming, prefix)| format!("{prefix}{}", naming.cls_token()))
                        .collect(),
                });
            }
        };
        let checkpoint = Self {
            path,
            file,
            naming,
            prefix,
        };
        for (name, why) in naming.unsupported() {
            if checkpoint.shape(&name).is_some() {
                return Err(WeightsError::Unsupported {
                    path: path.to_path_buf(),
                    tensor: checkpoint.full(&name),
                    why,
                });
            }
        }
        Ok(checkpoint)
    }

    /// The name of tensor `name` in the file (with the prefix).
    fn full(&self, name: &str) -> String {
        format!("{}{name}", self.prefix)
    }

    /// The shape of tensor `name` (without prefix), if present.
    fn shape(&self, name: &str) -> Option<Vec<usize>> {
        let view = self.file.tensor(&self.full(name)).ok()?;
        Some(view.shape().to_vec())
    }

    /// The shape of the tensor holding `weight`, which must exist with `rank` axes.
    fn required_shape(&self, weight: WeightKey, rank: usize) -> Result<Vec<usize>, WeightsError> {
        let name = &self.naming.names(weight)[0];
        let shape = self.shape(name).ok_or_else(|| self.missing(name))?;
        if shape.len() != rank {
            return Err(WeightsError::Rank {
                path: self.path.to_path_buf(),
                tensor: self.full(name),
                shape,
                rank,
            });
        }
        Ok(shape)
    }

    fn missing(&self, name: &str) -> WeightsError {
        WeightsError::Missing {
            path: self.path.to_path_buf(),
            tensor: self.full(name),
        }
    }

    /// The network's shape, read off the tensors' shapes (see [`DinoVit::load_safetensors`]).
    fn infer_config(&self) -> Result<VitConfig, WeightsError> {
        let path = || self.path.to_path_buf();
        let cls = self.required_shape(WeightKey::ClsToken, 3)?;
        let dim = cls[2];
        let patch = self.required_shape(WeightKey::PatchWeight, 4)?[2];
        let positions = self.required_shape(WeightKey::PosEmbed, 3)?[1];
        let side = positions.saturating_sub(1).isqrt();
        if !(side > 0 && side * side == positions - 1) {
            return Err(WeightsError::PositionGrid {
                path: path(),
                tensor: self.full(&self.naming.names(WeightKey::PosEmbed)[0]),
                positions,
            });
        }
        let block_norm = |index| WeightKey::Block(index, BlockWeight::Norm1Weight);
        let depth = (0..)
            .take_while(|&index| {
                self.shape(&self.naming.names(block_norm(index))[0])
                    .is_some()
            })
            .count();
        if depth == 0 {
            return Err(self.missing(&self.naming.names(block_norm(0))[0]));
        }
        let mlp_hidden = self.required_shape(WeightKey::Block(0, BlockWeight::Fc1Weight), 2)?[0];
        let heads = VitConfig::heads_for_dim(dim).ok_or_else(|| WeightsError::UnknownHeads {
            path: path(),
            dim,
            tensor: self.full(self.naming.cls_token()),
        })?;
        let config = VitConfig {
            dim,
            depth,
            heads,
            mlp_hidden,
            patch,
            pos_grid: [side, side],
            eps: 1e-6,
        };
        config
            .validate()
            .map_err(|error| WeightsError::InvalidShape {
                path: path(),
                error,
            })?;
        Ok(config)
    }

    /// Tensor `name` (without prefix) as f32 values, checked to have `shape`.
    fn read(&self, name: &str, shape: &[usize]) -> Result<Vec<f32>, WeightsError> {
        let full = self.full(name);
        let view = self.file.tensor(&full).map_err(|_| self.missing(name))?;
        if view.shape() != shape {
            return Err(WeightsError::Shape {
                path: self.path.to_path_buf(),
                tensor: full,
                shape: view.shape().to_vec(),
                expected: shape.to_vec(),
            });
        }
        let bytes = view.data();
        Ok(match view.dtype() {
            Dtype::F32 => bytes
                .chunks_exact(4)
                .map(|b| f32::from_le_bytes([b[0], b[1], b[2], b[3]]))
                .collect(),
            Dtype::F16 => bytes
                .chunks_exact(2)
                .map(|b| f16::from_le_bytes([b[0], b[1]]).to_f32())
                .collect(),
            Dtype::BF16 => bytes
                .chunks_exact(2)
                .map(|b| bf16::from_le_bytes([b[0], b[1]]).to_f32())
                .collect(),
            other => {
                return Err(WeightsError::Dtype {
                    path: self.path.to_path_buf(),
                    tensor: full,
                    dtype: format!("{other:?}"),
                });
            }
        })
    }
}

impl WeightSource for Checkpoint<'_> {
    fn take(&mut self, weight: WeightKey, shape: &[usize]) -> Result<Vec<f32>, WeightsError> {
        let names = self.naming.names(weight);
        let mut part_shape = shape.to_vec();
        part_shape[0] /= names.len();
        let mut values = Vec::with_capacity(shape.iter().product());
        for name in &names {
            values.extend(self.read(name, &part_shape)?);
        }
        Ok(values)
    }
}
