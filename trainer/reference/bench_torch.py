#!/usr/bin/env python3
"""PyTorch CPU timing of one SuperFlow training step, to compare with the Rust bench.

Usage (needs PyTorch, numpy and safetensors; CI does not run it)::

    /tmp/torchenv/bin/python trainer/reference/bench_torch.py --batch FILE \\
        --preset tiny|minkunet18|minkunet34 [--pixel-stride S] --steps N --warmup W \\
        --threads T [--json]

    # checks the losses and the ViT against the fixtures of the other two scripts
    /tmp/torchenv/bin/python trainer/reference/bench_torch.py --self-test

    # a batch of several rigs: the frozen ViT on its images (batch format 2, cameras per
    # sample) against the slots a layout of `cameras` slots per sample would hold
    /tmp/torchenv/bin/python trainer/reference/bench_torch.py --batch FILE --empty-slots \
        [--vit-preset minkunet18] --threads T

    # no batch file at hand: a synthetic batch with the same sections and shapes
    /tmp/torchenv/bin/python trainer/reference/bench_torch.py --synthetic \\
        [--synthetic-points 8000] [--write-synthetic FILE] --preset tiny --steps 3 --warmup 1

``FILE`` is a superflow batch saved by the Rust side: the 11 400-byte ``BatchHeader``
then the payload (``schemas/BATCH_FORMAT.md``); it is read and validated with
the reader of the ``superflow`` package (``tests/python/read_batch.py``). Prints the median milliseconds per step and
``steps/s = 1000 / median ms``; with ``--json`` the human-readable lines go to stderr
and stdout gets one line ``{"preset", "ms_per_step_median", "steps_per_s", "threads",
"pixel_stride", "sampled_pixels", "params", "prep_ms", "phases_ms": {"vit", "forward",
"backward", "update"}}`` (phases: medians over the timed steps). ``trainer/benches/step.rs``
runs it next to the burn step on the same batch file.

One step = forward (frozen ViT under ``no_grad`` on every image of the batch, 2D head,
3D UNet, 3D head, losses) + backward + AdamW step. The batch arrays are turned into
torch index tensors once, before the timed steps ("prep", reported apart: the Rust
trainer redoes this "inputs" phase every step, as every batch differs), as they do
not change between steps; the ImageNet normalisation of the images is inside the step.
Seeded (``--seed``), so the weights are the same from run to run (the initial weights
have the Rust trainer's distributions, not its values).

Model (the Rust trainer's):

* 3D: MinkowskiEngine's MinkUNet run on the batch's kernel maps (no sparse library).
  A 3x3x3 convolution at level l: pairs ``l{l}_nbr`` = (input row, output row), grouped
  by offset k (``starts[k]:starts[k+1]``); as ``trainer/src/unet.rs`` does it: gather
  ``x[in_rows]`` once, multiply each offset's part (``split``) by ``W[k]``, concatenate,
  one ``out.index_add_(0, out_rows, ...)``. The kernel-2 stride-2 down
  convolution uses ``l{l}_down`` (row at l, row at l+1) grouped by child position
  (``l{l}_down_starts``), the transposed up convolution the same pairs reversed. No conv
  biases. BatchNorm1d over rows (training mode, eps 1e-5, momentum 0.1), ReLU.
  Stem conv3 4 -> stem (32; 16 for tiny) + BN + ReLU; 4 encoder stages (down conv
  ch -> ch + BN + ReLU, then BasicBlocks to planes[i]); 4 decoder stages (up conv to
  planes[4+i] + BN + ReLU, concatenation with the encoder output of that level, the
  stem's for the last, then BasicBlocks). BasicBlock = conv3-BN-ReLU-conv3-BN plus the
  residual (1x1 linear without bias + BN when the channels change), ReLU after the sum.
  Presets: minkunet34 blocks [2,3,4,6,2,2,2,2], minkunet18 [2]*8, both planes
  [32,64,128,256,256,128,96,96]; tiny blocks [1]*8, planes [16,32,32,32,32,32,16,16],
  stem 16. Input = ``voxel_features`` (x, y, z, intensity). Head: Linear(planes[7], 64)
  with bias, L2-normalised; point features = voxel features at ``point_to_voxel``.
* 2D: frozen DINOv2 (tiny: the fixture ``tests/fixtures/tiny_dinov2.safetensors``;
  minkunet18/34: ViT-S/14, dim 384, depth 12, 6 heads, 37 x 37 position grid, random
  weights), position embeddings resized as transformers does (bicubic, ``size=``,
  align_corners False), attention via ``scaled_dot_product_attention``. Head: 1x1 conv
  dim -> 64 with bias, bilinear upsampling to the image size (x14, align_corners True),
  L2 normalisation over channels -- evaluated, as ``trainer/src/model.rs`` does, only at
  the pixels the superpixel pooling samples: the 1x1 conv at patch resolution, then each
  sampled pixel = the 4 grid cells around it with their bilinear weights, then the L2
  normalisation (the same values as the full-resolution map at those pixels).
* Pixel sampling (``--pixel-stride S``, as ``[loss] pixel_stride`` and
  ``LossPlan::new``): in every image, rows ``S//2, S//2 + S, ...`` and the same columns;
  superpixel means are over those pixels only. ``S = 1`` is every pixel (the official
  full-resolution pooling).
* Losses: as ``make_loss_fixture.py`` (tau 0.07), pooled with ``index_add_``; weights
  sc 1, tc 1, d2s 1, d2s in its InfoNCE form. L_tc averages the terms of every frame
  other than the key frame (the frame whose ``frame_offsets`` entry is 0).
* AdamW(lr 0.01, betas (0.9, 0.999), weight_decay 0.01, eps 1e-6) over the UNet, both
  heads (not the ViT).
"""

from __future__ import annotations

import argparse
import json
import math
import os
import statistics
import sys
import time
from itertools import pairwise
from typing import Any

import numpy as np
import torch
import torch.nn as nn
import torch.nn.functional as Fn

HERE = os.path.dirname(os.path.abspath(__file__))
sys.path.insert(0, os.path.join(HERE, "..", "..", "tests", "python"))
import read_batch as rb  # noqa: E402

TAU = 0.07
OUT_DIM = 64
MEAN = (0.485, 0.456, 0.406)
STD = (0.229, 0.224, 0.225)
PRESETS = {
    "tiny": {"stem": 16, "blocks": [1] * 8, "planes": [16, 32, 32, 32, 32, 32, 16, 16],
             "vit": "tiny"},
    "minkunet18": {"stem": 32, "blocks": [2] * 8,
                   "planes": [32, 64, 128, 256, 256, 128, 96, 96], "vit": "vits14"},
    "minkunet34": {"stem": 32, "blocks": [2, 3, 4, 6, 2, 2, 2, 2],
                   "planes": [32, 64, 128, 256, 256, 128, 96, 96], "vit": "vits14"},
}


# ---------------------------------------------------------------------------------------
# Sparse UNet on kernel maps
# ---------------------------------------------------------------------------------------

def normal_(weight: torch.Tensor, std: float) -> torch.Tensor:
    with torch.no_grad():
        return weight.normal_(0.0, std)


def linear(cin: int, cout: int, std: float, bias: bool) -> nn.Linear:
    """A Linear initialised as the Rust trainer's (normal weights, zero bias)."""
    layer = nn.Linear(cin, cout, bias=bias)
    normal_(layer.weight, std)
    if bias:
        with torch.no_grad():
            layer.bias.zero_()
    return layer


class SparseConv(nn.Module):
    """Weights [kernels, in, out], normal with std sqrt(2 / (kernels * out)) (the Rust
    init); applied to a kernel map (in rows, out rows, starts of each kernel's pairs)."""

    def __init__(self, kernels: int, cin: int, cout: int):
        super().__init__()
        self.weight = nn.Parameter(torch.randn(kernels, cin, cout) * math.sqrt(2.0 / (kernels * cout)))

    def forward(self, x: torch.Tensor, kmap: tuple, n_out: int) -> torch.Tensor:
        rows_in, rows_out, starts = kmap
        out = x.new_zeros(n_out, self.weight.shape[2])
        if rows_in.numel() == 0:
            return out
        # split, not slices: a slice's backward fills a zero tensor of the whole gather.
        sizes = [e - s for s, e in pairwise(starts)]
        parts = [g @ self.weight[k]
                 for k, g in enumerate(torch.index_select(x, 0, rows_in).split(sizes)) if g.shape[0]]
        return out.index_add_(0, rows_out, torch.cat(parts))


class BasicBlock(nn.Module):
    def __init__(self, cin: int, cout: int):
        super().__init__()
        self.conv1, self.bn1 = SparseConv(27, cin, cout), nn.BatchNorm1d(cout)
        self.conv2, self.bn2 = SparseConv(27, cout, cout), nn.BatchNorm1d(cout)
        self.down = None
        if cin != cout:
            self.down = nn.Sequential(linear(cin, cout, math.sqrt(2.0 / cout), bias=False),
                                      nn.BatchNorm1d(cout))

    def forward(self, x, nbr):
        n = x.shape[0]
        y = torch.relu(self.bn1(self.conv1(x, nbr, n)))
        y = self.bn2(self.conv2(y, nbr, n))
        return torch.relu(y + (x if self.down is None else self.down(x)))


class MinkUNet(nn.Module):
    def __init__(self, preset: dict, cin: int = 4):
        super().__init__()
        stem, blocks, planes = preset["stem"], preset["blocks"], preset["planes"]
        self.stem = SparseConv(27, cin, stem)
        self.stem_bn = nn.BatchNorm1d(stem)
        self.downs, self.down_bns, self.enc = nn.ModuleList(), nn.ModuleList(), nn.ModuleList()
        ch, skips = stem, [stem]
        for i in range(4):
            self.downs.append(SparseConv(8, ch, ch))
            self.down_bns.append(nn.BatchNorm1d(ch))
            layer = nn.ModuleList()
            for j in range(blocks[i]):
                layer.append(BasicBlock(ch if j == 0 else planes[i], planes[i]))
            self.enc.append(layer)
            ch = planes[i]
            skips.append(ch)
        self.ups, self.up_bns, self.dec = nn.ModuleList(), nn.ModuleList(), nn.ModuleList()
        for i in range(4):
            out = planes[4 + i]
            self.ups.append(SparseConv(8, ch, out))
            self.up_bns.append(nn.BatchNorm1d(out))
            layer = nn.ModuleList()
            cat = out + skips[3 - i]
            for j in range(blocks[4 + i]):
                layer.append(BasicBlock(cat if j == 0 else out, out))
            self.dec.append(layer)
            ch = out
        self.out_channels = ch

    def forward(self, feats, maps):
        """maps: {"rows": [V_l], "nbr": [map per level], "down": [map per level],
        "up": [map per level]}; a map is (in rows, out rows, starts per kernel)."""
        rows = maps["rows"]
        x = torch.relu(self.stem_bn(self.stem(feats, maps["nbr"][0], rows[0])))
        skips = [x]
        for i in range(4):
            x = torch.relu(self.down_bns[i](self.downs[i](x, maps["down"][i], rows[i + 1])))
            for block in self.enc[i]:
                x = block(x, maps["nbr"][i + 1])
            skips.append(x)
        for i in range(4):
            level = 3 - i
            x = torch.relu(self.up_bns[i](self.ups[i](x, maps["up"][level], rows[level])))
            x = torch.cat([x, skips[level]], dim=1)
            for block in self.dec[i]:
                x = block(x, maps["nbr"][level])
        return x


# ---------------------------------------------------------------------------------------
# Frozen DINOv2 and the 2D head
# ---------------------------------------------------------------------------------------

def vits14_weights(seed: int) -> dict:
    """Random ViT-S/14 weights under the torch-hub names (37 x 37 position grid)."""
    g = torch.Generator().manual_seed(seed)
    d, depth = 384, 12

    def rnd(*shape, std=0.02):
        return torch.randn(shape, generator=g) * std

    t = {"cls_token": rnd(1, 1, d), "pos_embed": rnd(1, 1 + 37 * 37, d),
         "mask_token": torch.zeros(1, d),
         "patch_embed.proj.weight": rnd(d, 3, 14, 14), "patch_embed.proj.bias": torch.zeros(d),
         "norm.weight": torch.ones(d), "norm.bias": torch.zeros(d)}
    for i in range(depth):
        b = f"blocks.{i}."
        t.update({b + "norm1.weight": torch.ones(d), b + "norm1.bias": torch.zeros(d),
                  b + "attn.qkv.weight": rnd(3 * d, d), b + "attn.qkv.bias": torch.zeros(3 * d),
                  b + "attn.proj.weight": rnd(d, d), b + "attn.proj.bias": torch.zeros(d),
                  b + "ls1.gamma": torch.ones(d), b + "ls2.gamma": torch.ones(d),
                  b + "norm2.weight": torch.ones(d), b + "norm2.bias": torch.zeros(d),
                  b + "mlp.fc1.weight": rnd(4 * d, d), b + "mlp.fc1.bias": torch.zeros(4 * d),
                  b + "mlp.fc2.weight": rnd(d, 4 * d), b + "mlp.fc2.bias": torch.zeros(d)})
    return t


class FrozenViT:
    def __init__(self, tensors: dict, heads: int, eps: float = 1e-6):
        self.t = {k: v.float().contiguous() for k, v in tensors.items()}
        self.heads, self.eps = heads, eps
        self.depth = sum(1 for k in self.t if k.endswith(".norm1.weight"))
        self.dim = self.t["cls_token"].shape[-1]
        self.patch = self.t["patch_embed.proj.weight"].shape[-1]
        self._pos: dict[tuple[int, int], torch.Tensor] = {}

    def pos_embed(self, h: int, w: int) -> torch.Tensor:
        gh, gw = h // self.patch, w // self.patch
        if (gh, gw) not in self._pos:
            pos = self.t["pos_embed"]
            n = round(math.sqrt(pos.shape[1] - 1))
            if gh * gw != n * n or h != w:
                grid = pos[:, 1:].reshape(1, n, n, self.dim).permute(0, 3, 1, 2)
                grid = Fn.interpolate(grid, size=(gh, gw), mode="bicubic", align_corners=False)
                pos = torch.cat([pos[:, :1], grid.permute(0, 2, 3, 1).reshape(1, gh * gw, self.dim)], 1)
            self._pos[(gh, gw)] = pos
        return self._pos[(gh, gw)]

    @torch.no_grad()
    def __call__(self, x: torch.Tensor) -> torch.Tensor:
        """x [N, 3, H, W] (normalised) -> patch tokens [N, D, H/14, W/14]."""
        t, d, nh = self.t, self.dim, self.heads
        n, _, h, w = x.shape
        gh, gw = h // self.patch, w // self.patch
        tok = Fn.conv2d(x, t["patch_embed.proj.weight"], t["patch_embed.proj.bias"], stride=self.patch)
        tok = tok.flatten(2).transpose(1, 2)
        z = torch.cat([t["cls_token"].expand(n, -1, -1), tok], 1) + self.pos_embed(h, w)
        for i in range(self.depth):
            b = f"blocks.{i}."
            y = Fn.layer_norm(z, (d,), t[b + "norm1.weight"], t[b + "norm1.bias"], self.eps)
            qkv = Fn.linear(y, t[b + "attn.qkv.weight"], t[b + "attn.qkv.bias"])
            q, k, v = qkv.reshape(n, -1, 3, nh, d // nh).permute(2, 0, 3, 1, 4)
            o = Fn.scaled_dot_product_attention(q, k, v).transpose(1, 2).reshape(n, -1, d)
            z = z + t[b + "ls1.gamma"] * Fn.linear(o, t[b + "attn.proj.weight"], t[b + "attn.proj.bias"])
            y = Fn.layer_norm(z, (d,), t[b + "norm2.weight"], t[b + "norm2.bias"], self.eps)
            y = Fn.linear(Fn.gelu(Fn.linear(y, t[b + "mlp.fc1.weight"], t[b + "mlp.fc1.bias"])),
                          t[b + "mlp.fc2.weight"], t[b + "mlp.fc2.bias"])
            z = z + t[b + "ls2.gamma"] * y
        z = Fn.layer_norm(z, (d,), t["norm.weight"], t["norm.bias"], self.eps)
        return z[:, 1:].transpose(1, 2).reshape(n, d, gh, gw)


def pixel_sampler(pixels: np.ndarray, image: tuple, grid: tuple) -> dict:
    """Bilinear (aligned corners) sampling of a [gh, gw] patch grid upsampled to [H, W] at
    ``pixels`` [P, 3] (image, row, col), as ``PixelSampler::new``: source = dst * (g - 1)
    / (size - 1); the 4 cells around each pixel (rows of the [I * gh * gw] grid table)
    and their weights [P, 1]."""
    (h, w), (gh, gw) = image, grid
    sy = (gh - 1) / (h - 1) if h > 1 else 0.0
    sx = (gw - 1) / (w - 1) if w > 1 else 0.0
    img = pixels[:, 0].astype(np.int64)
    y = pixels[:, 1].astype(np.float64) * sy
    x = pixels[:, 2].astype(np.float64) * sx
    y0, x0 = np.floor(y).astype(np.int64), np.floor(x).astype(np.int64)
    y1, x1 = np.minimum(y0 + 1, gh - 1), np.minimum(x0 + 1, gw - 1)
    fy, fx = y - y0, x - x0
    base = img * gh * gw
    cells = [(y0, x0), (y0, x1), (y1, x0), (y1, x1)]
    weights = [(1 - fy) * (1 - fx), (1 - fy) * fx, fy * (1 - fx), fy * fx]
    return {"corners": [long(base + cy * gw + cx) for cy, cx in cells],
            "weights": [torch.from_numpy(wt.astype(np.float32))[:, None] for wt in weights]}


class Head2D(nn.Module):
    """1x1 conv dim -> 64 (a Linear on the patch rows, std sqrt(1 / dim), zero bias), x14
    bilinear upsampling with aligned corners evaluated at the sampled pixels only, L2
    normalisation: [I, dim, gh, gw] -> [P, 64] in the order of the sampler's pixels."""

    def __init__(self, dim: int):
        super().__init__()
        self.proj = linear(dim, OUT_DIM, math.sqrt(1.0 / dim), bias=True)

    def forward(self, tokens, sampler):
        n, d, gh, gw = tokens.shape
        rows = self.proj(tokens.permute(0, 2, 3, 1).reshape(n * gh * gw, d))
        out = None
        for idx, wt in zip(sampler["corners"], sampler["weights"], strict=False):
            term = rows[idx] * wt
            out = term if out is None else out + term
        return Fn.normalize(out, dim=1)


# ---------------------------------------------------------------------------------------
# Losses
# ---------------------------------------------------------------------------------------

def info_nce(a: torch.Tensor, b: torch.Tensor) -> torch.Tensor:
    if a.shape[0] == 0:
        return a.new_zeros(())
    return Fn.cross_entropy(a @ b.T / TAU, torch.arange(a.shape[0]))


def superflow_losses(pairing_feats, pixel_feats, ix, weights=(1.0, 1.0, 1.0)) -> dict:
    """pairing_feats [pairings, d]: the 3D feature of every pairing's point (pairing
    order); pixel_feats [P, d]: the 2D features of the sampled pixels (``ix["pixels"]``
    order), as ``SuperFlowLoss::forward`` takes them."""
    d, dt = pairing_feats.shape[1], pairing_feats.dtype
    q = torch.zeros(ix["px_slots"], d, dtype=dt).index_add_(0, ix["px_slot"], pixel_feats) / ix["cpx"].to(dt)
    k = torch.zeros(ix["pt_slots"], d, dtype=dt).index_add_(
        0, ix["pt_slot"], pairing_feats) / ix["cpt"].to(dt)
    sc = [info_nce(k[a], q[b]) for a, b in ix["sc"]]
    tc = [info_nce(k[a], k[b]) for a, b in ix["tc"]]
    d2s = info_nce(k[ix["d2s"][0]], k[ix["d2s"][1]])
    l_sc = torch.stack(sc).mean()
    l_tc = torch.stack(tc).mean() if tc else l_sc.new_zeros(())
    total = weights[0] * l_sc + weights[1] * l_tc + weights[2] * d2s
    return {"l_sc": l_sc, "l_tc": l_tc, "l_d2s": d2s, "total": total,
            "l_sc_frames": sc, "l_tc_terms": tc}


# ---------------------------------------------------------------------------------------
# Batch -> tensors (once)
# ---------------------------------------------------------------------------------------

def long(a) -> torch.Tensor:
    return torch.from_numpy(np.asarray(a, dtype=np.int64).copy())


def prepare(arr: dict, pixel_stride: int = 1, patch: int = 14, maps_needed: bool = True) -> dict:
    """Tensors of a batch for the reference: ``maps_needed=False`` for a 3D network that
    builds its own maps (a batch of ``kernel_maps = "none"`` has none)."""
    images = arr["images"]
    levels = sum(1 for name in arr if name.endswith("_nbr_starts"))
    maps: dict[str, list[Any]] = {"rows": [int(arr["l0_coords"].shape[0])] if not levels else [],
                                  "nbr": [], "down": [], "up": []}
    for lv in range(levels):
        maps["rows"].append(int(arr[f"l{lv}_coords"].shape[0]))
        nbr, starts = arr[f"l{lv}_nbr"].astype(np.int64), arr[f"l{lv}_nbr_starts"].astype(np.int64)
        maps["nbr"].append((long(nbr[:, 0]), long(nbr[:, 1]), [int(v) for v in starts]))
        if lv + 1 < levels:
            dn, ds = arr[f"l{lv}_down"].astype(np.int64), arr[f"l{lv}_down_starts"].astype(np.int64)
            child, parent, ds = long(dn[:, 0]), long(dn[:, 1]), [int(v) for v in ds]
            maps["down"].append((child, parent, ds))
            maps["up"].append((parent, child, ds))
    if maps_needed and levels != 5:
        raise ValueError(f"the UNet needs 5 levels of maps, the batch has {levels}")

    ix = prepare_losses(arr, pixel_stride)
    h, w = images.shape[1:3]
    if h % patch or w % patch:
        raise ValueError(f"images are {h}x{w}, not multiples of the ViT patch {patch}")
    p2v = np.asarray(arr["point_to_voxel"], dtype=np.int64)
    return {
        "images": torch.from_numpy(np.array(images)),
        "voxel_features": torch.from_numpy(np.array(arr["voxel_features"], dtype=np.float32)),
        "pairing_voxel": long(p2v[np.asarray(arr["pairing_point"], dtype=np.int64)]),
        "sampler": pixel_sampler(ix["pixels"], (h, w), (h // patch, w // patch)),
        "maps": maps, "ix": ix,
        "summary": (f"{ix['summary']}, points {arr['points'].shape[0]}, voxels {maps['rows']}"),
    }


def prepare_losses(arr: dict, pixel_stride: int = 1) -> dict:
    """Index tensors of the losses: pooling slots, counts and the kept slot pairs; the
    superpixel means are over the pixels sampled every ``pixel_stride`` rows and columns
    (from ``pixel_stride // 2``), image by image, row by row (``LossPlan::new``)."""
    b, f = arr["num_superpixels"].shape
    n_img, h, w = arr["superpixels"].shape
    # Sample bb's images are F * first[bb] + ff * K_bb + k (its own cameras, K_bb of them).
    first = np.asarray(arr["sample_cameras"], dtype=np.int64)
    k_of = np.diff(first)
    if len(first) != b + 1 or f * int(first[-1]) != n_img:
        raise ValueError(f"sample_cameras {first.tolist()} do not number {n_img} images of "
                         f"{b} samples x {f} frames")
    c_per = f + 1
    offsets = arr["frame_offsets"].astype(np.int64)
    key = int(np.flatnonzero(offsets == 0)[0])
    n_sp = arr["num_superpixels"].astype(np.int64)
    smax = max(int(n_sp.max()), 1)

    # Superpixel slots: frame (b*F + f) * smax + id; superpoint slots: cloud * smax + id.
    stride = max(int(pixel_stride), 1)
    rows, cols = np.arange(stride // 2, h, stride), np.arange(stride // 2, w, stride)
    sp = arr["superpixels"].astype(np.int64)[:, rows][:, :, cols].reshape(n_img, -1)
    grid = np.stack(np.meshgrid(np.arange(n_img), rows, cols, indexing="ij"), -1)
    pixels = grid.reshape(-1, 3)  # (image, row, col), image-major then row-major
    frame_of_image = np.repeat(np.arange(b * f), np.repeat(k_of, f))
    px_slot = (frame_of_image[:, None] * smax + sp).reshape(-1)
    cpx = np.bincount(px_slot, minlength=b * f * smax)
    pc = arr["pairing_clouds"].astype(np.int64)
    cloud_of = np.repeat(np.arange(b * c_per), np.diff(pc))
    pt_slot = cloud_of * smax + arr["pairing_superpixel"].astype(np.int64)
    cpt = np.bincount(pt_slot, minlength=b * c_per * smax)

    def slots(pairs):
        """(rows of side a, rows of side b) kept, b major, id minor."""
        ra, rb_ = [], []
        for bb in range(b):
            for (ga, gb, limit, need) in pairs(bb):
                s = np.arange(limit)
                keep = np.all([c[s] > 0 for c in need], axis=0) if limit else np.zeros(0, bool)
                ra.append(ga + s[keep])
                rb_.append(gb + s[keep])
        return long(np.concatenate(ra)), long(np.concatenate(rb_))

    def cloud_base(bb, c):
        return (bb * c_per + c) * smax

    def frame_base(bb, ff):
        return (bb * f + ff) * smax

    def cpt_of(bb, c):
        return cpt[cloud_base(bb, c):cloud_base(bb, c) + smax]

    def cpx_of(bb, ff):
        return cpx[frame_base(bb, ff):frame_base(bb, ff) + smax]

    sc = [slots(lambda bb, ff=ff: [(cloud_base(bb, ff), frame_base(bb, ff), int(n_sp[bb, ff]),
                                   [cpt_of(bb, ff), cpx_of(bb, ff)])]) for ff in range(f)]
    tc = [slots(lambda bb, ff=ff: [(cloud_base(bb, key), cloud_base(bb, ff),
                                   int(min(n_sp[bb, key], n_sp[bb, ff])),
                                   [cpt_of(bb, key), cpt_of(bb, ff)])])
          for ff in range(f) if ff != key]
    dense, keyrows = slots(lambda bb: [(cloud_base(bb, f), cloud_base(bb, key), int(n_sp[bb, key]),
                                        [cpt_of(bb, key), cpt_of(bb, f)])])
    return {
        "px_slot": long(px_slot), "px_slots": b * f * smax, "pixels": pixels,
        "cpx": torch.from_numpy(np.maximum(cpx, 1).astype(np.float32))[:, None],
        "pt_slot": long(pt_slot), "pt_slots": b * c_per * smax,
        "cpt": torch.from_numpy(np.maximum(cpt, 1).astype(np.float32))[:, None],
        "pairing_point": long(arr["pairing_point"]),
        "sc": sc, "tc": tc, "d2s": (dense, keyrows),
        "summary": (f"B={b} F={f} K={k_of.tolist()} images {h}x{w}, pixel stride {stride} "
                    f"({pixels.shape[0]} sampled pixels), pairings "
                    f"{arr['pairing_point'].shape[0]}, slots sc {[len(a) for a, _ in sc]} "
                    f"tc {[len(a) for a, _ in tc]} d2s {len(dense)}"),
    }


# ---------------------------------------------------------------------------------------
# Synthetic batch (the same sections, written in the batch format and read back)
# ---------------------------------------------------------------------------------------

DTYPE_CODES = {np.dtype("<u1"): 1, np.dtype("<u2"): 2, np.dtype("<i4"): 3, np.dtype("<u4"): 4,
               np.dtype("<i8"): 5, np.dtype("<u8"): 6, np.dtype("<f4"): 7, np.dtype("<f8"): 8}


def encode_batch(sections: list, sample_count: int) -> bytes:
    """Header + payload of a batch holding `sections` [(name, array)]."""
    header = np.zeros(1, dtype=rb.HEADER)
    offset, blobs = 0, []
    for i, (name, a) in enumerate(sections):
        a = np.ascontiguousarray(a)
        entry = header[0]["sections"][i]
        entry["name"] = name.encode()
        entry["dtype"] = DTYPE_CODES[a.dtype]
        entry["ndim"] = a.ndim
        entry["shape"][:a.ndim] = a.shape
        entry["offset"] = offset
        entry["len_bytes"] = a.nbytes
        blobs.append((offset, a.tobytes()))
        offset = (offset + a.nbytes + 63) // 64 * 64
    payload = bytearray(offset)
    for off, data in blobs:
        payload[off:off + len(data)] = data
    h = header[0]
    h["magic"], h["version"], h["header_size"] = rb.MAGIC, rb.VERSION, rb.HEADER_SIZE
    h["section_count"], h["payload_len"], h["sample_count"] = len(sections), offset, sample_count
    h["run"] = b"synthetic"
    return header.tobytes() + bytes(payload)


def synthetic_batch(seed: int, points: int, height: int, width: int, b: int = 2, f: int = 3,
                    k: int = 3, levels: int = 5, voxel: float = 0.2) -> bytes:
    rng = np.random.default_rng(seed)
    c_per, n_img = f + 1, b * f * k
    key = 1

    # Superpixels: blocks of about 16 x 24 pixels with ids drawn per frame.
    n_sp = rng.integers(120, 180, size=(b, f)).astype(np.uint32)
    sp = np.zeros((n_img, height, width), np.uint16)
    for i in range(n_img):
        n = int(n_sp[(i // k) // f, (i // k) % f])  # image i is of frame i // k
        ids = rng.integers(0, n, size=(-(-height // 16), -(-width // 24)))
        sp[i] = np.kron(ids, np.ones((16, 24), np.int64))[:height, :width]
    images = rng.integers(0, 256, size=(n_img, height, width, 3), dtype=np.uint8)

    xyz, inten, point_clouds, sweeps = [], [], [0], []
    for _ in range(b):
        for c in range(c_per):
            n = points * (2 if c == f else 1)
            r = np.minimum(2.0 + rng.exponential(12.0, n), 80.0)
            th = rng.uniform(-np.pi, np.pi, n)
            z = np.where(rng.random(n) < 0.6, -1.7, rng.uniform(-1.7, 2.0, n)) + rng.normal(0, 0.05, n)
            xyz.append(np.stack([r * np.cos(th), r * np.sin(th), z], 1).astype(np.float32))
            inten.append(rng.random(n).astype(np.float32))
            sweeps.append((np.arange(n) >= points).astype(np.uint8) if c == f else np.zeros(n, np.uint8))
            point_clouds.append(point_clouds[-1] + n)
    pts = np.concatenate([np.concatenate(xyz), np.concatenate(inten)[:, None]], 1).astype(np.float32)
    cloud_of_point = np.repeat(np.arange(b * c_per), np.diff(point_clouds))

    # Level 0 voxels: unique (cloud, cell); representative point = first in the cell.
    cell = np.floor(pts[:, :3] / voxel).astype(np.int64)
    keys0 = np.concatenate([cloud_of_point[:, None], cell], 1)
    coords0, first, p2v = np.unique(keys0, axis=0, return_index=True, return_inverse=True)
    coords = [coords0]
    for _ in range(1, levels):
        prev = coords[-1]
        coords.append(np.unique(np.concatenate([prev[:, :1], prev[:, 1:] >> 1], 1), axis=0))

    def encode(c):  # (cloud, x, y, z) -> one sortable int64
        return (((c[:, 0] * 8192 + (c[:, 1] + 4096)) * 8192 + (c[:, 2] + 4096)) * 8192 + (c[:, 3] + 4096))

    def lookup(table_keys, c):
        q = encode(c)
        pos = np.clip(np.searchsorted(table_keys, q), 0, len(table_keys) - 1)
        return np.where(table_keys[pos] == q, pos, -1)

    sections_levels = []
    for lv in range(levels):
        cl = coords[lv]
        keys = encode(cl)  # np.unique sorts rows lexicographically, so keys are sorted
        assert (np.diff(keys) > 0).all()
        pairs, starts = [], [0]
        for j in range(27):
            off = np.array([0, j // 9 - 1, (j // 3) % 3 - 1, j % 3 - 1])
            src = lookup(keys, cl + off)
            out_rows = np.flatnonzero(src >= 0)
            pairs.append(np.stack([src[out_rows], out_rows], 1))
            starts.append(starts[-1] + len(out_rows))
        rows = np.searchsorted(cl[:, 0], np.arange(b * c_per + 1))
        sections_levels += [(f"l{lv}_coords", cl.astype(np.int32)), (f"l{lv}_clouds", rows.astype(np.uint32)),
                            (f"l{lv}_nbr", np.concatenate(pairs).astype(np.uint32)),
                            (f"l{lv}_nbr_starts", np.array(starts, np.uint32))]
        if lv + 1 < levels:
            parent_keys = encode(coords[lv + 1])
            parent = lookup(parent_keys, np.concatenate([cl[:, :1], cl[:, 1:] >> 1], 1))
            assert (parent >= 0).all()
            pos = cl[:, 1:] & 1
            kid = pos[:, 0] * 4 + pos[:, 1] * 2 + pos[:, 2]
            order = np.argsort(kid, kind="stable")
            dn = np.stack([order, parent[order]], 1)
            ds = np.concatenate([[0], np.cumsum(np.bincount(kid, minlength=8))])
            sections_levels += [(f"l{lv}_down", dn.astype(np.uint32)), (f"l{lv}_down_starts", ds.astype(np.uint32))]

    # Pairings: about a third of the points, each on a random pixel of its frame's images.
    pp, pi, ppx, psp, pairing_clouds = [], [], [], [], [0]
    for bb in range(b):
        for c in range(c_per):
            g = bb * c_per + c
            ff = key if c == f else c
            lo, hi = point_clouds[g], point_clouds[g + 1]
            n = (hi - lo) // 3
            prow = rng.integers(lo, hi, n)
            img = (bb * f + ff) * k + rng.integers(0, k, n)
            r, col = rng.integers(0, height, n), rng.integers(0, width, n)
            pp.append(prow)
            pi.append(img)
            ppx.append(np.stack([r, col], 1))
            psp.append(sp[img, r, col])
            pairing_clouds.append(pairing_clouds[-1] + n)
    P = pairing_clouds[-1]
    V0 = len(coords0)
    sections = [
        ("sample_ids", np.zeros((b, 5), np.uint64)),
        ("frame_stamps", np.zeros((b, f), np.int64)),
        ("frame_offsets", np.arange(f, dtype=np.int32) - key),
        ("camera_ids", np.tile(np.arange(k, dtype=np.uint32), b)),
        ("sample_cameras", np.arange(b + 1, dtype=np.uint32) * k),
        ("image_stamps", np.zeros(n_img, np.int64)),
        ("image_flipped", np.zeros(n_img, np.uint8)),
        ("images", images),
        ("superpixels", sp),
        ("num_superpixels", n_sp),
        ("points", pts),
        ("point_clouds", np.array(point_clouds, np.uint32)),
        ("source_sweep", np.concatenate(sweeps)),
        ("point_to_voxel", p2v.reshape(-1).astype(np.uint32)),
        ("augmentation", np.tile(np.array([0, 0, 0, 1], np.float32), (b * c_per, 1))),
        ("pairing_point", np.concatenate(pp).astype(np.uint32)),
        ("pairing_image", np.concatenate(pi).astype(np.uint32)),
        ("pairing_pixel", np.concatenate(ppx).astype(np.uint16)),
        ("pairing_uv", np.zeros((P, 2), np.float32)),
        ("pairing_depth", np.ones(P, np.float32)),
        ("pairing_superpixel", np.concatenate(psp).astype(np.uint32)),
        ("pairing_clouds", np.array(pairing_clouds, np.uint32)),
        ("voxel_features", pts[first]),
        *sections_levels,
    ]
    assert len(pts[first]) == V0
    return encode_batch(sections, b)


def load(data: bytes):
    buf = np.frombuffer(data, np.uint8)
    return rb.read_batch(buf[:rb.HEADER_SIZE], buf[rb.HEADER_SIZE:])


# ---------------------------------------------------------------------------------------

def build(preset_name: str, seed: int = 0):
    """The frozen ViT and the trainable modules of a preset (seeded)."""
    torch.manual_seed(seed)
    preset = PRESETS[preset_name]
    if preset["vit"] == "tiny":
        from safetensors.torch import load_file
        vit = FrozenViT(load_file(os.path.join(HERE, "..", "tests", "fixtures", "tiny_dinov2.safetensors")),
                        heads=2)
    else:
        vit = FrozenViT(vits14_weights(seed), heads=6)
    unet = MinkUNet(preset)
    head3d = linear(unet.out_channels, OUT_DIM, math.sqrt(1.0 / unet.out_channels), bias=True)
    head2d = Head2D(vit.dim)
    return vit, unet, head3d, head2d


def make_step(batch: dict, vit, unet, head3d, head2d, opt):
    """One training step; returns (losses, phase seconds {vit, forward, backward, update})."""
    mean = torch.tensor(MEAN).view(1, 3, 1, 1)
    std = torch.tensor(STD).view(1, 3, 1, 1)

    def step():
        t = [time.perf_counter()]
        with torch.no_grad():
            x = batch["images"].permute(0, 3, 1, 2).float() / 255.0
            tokens = vit((x - mean) / std)
        t.append(time.perf_counter())
        pixel = head2d(tokens, batch["sampler"])
        vox = Fn.normalize(head3d(unet(batch["voxel_features"], batch["maps"])), dim=1)
        losses = superflow_losses(vox[batch["pairing_voxel"]], pixel, batch["ix"])
        t.append(time.perf_counter())
        opt.zero_grad(set_to_none=True)
        losses["total"].backward()
        t.append(time.perf_counter())
        opt.step()
        t.append(time.perf_counter())
        phases = dict(zip(("vit", "forward", "backward", "update"), np.diff(t), strict=False))
        return losses, phases

    return step


def self_test(seed: int) -> None:
    """Checks the losses and the ViT against the fixtures, the 2D head's pixel sampling
    against full-resolution upsampling, and a tiny step on a synthetic batch."""
    fixtures = os.path.join(HERE, "..", "tests", "fixtures")
    for name in ("losses_mixed.json", "losses.json"):  # the last one stays for the checks below
        with open(os.path.join(fixtures, name)) as fh:
            fx = json.load(fh)
        cfg = fx["config"]
        b, f, h, w, d = (cfg[x] for x in ("batch", "frames", "height", "width", "dim"))
        cams = cfg["cameras"] if isinstance(cfg["cameras"], list) else [cfg["cameras"]] * b
        n_img = f * sum(cams)
        arr = {"num_superpixels": np.array(fx["num_superpixels"], np.uint32),
               "superpixels": np.array(fx["superpixels"], np.uint16).reshape(n_img, h, w),
               "frame_offsets": np.arange(f, dtype=np.int32) - cfg["key_frame"],
               "sample_cameras": np.concatenate([[0], np.cumsum(cams)]).astype(np.uint32)}
        for section in ("pairing_point", "pairing_superpixel", "pairing_clouds"):
            arr[section] = np.array(fx[section], np.uint32)
        ix = prepare_losses(arr)
        pf = torch.tensor(np.array(fx["point_features"], np.float32).reshape(-1, d),
                          dtype=torch.float64, requires_grad=True)
        xf = torch.tensor(np.array(fx["pixel_features"], np.float32).reshape(n_img, d, h, w),
                          dtype=torch.float64, requires_grad=True)
        wt = cfg["weights"]
        # Stride 1: every pixel, image-major then row-major = the full map's order.
        out = superflow_losses(pf[ix["pairing_point"]], xf.permute(0, 2, 3, 1).reshape(-1, d),
                               ix, (wt["sc"], wt["tc"], wt["d2s"]))
        out["total"].backward()
        assert pf.grad is not None and xf.grad is not None
        ex = fx["expected"]
        for got, want in ((out["l_sc"], ex["l_sc"]), (out["l_tc"], ex["l_tc"]),
                          (out["l_d2s"], ex["l_d2s_infonce"]),
                          (out["total"], ex["total_infonce"])):
            assert abs(got.item() - want) < 1e-10, (got.item(), want)
        assert np.abs(pf.grad.numpy().reshape(-1) - ex["grad_point_features_infonce"]).max() < 1e-10
        assert np.abs(xf.grad.numpy().reshape(-1) - ex["grad_pixel_features_infonce"]).max() < 1e-10
        print(f"losses match {name} (to 1e-10, gradients included)")
    k = cams[0]

    # Strided pooling = the full-map pooling restricted to the sampled pixels.
    for stride in (2, 3, 4):
        ixs = prepare_losses(arr, stride)
        rows, cols = np.arange(stride // 2, h, stride), np.arange(stride // 2, w, stride)
        assert ixs["pixels"].shape[0] == b * f * k * len(rows) * len(cols)
        sub = xf.detach()[:, :, rows][:, :, :, cols].permute(0, 2, 3, 1).reshape(-1, d)
        got = superflow_losses(pf.detach()[ixs["pairing_point"]], sub, ixs)["l_sc"].item()
        pix = torch.from_numpy(ixs["pixels"])
        again = xf.detach()[pix[:, 0], :, pix[:, 1], pix[:, 2]]
        want = superflow_losses(pf.detach()[ixs["pairing_point"]], again, ixs)["l_sc"].item()
        assert abs(got - want) < 1e-12, (stride, got, want)
    print("strided superpixel pooling samples rows/cols stride//2, stride//2 + stride, ...")

    # The 2D head at sampled pixels = full-resolution upsampling at those pixels.
    g = torch.Generator().manual_seed(seed)
    tokens = torch.randn(3, 24, 4, 6, generator=g)
    head = Head2D(24)
    with torch.no_grad():
        full = Fn.conv2d(tokens, head.proj.weight[:, :, None, None], head.proj.bias)
        full = Fn.normalize(Fn.interpolate(full, size=(56, 84), mode="bilinear", align_corners=True), dim=1)
        for stride in (1, 3, 4):
            rows, cols = np.arange(stride // 2, 56, stride), np.arange(stride // 2, 84, stride)
            pixels = np.stack(np.meshgrid(np.arange(3), rows, cols, indexing="ij"), -1).reshape(-1, 3)
            got = head(tokens, pixel_sampler(pixels, (56, 84), (4, 6)))
            want = full[:, :, rows][:, :, :, cols].permute(0, 2, 3, 1).reshape(-1, OUT_DIM)
            err = (got - want).abs().max().item()
            assert err < 1e-5, (stride, err)
    print(f"2D head at sampled pixels matches the full-resolution map (max |diff| {err:.1e})")

    from safetensors.torch import load_file
    with open(os.path.join(fixtures, "vit.json")) as fh:
        vx = json.load(fh)
    vit = FrozenViT(load_file(os.path.join(fixtures, "tiny_dinov2.safetensors")), heads=2)
    for case in vx["cases"]:
        img = torch.tensor(case["image"], dtype=torch.float32).reshape(case["height"], case["width"], 3)
        x = ((img / 255.0 - torch.tensor(MEAN)) / torch.tensor(STD)).permute(2, 0, 1)[None]
        got = vit(x)[0].permute(1, 2, 0).reshape(-1)
        err = (got.double() - torch.tensor(case["patch_tokens"], dtype=torch.float64)).abs().max().item()
        assert err < 1e-4, (case["name"], err)
        print(f"ViT case {case['name']} matches vit.json (max |diff| {err:.1e})")

    data = synthetic_batch(seed, 500, 56, 112)
    _, arrays = load(data)
    batch = prepare(arrays, pixel_stride=4)
    for lv in range(4):  # every voxel has one parent and the up map covers every child
        assert len(batch["maps"]["down"][lv][0]) == batch["maps"]["rows"][lv]
    print(f"synthetic batch reads back: {batch['summary']}")
    vit, unet, head3d, head2d = build("tiny", seed=seed)
    params = [*unet.parameters(), *head3d.parameters(), *head2d.parameters()]
    opt = torch.optim.AdamW(params, lr=0.01, betas=(0.9, 0.999), weight_decay=0.01, eps=1e-6)
    step = make_step(batch, vit, unet, head3d, head2d, opt)
    first = [step()[0]["total"].item() for _ in range(2)]
    assert all(math.isfinite(v) for v in first), first
    print(f"tiny preset trains on it at pixel stride 4 (total {first[0]:.4f} -> {first[1]:.4f})")


def empty_slots(arrays: dict, preset: str, seed: int, log) -> None:
    """The frozen ViT of `preset` on the batch's images (one row per real camera image:
    batch format 2), and on the rows a layout with the largest camera count in every
    sample would hold (the others empty): what a masked layout costs, per step, when the
    ViT runs on every slot. Also the bytes those slots add to the payload."""
    frames = len(arrays["frame_offsets"])
    cameras = np.diff(np.asarray(arrays["sample_cameras"], dtype=np.int64))
    images = torch.from_numpy(np.array(arrays["images"])).permute(0, 3, 1, 2).float() / 255.0
    empty = frames * int(cameras.max()) * len(cameras) - images.shape[0]
    padded = torch.cat([images, torch.zeros(empty, *images.shape[1:])])
    vit = build(preset, seed)[0]
    mean = torch.tensor(MEAN).view(1, 3, 1, 1)
    std = torch.tensor(STD).view(1, 3, 1, 1)

    def seconds(x: torch.Tensor) -> float:
        with torch.no_grad():
            started = time.perf_counter()
            vit((x - mean) / std)
            return time.perf_counter() - started

    seconds(images[:2])  # warm-up
    runs = [(seconds(images), seconds(padded)) for _ in range(3)]
    ragged = statistics.median(r for r, _ in runs)
    masked = statistics.median(m for _, m in runs)
    h, w = images.shape[2:]
    slot_bytes = h * w * 3 + h * w * 2 + 8 + 1  # images, superpixels, stamp, flipped
    payload = sum(np.asarray(a).nbytes for a in arrays.values())
    log(f"cameras per sample {cameras.tolist()}, {frames} frames: {images.shape[0]} images; "
        f"{empty} empty slots in a layout of {int(cameras.max())} per sample")
    log(f"ViT ({preset}) on the images: {ragged:.2f} s; on every slot: {masked:.2f} s "
        f"(x{masked / ragged:.3f}); the empty slots add {empty * slot_bytes / 1e6:.2f} MB to "
        f"{payload / 1e6:.2f} MB of sections (+{100 * empty * slot_bytes / payload:.1f} %)")


def main(argv=None) -> int:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("--batch", help="batch file (header + payload)")
    p.add_argument("--preset", choices=sorted(PRESETS), default="tiny")
    p.add_argument("--pixel-stride", type=int, default=1,
                   help="superpixel pooling at every S-th pixel (1 = every pixel)")
    p.add_argument("--steps", type=int, default=10)
    p.add_argument("--warmup", type=int, default=2)
    p.add_argument("--threads", type=int, default=os.cpu_count())
    p.add_argument("--json", action="store_true")
    p.add_argument("--seed", type=int, default=0)
    p.add_argument("--synthetic", action="store_true", help="use a synthetic batch")
    p.add_argument("--synthetic-points", type=int, default=8000, help="points per frame cloud")
    p.add_argument("--synthetic-size", default="224x448", help="image HxW of the synthetic batch")
    p.add_argument("--write-synthetic", help="also save the synthetic batch to this file")
    p.add_argument("--self-test", action="store_true",
                   help="check the losses, the 2D head and the ViT against references, then exit")
    p.add_argument("--empty-slots", action="store_true",
                   help="time the ViT on the batch's images and on as many slots as a layout "
                        "of the largest camera count per sample would hold, then exit")
    args = p.parse_args(argv)
    log = (lambda *a: print(*a, file=sys.stderr)) if args.json else print
    if args.self_test:
        self_test(args.seed)
        return 0
    if bool(args.batch) == args.synthetic:
        p.error("give exactly one of --batch FILE and --synthetic")
    if args.pixel_stride < 1:
        p.error("--pixel-stride must be at least 1")

    torch.set_num_threads(args.threads)
    if args.empty_slots:
        header, payload = rb.load_batch_file(args.batch)
        _, arrays = rb.read_batch(header, payload)
        empty_slots(arrays, args.preset, args.seed, log)
        return 0
    if args.synthetic:
        hh, ww = (int(v) for v in args.synthetic_size.split("x"))
        data = synthetic_batch(args.seed, args.synthetic_points, hh, ww)
        if args.write_synthetic:
            with open(args.write_synthetic, "wb") as fh:
                fh.write(data)
        _, arrays = load(data)
    else:
        header, payload = rb.load_batch_file(args.batch)
        _, arrays = rb.read_batch(header, payload)

    t0 = time.perf_counter()
    batch = prepare(arrays, args.pixel_stride)
    prep_ms = (time.perf_counter() - t0) * 1e3
    log(f"batch: {batch['summary']}; prep {prep_ms:.1f} ms")

    vit, unet, head3d, head2d = build(args.preset, seed=args.seed)
    params = [*unet.parameters(), *head3d.parameters(), *head2d.parameters()]
    n_params = sum(x.numel() for x in params)
    opt = torch.optim.AdamW(params, lr=0.01, betas=(0.9, 0.999), weight_decay=0.01, eps=1e-6)
    log(f"preset {args.preset}: {n_params} trainable parameters "
        f"({sum(x.numel() for x in unet.parameters()) + sum(x.numel() for x in head3d.parameters())} 3D), "
        f"ViT dim {vit.dim} depth {vit.depth}, pixel stride {args.pixel_stride}, threads {args.threads}")
    step = make_step(batch, vit, unet, head3d, head2d, opt)

    times, phases = [], []
    for i in range(args.warmup + args.steps):
        t0 = time.perf_counter()
        losses, split = step()
        dt = (time.perf_counter() - t0) * 1e3
        if i >= args.warmup:
            times.append(dt)
            phases.append(split)
        log(f"step {i}{' (warmup)' if i < args.warmup else ''}: {dt:.1f} ms "
            f"(ViT {split['vit'] * 1e3:.0f}, forward {split['forward'] * 1e3:.0f}, "
            f"backward {split['backward'] * 1e3:.0f}, update {split['update'] * 1e3:.0f}), total "
            f"{losses['total'].item():.4f} (sc {losses['l_sc'].item():.4f}, "
            f"tc {losses['l_tc'].item():.4f}, d2s {losses['l_d2s'].item():.4f})")
        if not math.isfinite(losses["total"].item()):
            raise RuntimeError("the loss is not finite")
    med = statistics.median(times) if times else float("nan")
    log(f"{args.preset}: {med:.1f} ms/step (median of {len(times)}, mean "
        f"{statistics.fmean(times) if times else float('nan'):.1f}), {1e3 / med:.3f} steps/s, "
        f"{args.threads} threads")
    if args.json:
        print(json.dumps({
            "preset": args.preset, "ms_per_step_median": med, "steps_per_s": 1e3 / med,
            "threads": args.threads, "pixel_stride": args.pixel_stride,
            "sampled_pixels": int(batch["ix"]["pixels"].shape[0]), "params": n_params,
            "params_3d": sum(x.numel() for x in unet.parameters())
            + sum(x.numel() for x in head3d.parameters()),
            "prep_ms": prep_ms,
            "phases_ms": {k: statistics.median(ph[k] for ph in phases) * 1e3 if phases else float("nan")
                          for k in ("vit", "forward", "backward", "update")},
        }))
    return 0


if __name__ == "__main__":
    sys.exit(main())
