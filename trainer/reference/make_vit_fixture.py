#!/usr/bin/env python3
"""A tiny DINOv2 ViT with random weights and its outputs, for the Rust trainer's tests.

Writes, under ``trainer/tests/fixtures/``:

* ``tiny_dinov2_hf.safetensors``: the weights under Hugging Face names, the very file
  ``Dinov2Model.save_pretrained`` writes (``model.safetensors``);
* ``tiny_dinov2.safetensors``: the same weights under the original
  facebookresearch/dinov2 torch-hub names (``blocks.{i}.attn.qkv`` etc.);
* ``vit.json``: the configuration, two test images and the expected outputs.

Run (needs PyTorch, numpy, safetensors and ``transformers``; CI does not, it only reads
the committed files)::

    /tmp/torchenv/bin/pip install transformers
    /tmp/torchenv/bin/python trainer/reference/make_vit_fixture.py

Deterministic (fixed seed); rerunning rewrites the same bytes.

Model: ``transformers.Dinov2Model`` with hidden size 32, 2 layers, 2 heads (head dim 16),
MLP ratio 4 (hidden 128, GELU in its exact erf form), patch 14, image size 56 (a 4 x 4
grid of position embeddings plus the cls position), LayerNorm eps 1e-6, layer scale on,
q/k/v biases on, no register tokens, no SwiGLU. Every parameter is re-drawn from a seeded
normal: std 0.3, and 1 + 0.3 N for the LayerNorm weights.

Images (u8 RGB, HWC, stored flat in the JSON)::

    pixel[y, x, c] = (3*y*y + 7*x + 85*c + 5*((x*y) % 31) + 11*((x + 2*y) // 9)) % 256

They are normalised in float32 as ``(pixel / 255 - mean[c]) / std[c]`` with the ImageNet
mean (0.485, 0.456, 0.406) and std (0.229, 0.224, 0.225), then fed as NCHW.

Cases: (a) 56 x 56, the native 4 x 4 grid: no interpolation (transformers skips it when
the patch count equals the position count and the image is square). (b) 42 x 84, a
3 x 6 grid: the 4 x 4 patch position embeddings are resized to 3 x 6.

Position-embedding interpolation in the installed transformers (5.x,
``Dinov2Embeddings.interpolate_pos_encoding``): the cls position (row 0) is kept; the
patch positions are reshaped to [1, D, 4, 4] (row-major grid: row index = y) and resized
with ``torch.nn.functional.interpolate(..., size=(H // 14, W // 14), mode="bicubic",
align_corners=False)`` in float32: ``size=`` (not ``scale_factor=``), no antialias, no 0.1
offset. In torch that means, per axis with in = 4 and out = the new grid size:
``src = (dst + 0.5) * in / out - 0.5`` (NOT clamped at 0 for bicubic), ``i0 = floor(src)``,
``t = src - i0``; the 4 taps ``i0 - 1 .. i0 + 2`` are clamped to ``[0, in - 1]`` (edge
replication) and weighted with the cubic convolution kernel of Keys with A = -0.75:
``w(d) = (A + 2)|d|^3 - (A + 3)|d|^2 + 1`` for ``|d| <= 1``,
``w(d) = A|d|^3 - 5A|d|^2 + 8A|d| - 4A`` for ``1 < |d| < 2`` (distances ``1 + t, t, 1 - t,
2 - t``). The result is flattened back row-major to [gh * gw, D] and appended after the
cls position. (The original facebookresearch code instead passes
``scale_factor = ((gh + 0.1) / 4, (gw + 0.1) / 4)``, which maps coordinates with
``1 / scale_factor`` and so differs slightly; this fixture follows transformers.) The
script re-implements this interpolation by hand and asserts it matches torch.

As an independent check, a plain PyTorch forward written from the hub-named tensors
(below, ``plain_forward``) must match transformers to 1e-5 on both cases.
Expected outputs in ``vit.json`` come from transformers run in float64 (``model.double()``,
images normalised in float64); ``float32_max_abs_diff`` records how far the float32 run
is from them.
"""

from __future__ import annotations

import json
import math
import os
import tempfile

import numpy as np
import torch
import torch.nn.functional as Fn
from safetensors.torch import load_file, save

SEED = 1234
HERE = os.path.dirname(os.path.abspath(__file__))
FIXTURES = os.path.join(HERE, "..", "tests", "fixtures")
MEAN = (0.485, 0.456, 0.406)
STD = (0.229, 0.224, 0.225)
IMAGE_FORMULA = ("pixel[y, x, c] = (3*y*y + 7*x + 85*c + 5*((x*y) % 31) + "
                 "11*((x + 2*y) // 9)) % 256")
INTERPOLATION = (
    "transformers Dinov2Embeddings.interpolate_pos_encoding: skipped when the patch count "
    "equals the position count and height == width; otherwise the cls position (row 0) is "
    "kept and the patch positions, reshaped to [1, D, 4, 4] (grid row-major, y first), are "
    "resized in float32 with torch.nn.functional.interpolate(size=(H // 14, W // 14), "
    "mode='bicubic', align_corners=False): size= (not scale_factor=), antialias=False, no "
    "0.1 offset. Per axis: src = (dst + 0.5) * in / out - 0.5 (not clamped at 0), "
    "i0 = floor(src), t = src - i0, taps i0-1..i0+2 clamped to [0, in-1], Keys cubic "
    "weights with A = -0.75; then flattened row-major to [gh*gw, D] after the cls position."
)


def image(h: int, w: int) -> np.ndarray:
    y, x, c = np.meshgrid(np.arange(h), np.arange(w), np.arange(3), indexing="ij")
    v = (3 * y * y + 7 * x + 85 * c + 5 * ((x * y) % 31) + 11 * ((x + 2 * y) // 9)) % 256
    return v.astype(np.uint8)


def normalise(img: np.ndarray, dtype) -> torch.Tensor:
    """u8 HWC -> [1, 3, H, W]: (pixel / 255 - mean) / std, computed in `dtype`."""
    x = torch.from_numpy(img.astype(np.float64)).to(dtype) / 255.0
    x = (x - torch.tensor(MEAN, dtype=dtype)) / torch.tensor(STD, dtype=dtype)
    return x.permute(2, 0, 1).unsqueeze(0).contiguous()


# ---------------------------------------------------------------------------------------
# Independent forward from the hub-named tensors
# ---------------------------------------------------------------------------------------

def cubic_weights(t: float, a: float = -0.75) -> list[float]:
    def w(d):
        d = abs(d)
        if d <= 1:
            return (a + 2) * d ** 3 - (a + 3) * d ** 2 + 1
        if d < 2:
            return a * d ** 3 - 5 * a * d ** 2 + 8 * a * d - 4 * a
        return 0.0
    return [w(1 + t), w(t), w(1 - t), w(2 - t)]


def resize_matrix(n_in: int, n_out: int) -> torch.Tensor:
    """[n_out, n_in] matrix of bicubic resizing along one axis (as documented above)."""
    m = torch.zeros(n_out, n_in, dtype=torch.float64)
    for o in range(n_out):
        src = (o + 0.5) * n_in / n_out - 0.5
        i0 = math.floor(src)
        for tap, wt in zip(range(i0 - 1, i0 + 3), cubic_weights(src - i0), strict=False):
            m[o, min(max(tap, 0), n_in - 1)] += wt
    return m


def resize_pos(grid: torch.Tensor, gh: int, gw: int) -> torch.Tensor:
    """grid [n, n, D] -> [gh, gw, D]."""
    mh = resize_matrix(grid.shape[0], gh).to(grid.dtype)
    mw = resize_matrix(grid.shape[1], gw).to(grid.dtype)
    return torch.einsum("yi,xj,ijd->yxd", mh, mw, grid)


def plain_forward(t: dict, x: torch.Tensor, heads: int, eps: float = 1e-6):
    """x [1, 3, H, W] -> (tokens after the final norm [1, 1 + gh*gw, D], pos used)."""
    p = t["patch_embed.proj.weight"].shape[-1]
    gh, gw = x.shape[2] // p, x.shape[3] // p
    tok = Fn.conv2d(x, t["patch_embed.proj.weight"], t["patch_embed.proj.bias"], stride=p)
    tok = tok.flatten(2).transpose(1, 2)  # [1, gh*gw, D], patches row-major
    d = tok.shape[-1]
    pos = t["pos_embed"]
    n = round(math.sqrt(pos.shape[1] - 1))
    if gh * gw != n * n or x.shape[2] != x.shape[3]:
        patch = resize_pos(pos[0, 1:].reshape(n, n, d), gh, gw).reshape(1, gh * gw, d)
        pos = torch.cat([pos[:, :1], patch], dim=1)
    h = torch.cat([t["cls_token"], tok], dim=1) + pos
    hd = d // heads
    i = 0
    while f"blocks.{i}.norm1.weight" in t:
        b = f"blocks.{i}."
        y = Fn.layer_norm(h, (d,), t[b + "norm1.weight"], t[b + "norm1.bias"], eps)
        qkv = y @ t[b + "attn.qkv.weight"].T + t[b + "attn.qkv.bias"]
        q, k, v = qkv.reshape(1, -1, 3, heads, hd).permute(2, 0, 3, 1, 4)  # [1, heads, T, hd]
        att = torch.softmax((q @ k.transpose(-1, -2)) * hd ** -0.5, dim=-1)
        o = (att @ v).transpose(1, 2).reshape(1, -1, d)
        o = o @ t[b + "attn.proj.weight"].T + t[b + "attn.proj.bias"]
        h = h + t[b + "ls1.gamma"] * o
        y = Fn.layer_norm(h, (d,), t[b + "norm2.weight"], t[b + "norm2.bias"], eps)
        y = y @ t[b + "mlp.fc1.weight"].T + t[b + "mlp.fc1.bias"]
        y = 0.5 * y * (1 + torch.erf(y / math.sqrt(2)))
        y = y @ t[b + "mlp.fc2.weight"].T + t[b + "mlp.fc2.bias"]
        h = h + t[b + "ls2.gamma"] * y
        i += 1
    return Fn.layer_norm(h, (d,), t["norm.weight"], t["norm.bias"], eps), pos


# ---------------------------------------------------------------------------------------

def hub_from_hf(sd: dict, layers: int) -> dict:
    """The Hugging Face state dict under facebookresearch/dinov2 names."""
    out = {
        "cls_token": sd["embeddings.cls_token"],
        "mask_token": sd["embeddings.mask_token"],
        "pos_embed": sd["embeddings.position_embeddings"],
        "patch_embed.proj.weight": sd["embeddings.patch_embeddings.projection.weight"],
        "patch_embed.proj.bias": sd["embeddings.patch_embeddings.projection.bias"],
        "norm.weight": sd["layernorm.weight"],
        "norm.bias": sd["layernorm.bias"],
    }
    for i in range(layers):
        hf, hub = f"encoder.layer.{i}.", f"blocks.{i}."
        att = hf + "attention.attention."
        for kind in ("weight", "bias"):
            out[hub + f"attn.qkv.{kind}"] = torch.cat(
                [sd[att + f"query.{kind}"], sd[att + f"key.{kind}"], sd[att + f"value.{kind}"]], 0)
            out[hub + f"attn.proj.{kind}"] = sd[hf + f"attention.output.dense.{kind}"]
            for name in ("norm1", "norm2", "mlp.fc1", "mlp.fc2"):
                out[hub + f"{name}.{kind}"] = sd[hf + f"{name}.{kind}"]
        out[hub + "ls1.gamma"] = sd[hf + "layer_scale1.lambda1"]
        out[hub + "ls2.gamma"] = sd[hf + "layer_scale2.lambda1"]
    return {k: v.contiguous().clone() for k, v in out.items()}


def floats(t: torch.Tensor) -> list[float]:
    return [float(v) for v in t.detach().reshape(-1).tolist()]


def main() -> None:
    from transformers import Dinov2Config, Dinov2Model

    torch.manual_seed(SEED)
    config = Dinov2Config(
        hidden_size=32, num_hidden_layers=2, num_attention_heads=2, mlp_ratio=4,
        patch_size=14, image_size=56, num_channels=3, layer_norm_eps=1e-6,
        hidden_act="gelu", layerscale_value=1.0, use_swiglu_ffn=False, qkv_bias=True,
        drop_path_rate=0.0, hidden_dropout_prob=0.0, attention_probs_dropout_prob=0.0,
        attn_implementation="eager",
    )
    model = Dinov2Model(config).eval()
    assert not hasattr(model.embeddings, "register_tokens")

    gen = torch.Generator().manual_seed(SEED)
    with torch.no_grad():
        for name, p in sorted(model.named_parameters()):
            noise = torch.randn(p.shape, generator=gen, dtype=torch.float32) * 0.3
            is_ln_weight = name.endswith("weight") and ("norm" in name.split(".")[-2])
            p.copy_(1.0 + noise if is_ln_weight else noise)

    # The Hugging Face file, exactly as save_pretrained writes it.
    with tempfile.TemporaryDirectory() as tmp:
        model.save_pretrained(tmp, safe_serialization=True)
        with open(os.path.join(tmp, "model.safetensors"), "rb") as f:
            hf_bytes = f.read()
        hf = load_file(os.path.join(tmp, "model.safetensors"))
    print("tiny_dinov2_hf.safetensors (save_pretrained names):")
    for k in sorted(hf):
        print(f"  {k} {list(hf[k].shape)} {hf[k].dtype}")
    expected_hf = {"embeddings.cls_token", "embeddings.mask_token",
                   "embeddings.position_embeddings",
                   "embeddings.patch_embeddings.projection.weight",
                   "embeddings.patch_embeddings.projection.bias",
                   "layernorm.weight", "layernorm.bias"}
    for i in range(2):
        for n in ("norm1", "norm2", "attention.attention.query", "attention.attention.key",
                  "attention.attention.value", "attention.output.dense", "mlp.fc1", "mlp.fc2"):
            expected_hf |= {f"encoder.layer.{i}.{n}.weight", f"encoder.layer.{i}.{n}.bias"}
        expected_hf |= {f"encoder.layer.{i}.layer_scale1.lambda1",
                        f"encoder.layer.{i}.layer_scale2.lambda1"}
    assert set(hf) == expected_hf, (sorted(set(hf) ^ expected_hf))
    # The file holds the model's weights.
    own = {n: p for n, p in model.named_parameters()}
    assert torch.equal(hf["embeddings.cls_token"], own["embeddings.cls_token"])
    assert torch.equal(hf["encoder.layer.1.attention.attention.value.weight"],
                       own["encoder.layer.1.attention.v_proj.weight"])

    hub = hub_from_hf(hf, config.num_hidden_layers)
    print("tiny_dinov2.safetensors (facebookresearch/dinov2 hub names):")
    for k in sorted(hub):
        print(f"  {k} {list(hub[k].shape)}")
    d = config.hidden_size
    assert list(hub["cls_token"].shape) == [1, 1, d]
    assert list(hub["pos_embed"].shape) == [1, 17, d]
    assert list(hub["mask_token"].shape) == [1, d]
    assert list(hub["blocks.0.attn.qkv.weight"].shape) == [3 * d, d]

    os.makedirs(FIXTURES, exist_ok=True)
    with open(os.path.join(FIXTURES, "tiny_dinov2_hf.safetensors"), "wb") as f:
        f.write(hf_bytes)
    with open(os.path.join(FIXTURES, "tiny_dinov2.safetensors"), "wb") as f:
        f.write(save(dict(sorted(hub.items())), metadata={"format": "pt"}))

    # The interpolation as documented equals torch's.
    grid = hub["pos_embed"][0, 1:].reshape(4, 4, d)
    for gh, gw in ((3, 6), (16, 32), (5, 5), (2, 7)):
        torch_way = Fn.interpolate(grid.permute(2, 0, 1)[None], size=(gh, gw), mode="bicubic",
                                   align_corners=False)[0].permute(1, 2, 0)
        mine = resize_pos(grid.double(), gh, gw)
        err = (torch_way.double() - mine).abs().max().item()
        assert err < 1e-5, (gh, gw, err)

    model64 = Dinov2Model(config).eval()
    model64.load_state_dict(model.state_dict())
    model64 = model64.double()
    hub64 = {k: v.double() for k, v in hub.items()}
    cases = []
    worst32 = 0.0
    for name, (hgt, wid) in (("native_56x56", (56, 56)), ("interpolated_42x84", (42, 84))):
        img = image(hgt, wid)
        gh, gw = hgt // 14, wid // 14
        with torch.no_grad():
            out64 = model64(pixel_values=normalise(img, torch.float64)).last_hidden_state
            out32 = model(pixel_values=normalise(img, torch.float32)).last_hidden_state
            plain, pos = plain_forward(hub64, normalise(img, torch.float64), heads=2)
            pos_hf = model64.embeddings.interpolate_pos_encoding(
                torch.zeros(1, 1 + gh * gw, d, dtype=torch.float64), hgt, wid)
        err = (plain - out64).abs().max().item()
        assert err < 1e-5, (name, err)
        assert (pos - pos_hf).abs().max().item() < 1e-5
        worst32 = max(worst32, (out32.double() - out64).abs().max().item())
        assert out64.shape == (1, 1 + gh * gw, d)
        print(f"case {name}: grid {gh}x{gw}, plain vs transformers max |diff| {err:.2e}, "
              f"float32 vs float64 {(out32.double() - out64).abs().max().item():.2e}, "
              f"output std {out64[0, 1:].std().item():.3f}")
        cases.append({
            "name": name, "height": hgt, "width": wid, "grid": [gh, gw],
            "interpolated": bool(gh * gw != 16 or hgt != wid),
            "image": [int(v) for v in img.reshape(-1)],
            "pos_embed": floats(pos_hf[0]),
            "cls_token": floats(out64[0, 0]),
            "patch_tokens": floats(out64[0, 1:]),
        })

    doc = {
        "config": {
            "hidden_size": d, "num_layers": config.num_hidden_layers,
            "num_heads": config.num_attention_heads, "head_dim": d // config.num_attention_heads,
            "mlp_hidden": int(d * config.mlp_ratio), "patch_size": 14, "image_size": 56,
            "pos_grid": [4, 4], "num_positions": 17, "layer_norm_eps": 1e-6,
            "gelu": "exact: 0.5 * x * (1 + erf(x / sqrt(2)))",
            "attention_scale": "head_dim ** -0.5",
            "layer_scale": True, "qkv_bias": True, "register_tokens": 0, "swiglu": False,
            "image_mean": list(MEAN), "image_std": list(STD),
            "normalisation": "float32 (pixel / 255 - mean[c]) / std[c], NCHW",
            "seed": SEED,
            "init": "every parameter N(0, 0.3^2); LayerNorm weights 1 + N(0, 0.3^2)",
        },
        "pos_embed_interpolation": INTERPOLATION,
        "image_formula": IMAGE_FORMULA,
        "image_layout": "u8 RGB, HWC, row-major, flat",
        "output_layout": "patch_tokens: [gh*gw, D] row-major, patches row-major (y major); "
                         "cls_token: [D]; pos_embed: the position embeddings added, "
                         "[1 + gh*gw, D] (cls position first); all after/for the final "
                         "LayerNorm of transformers' last_hidden_state, computed in float64",
        "float32_max_abs_diff": worst32,
        "cases": cases,
    }
    with open(os.path.join(FIXTURES, "vit.json"), "w") as f:
        f.write(json.dumps(doc, separators=(",", ":")) + "\n")
    print(f"wrote {os.path.normpath(FIXTURES)}/tiny_dinov2_hf.safetensors, "
          f"tiny_dinov2.safetensors, vit.json (float32 vs float64 {worst32:.2e})")


if __name__ == "__main__":
    main()
