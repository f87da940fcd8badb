#!/usr/bin/env python3
"""Reference values of the SuperFlow losses for the Rust trainer's tests.

Writes ``trainer/tests/fixtures/losses.json``: small fixed random inputs (features,
superpixels, pairings laid out exactly like a superflow batch) and the expected losses
and gradients, computed by an independent, deliberately plain PyTorch implementation.

Run (needs PyTorch and numpy; CI does not, it only reads the committed JSON)::

    /tmp/torchenv/bin/python trainer/reference/make_loss_fixture.py          # losses.json
    /tmp/torchenv/bin/python trainer/reference/make_loss_fixture.py --mixed  # losses_mixed.json

``--mixed`` writes the same kind of fixture for a batch of two rigs: sample 0 with three
cameras, sample 1 with one (``config.cameras`` is then the list of per-sample counts).

The script is deterministic (fixed seed) and rewrites the same file byte for byte.

Batch conventions (those of the Rust side):

* ``B`` samples, ``F`` frames (offsets -1, 0, +1; key frame index 1), ``K_b`` cameras in
  sample ``b`` (``K`` each, or per sample with ``--mixed``), ``C = F + 1`` clouds per
  sample: frames ``0..F-1`` then the dense cloud at ``c = F``.
  Cloud number ``b*C + c``; ``point_clouds`` (``B*C + 1`` entries) holds the first
  global point row of each cloud, ``pairing_clouds`` the first pairing of each cloud.
* Images are numbered ``F*first[b] + f*K_b + k`` (``first[b]`` = cameras of the samples
  before ``b``; ``(b*F + f)*K + k`` when every sample has ``K``); ``superpixels`` is
  ``[I, H, W]`` flattened, ids of frame ``(b, f)`` are ``0..num_superpixels[b][f]``
  shared by its ``K_b`` images.
  Some ids are absent from the images, some have no pairings (on purpose).
* Pairings of frame cloud ``(b, f)`` use images of frame ``(b, f)``; pairings of the
  dense cloud of ``b`` use the images of its key frame ``(b, 1)``.

Losses (``tau`` = 0.07, weights ``sc`` 1.0, ``tc`` 0.5, ``d2s`` 0.25):

* ``q[b,f,s]`` = mean of the pixel features of all pixels (of the K_b images of frame
  ``(b,f)``) with id ``s``; ``k[cloud,s]`` = mean over the pairings of the cloud with
  superpixel ``s`` of the paired point's feature (each pairing counts once). No
  re-normalisation after pooling.
* ``InfoNCE(a, b)`` = mean_i CE(a @ b^T / tau, i) over the M kept rows; 0 when M = 0.
* ``L_sc[f]`` = InfoNCE(k[(.,f)], q[.,f]) over slots ``(b, s)`` (b major), ``s < n[b][f]``,
  ``cpt > 0`` and ``cpx > 0``; ``L_sc`` = mean over frames.
* ``L_tc`` = mean over ``f in {0, 2}`` of InfoNCE(k[(.,1)], k[(.,f)]) over slots
  ``s < min(n[b][1], n[b][f])`` with ``cpt > 0`` in both frame clouds.
* ``L_d2s`` over slots ``s < n[b][1]`` with ``cpt > 0`` in the key frame cloud and in the
  dense cloud: cosine form mean(1 - cos(k_key, k_dense)); InfoNCE form
  InfoNCE(k_dense, k_key).
* ``total_cosine`` / ``total_infonce`` = w_sc L_sc + w_tc L_tc + w_d2s L_d2s (the form).

Inputs are generated in float32 and written as the shortest decimal that parses back to
the same float32 (parse them as f32). Everything is then computed in float64 from those
exact float32 values; expected values are float64 ``repr``. Gradients are those of the
totals with respect to ``point_features`` ([N, D]) and ``pixel_features`` ([I, D, H, W]),
with the stored (already normalised) features as autograd leaves.

Two implementations are run (per-slot Python loops, and one-hot pooling matrices with
``log_softmax``) and must agree to 1e-10 before anything is written.
"""

from __future__ import annotations

import json
import os
import sys
from typing import Any, cast

import numpy as np
import torch

SEED = 20240611
MIXED = "--mixed" in sys.argv[1:]
B, F = 2, 3
# Cameras of each sample: one rig of two cameras, or two rigs (three cameras, one).
CAMERAS = [3, 1] if MIXED else [2, 2]
FIRST = [sum(CAMERAS[:b]) for b in range(B + 1)]
C = F + 1
H, W = 6, 8
D = 8
TAU = 0.07
KEY = 1
WEIGHTS = {"sc": 1.0, "tc": 0.5, "d2s": 0.25}
OUT = os.path.join(os.path.dirname(os.path.abspath(__file__)), "..", "tests", "fixtures",
                   "losses_mixed.json" if MIXED else "losses.json")


def image(b: int, f: int, k: int) -> int:
    """The number of image ``k`` of frame ``f`` of sample ``b``."""
    return F * FIRST[b] + f * CAMERAS[b] + k


# ---------------------------------------------------------------------------------------
# Inputs
# ---------------------------------------------------------------------------------------

def make_inputs() -> dict:
    rng = np.random.default_rng(SEED)
    n_img = F * FIRST[B]
    # Ids per frame; the key frame has fewer ids than the others in sample 0 and more in
    # sample 1, so that s < min(n[b][1], n[b][f]) bounds L_tc from either side.
    num_sp = [[7, 5, 6], [6, 7, 5]]
    superpixels = np.zeros((n_img, H, W), dtype=np.int64)
    absent = {}  # (b, f) -> ids absent from every image of the frame
    for b in range(B):
        for f in range(F):
            n = num_sp[b][f]
            # One id (two in the key frame of sample 1) never drawn in the images.
            gone = {int(rng.integers(0, n))}
            if (b, f) == (1, 1):
                gone.add(n - 1)
            absent[(b, f)] = gone
            present = [s for s in range(n) if s not in gone]
            for k in range(CAMERAS[b]):
                img = image(b, f, k)
                # Blocky maps: superpixels look like patches, plus a few random pixels.
                blocks = rng.choice(present, size=(3, 4))
                sp = np.kron(blocks, np.ones((2, 2), dtype=np.int64))
                noise = rng.random((H, W)) < 0.15
                sp[noise] = rng.choice(present, size=int(noise.sum()))
                superpixels[img] = sp
            # Every id not declared absent appears at least once in the frame.
            for s in present:
                if not any((superpixels[image(b, f, k)] == s).any()
                           for k in range(CAMERAS[b])):
                    img = image(b, f, int(rng.integers(0, CAMERAS[b])))
                    superpixels[img, int(rng.integers(0, H)), int(rng.integers(0, W))] = s
    # The ids really absent (the fix-up above may have overwritten a last pixel of an id).
    for b in range(B):
        for f in range(F):
            imgs = superpixels[image(b, f, 0):image(b, f, 0) + CAMERAS[b]]
            absent[(b, f)] = {s for s in range(num_sp[b][f]) if not (imgs == s).any()}

    counts = rng.integers(20, 31, size=B * C)
    point_clouds = np.concatenate([[0], np.cumsum(counts)]).astype(np.int64)
    n_points = int(point_clouds[-1])

    pairing_point: list[int] = []
    pairing_image: list[int] = []
    pairing_pixel: list[tuple[int, int]] = []
    pairing_sp: list[int] = []
    pairing_clouds = [0]
    for b in range(B):
        for c in range(C):
            cloud = b * C + c
            f = c if c < F else KEY
            n = num_sp[b][f]
            present = [s for s in range(n) if s not in absent[(b, f)]]
            # One id of the images with no pairing in this cloud, on purpose. The dense
            # cloud skips the key frame's last id: with the key frame cloud's own skipped
            # id, L_d2s drops ids from either side.
            skip = {int(rng.choice(present))}
            if c == F:
                skip = {present[-1]}
            first = image(b, f, 0)
            want = int(rng.integers(30, 46))
            lo, hi = int(point_clouds[cloud]), int(point_clouds[cloud + 1])
            while len(pairing_point) - pairing_clouds[-1] < want:
                k = int(rng.integers(0, CAMERAS[b]))
                r, col = int(rng.integers(0, H)), int(rng.integers(0, W))
                s = int(superpixels[first + k, r, col])
                if s in skip:
                    continue
                pairing_point.append(int(rng.integers(lo, hi)))
                pairing_image.append(first + k)
                pairing_pixel.append((r, col))
                pairing_sp.append(s)
            pairing_clouds.append(len(pairing_point))

    point_features = rng.standard_normal((n_points, D)).astype(np.float32)
    point_features /= np.linalg.norm(point_features, axis=1, keepdims=True).astype(np.float32)
    point_features = point_features.astype(np.float32)
    pixel_features = rng.standard_normal((n_img, D, H, W)).astype(np.float32)
    pixel_features /= np.linalg.norm(pixel_features, axis=1, keepdims=True).astype(np.float32)
    pixel_features = pixel_features.astype(np.float32)

    return {
        "num_superpixels": num_sp,
        "superpixels": superpixels,
        "point_features": point_features,
        "point_clouds": point_clouds,
        "pairing_point": np.array(pairing_point, dtype=np.int64),
        "pairing_image": np.array(pairing_image, dtype=np.int64),
        "pairing_pixel": np.array(pairing_pixel, dtype=np.int64).reshape(-1, 2),
        "pairing_superpixel": np.array(pairing_sp, dtype=np.int64),
        "pairing_clouds": np.array(pairing_clouds, dtype=np.int64),
        "pixel_features": pixel_features,
    }


# ---------------------------------------------------------------------------------------
# Implementation 1: loops, one slot at a time
# ---------------------------------------------------------------------------------------

def info_nce_loop(a: list[torch.Tensor], b: list[torch.Tensor]) -> torch.Tensor:
    """mean_i -log softmax_j(a_i . b_j / tau)[i], written with explicit sums."""
    m = len(a)
    if m == 0:
        return torch.zeros((), dtype=torch.float64)
    total = torch.zeros((), dtype=torch.float64)
    for i in range(m):
        logits = [torch.dot(a[i], b[j]) / TAU for j in range(m)]
        top = max(float(x.detach()) for x in logits)
        # m > 0: the sum is of tensors, never the empty sum's 0
        lse = top + torch.log(cast(torch.Tensor, sum(torch.exp(x - top) for x in logits)))
        total = total + (lse - logits[i])
    return total / m


def losses_loop(inp: dict, pf: torch.Tensor, xf: torch.Tensor) -> dict:
    """pf: point features [N, D]; xf: pixel features [I, D, H, W] (float64 leaves)."""
    n = inp["num_superpixels"]
    sp = inp["superpixels"]
    pc = inp["pairing_clouds"]

    def q(b, f, s):
        acc, cnt = torch.zeros(D, dtype=torch.float64), 0
        for k in range(CAMERAS[b]):
            img = image(b, f, k)
            for r in range(H):
                for c in range(W):
                    if sp[img, r, c] == s:
                        acc = acc + xf[img, :, r, c]
                        cnt += 1
        return (acc / cnt if cnt else acc), cnt

    def kp(cloud, s):
        acc, cnt = torch.zeros(D, dtype=torch.float64), 0
        for p in range(int(pc[cloud]), int(pc[cloud + 1])):
            if inp["pairing_superpixel"][p] == s:
                acc = acc + pf[int(inp["pairing_point"][p])]
                cnt += 1
        return (acc / cnt if cnt else acc), cnt

    out: dict[str, Any] = {"l_sc_frames": [], "slots": {"sc": [], "tc": [], "d2s": 0}, "l_tc_terms": []}
    for f in range(F):
        a, bb = [], []
        for b in range(B):
            for s in range(n[b][f]):
                kv, cpt = kp(b * C + f, s)
                qv, cpx = q(b, f, s)
                if cpt > 0 and cpx > 0:
                    a.append(kv)
                    bb.append(qv)
        out["l_sc_frames"].append(info_nce_loop(a, bb))
        out["slots"]["sc"].append(len(a))
    out["l_sc"] = sum(out["l_sc_frames"]) / F

    for f in (0, 2):
        a, bb = [], []
        for b in range(B):
            for s in range(min(n[b][KEY], n[b][f])):
                kt, ct = kp(b * C + KEY, s)
                ko, co = kp(b * C + f, s)
                if ct > 0 and co > 0:
                    a.append(kt)
                    bb.append(ko)
        out["l_tc_terms"].append(info_nce_loop(a, bb))
        out["slots"]["tc"].append(len(a))
    out["l_tc"] = sum(out["l_tc_terms"]) / 2

    key, dense = [], []
    for b in range(B):
        for s in range(n[b][KEY]):
            kk, ck = kp(b * C + KEY, s)
            kd, cd = kp(b * C + F, s)
            if ck > 0 and cd > 0:
                key.append(kk)
                dense.append(kd)
    out["slots"]["d2s"] = len(key)
    if key:
        cos = [torch.dot(x, y) / (torch.sqrt(torch.dot(x, x)) * torch.sqrt(torch.dot(y, y)))
               for x, y in zip(key, dense, strict=False)]
        out["l_d2s_cosine"] = sum(1 - c for c in cos) / len(cos)
    else:
        out["l_d2s_cosine"] = torch.zeros((), dtype=torch.float64)
    out["l_d2s_infonce"] = info_nce_loop(dense, key)
    base = WEIGHTS["sc"] * out["l_sc"] + WEIGHTS["tc"] * out["l_tc"]
    out["total_cosine"] = base + WEIGHTS["d2s"] * out["l_d2s_cosine"]
    out["total_infonce"] = base + WEIGHTS["d2s"] * out["l_d2s_infonce"]
    return out


# ---------------------------------------------------------------------------------------
# Implementation 2: one-hot pooling matrices and log_softmax
# ---------------------------------------------------------------------------------------

def info_nce_mat(a: torch.Tensor, b: torch.Tensor) -> torch.Tensor:
    if a.shape[0] == 0:
        return torch.zeros((), dtype=torch.float64)
    logp = torch.log_softmax(a @ b.T / TAU, dim=1)
    return -torch.diagonal(logp).mean()


def losses_mat(inp: dict, pf: torch.Tensor, xf: torch.Tensor) -> dict:
    n = inp["num_superpixels"]
    n_img = F * FIRST[B]
    smax = max(max(r) for r in n)
    # Superpixel slot of frame (b, f), id s: (b*F + f)*smax + s. Pixel j = (img, r, c).
    sp = torch.as_tensor(inp["superpixels"]).reshape(n_img, H * W)
    img_frame = torch.tensor([b * F + f for b in range(B) for f in range(F)
                              for _ in range(CAMERAS[b])])
    slot_px = (img_frame[:, None] * smax + sp).reshape(-1)
    onehot_px = torch.zeros(B * F * smax, n_img * H * W, dtype=torch.float64)
    onehot_px[slot_px, torch.arange(n_img * H * W)] = 1.0
    cpx = onehot_px.sum(1)
    pix = xf.permute(0, 2, 3, 1).reshape(n_img * H * W, D)
    q = (onehot_px @ pix) / cpx.clamp(min=1)[:, None]
    q = q.reshape(B, F, smax, D)
    cpx = cpx.reshape(B, F, smax)

    # Superpoint slot of cloud g, id s: g*smax + s.
    pc = torch.as_tensor(inp["pairing_clouds"])
    P = int(pc[-1])
    cloud_of = torch.bucketize(torch.arange(P), pc[1:], right=True)
    slot_pt = cloud_of * smax + torch.as_tensor(inp["pairing_superpixel"])
    onehot_pt = torch.zeros(B * C * smax, P, dtype=torch.float64)
    onehot_pt[slot_pt, torch.arange(P)] = 1.0
    gather = torch.zeros(P, pf.shape[0], dtype=torch.float64)
    gather[torch.arange(P), torch.as_tensor(inp["pairing_point"])] = 1.0
    cpt = onehot_pt.sum(1)
    kf = (onehot_pt @ gather @ pf) / cpt.clamp(min=1)[:, None]
    kf = kf.reshape(B, C, smax, D)
    cpt = cpt.reshape(B, C, smax)

    def valid(b, limit):
        return torch.arange(smax) < limit

    out: dict[str, Any] = {"l_sc_frames": [], "l_tc_terms": []}
    for f in range(F):
        rows_a, rows_b = [], []
        for b in range(B):
            m = valid(b, n[b][f]) & (cpt[b, f] > 0) & (cpx[b, f] > 0)
            rows_a.append(kf[b, f][m])
            rows_b.append(q[b, f][m])
        out["l_sc_frames"].append(info_nce_mat(torch.cat(rows_a), torch.cat(rows_b)))
    out["l_sc"] = torch.stack(out["l_sc_frames"]).mean()
    for f in (0, 2):
        rows_a, rows_b = [], []
        for b in range(B):
            m = valid(b, min(n[b][KEY], n[b][f])) & (cpt[b, KEY] > 0) & (cpt[b, f] > 0)
            rows_a.append(kf[b, KEY][m])
            rows_b.append(kf[b, f][m])
        out["l_tc_terms"].append(info_nce_mat(torch.cat(rows_a), torch.cat(rows_b)))
    out["l_tc"] = torch.stack(out["l_tc_terms"]).mean()
    ka_rows, kd_rows = [], []
    for b in range(B):
        m = valid(b, n[b][KEY]) & (cpt[b, KEY] > 0) & (cpt[b, F] > 0)
        ka_rows.append(kf[b, KEY][m])
        kd_rows.append(kf[b, F][m])
    ka, kd = torch.cat(ka_rows), torch.cat(kd_rows)
    if ka.shape[0]:
        out["l_d2s_cosine"] = (1 - torch.nn.functional.cosine_similarity(ka, kd, dim=1, eps=0.0)).mean()
    else:
        out["l_d2s_cosine"] = torch.zeros((), dtype=torch.float64)
    out["l_d2s_infonce"] = info_nce_mat(kd, ka)
    base = WEIGHTS["sc"] * out["l_sc"] + WEIGHTS["tc"] * out["l_tc"]
    out["total_cosine"] = base + WEIGHTS["d2s"] * out["l_d2s_cosine"]
    out["total_infonce"] = base + WEIGHTS["d2s"] * out["l_d2s_infonce"]
    return out


# ---------------------------------------------------------------------------------------

def evaluate(fn, inp: dict) -> dict:
    """Losses (floats) and gradients of both totals (float64 numpy arrays)."""
    res = {}
    for form in ("infonce", "cosine"):
        pf = torch.tensor(inp["point_features"], dtype=torch.float64, requires_grad=True)
        xf = torch.tensor(inp["pixel_features"], dtype=torch.float64, requires_grad=True)
        out = fn(inp, pf, xf)
        out[f"total_{form}"].backward()
        assert pf.grad is not None and xf.grad is not None
        res[f"grad_point_features_{form}"] = pf.grad.numpy().reshape(-1).copy()
        res[f"grad_pixel_features_{form}"] = xf.grad.numpy().reshape(-1).copy()
        for key in ("l_sc", "l_tc", "l_d2s_cosine", "l_d2s_infonce", "total_cosine",
                    "total_infonce"):
            res[key] = float(out[key].detach())
        res["l_sc_frames"] = [float(x.detach()) for x in out["l_sc_frames"]]
        res["l_tc_terms"] = [float(x.detach()) for x in out["l_tc_terms"]]
        if "slots" in out:
            res["slots"] = out["slots"]
    return res


def f32(x) -> float:
    """The shortest decimal that parses back to the same float32, as a Python float
    (whose repr, used by json, is that same shortest decimal)."""
    return float(str(np.float32(x)))


def main() -> None:
    torch.manual_seed(SEED)
    inp = make_inputs()
    ref = evaluate(losses_loop, inp)
    alt = evaluate(losses_mat, inp)
    for key, want in ref.items():
        if key == "slots":
            continue
        got = alt[key]
        diff = float(np.max(np.abs(np.asarray(want) - np.asarray(got))))
        assert diff < 1e-10, f"{key}: implementations differ by {diff}"
    # The slot filters must really filter something, and no term may be empty.
    s = ref["slots"]
    assert all(x > 0 for x in s["sc"] + s["tc"]) and s["d2s"] > 0, s
    total_ids = [sum(inp["num_superpixels"][b][f] for b in range(B)) for f in range(F)]
    assert any(a < t for a, t in zip(s["sc"], total_ids, strict=False)), (s, total_ids)
    # Pairings must agree with the superpixel maps.
    pp = inp["pairing_pixel"]
    assert (inp["superpixels"][inp["pairing_image"], pp[:, 0], pp[:, 1]]
            == inp["pairing_superpixel"]).all()
    grads_px = ref["grad_pixel_features_infonce"]
    assert (grads_px == 0).any() and (grads_px != 0).any()

    cameras = CAMERAS if MIXED else CAMERAS[0]
    config = {"batch": B, "frames": F, "cameras": cameras, "clouds_per_sample": C, "height": H,
              "width": W, "dim": D, "temperature": TAU, "key_frame": KEY,
              "weights": dict(WEIGHTS)}
    expected = {
        "l_sc": ref["l_sc"], "l_sc_frames": ref["l_sc_frames"],
        "l_tc": ref["l_tc"], "l_tc_terms": ref["l_tc_terms"],
        "l_d2s_cosine": ref["l_d2s_cosine"], "l_d2s_infonce": ref["l_d2s_infonce"],
        "total_cosine": ref["total_cosine"], "total_infonce": ref["total_infonce"],
        "grad_point_features_infonce": [float(x) for x in ref["grad_point_features_infonce"]],
        "grad_pixel_features_infonce": [float(x) for x in ref["grad_pixel_features_infonce"]],
        "grad_point_features_cosine": [float(x) for x in ref["grad_point_features_cosine"]],
        "grad_pixel_features_cosine": [float(x) for x in ref["grad_pixel_features_cosine"]],
        "slots": ref["slots"],
    }
    doc = {
        "config": config,
        "num_superpixels": inp["num_superpixels"],
        "superpixels": [int(x) for x in inp["superpixels"].reshape(-1)],
        "point_features": [f32(x) for x in inp["point_features"].reshape(-1)],
        "num_points": int(inp["point_features"].shape[0]),
        "point_clouds": [int(x) for x in inp["point_clouds"]],
        "pairing_point": [int(x) for x in inp["pairing_point"]],
        "pairing_image": [int(x) for x in inp["pairing_image"]],
        "pairing_pixel": [int(x) for x in inp["pairing_pixel"].reshape(-1)],
        "pairing_superpixel": [int(x) for x in inp["pairing_superpixel"]],
        "pairing_clouds": [int(x) for x in inp["pairing_clouds"]],
        "pixel_features": [f32(x) for x in inp["pixel_features"].reshape(-1)],
        "expected": expected,
    }
    text = json.dumps(doc, separators=(",", ":")) + "\n"
    # The written float32 inputs parse back to exactly the values the losses used.
    back = json.loads(text)
    assert (np.array(back["point_features"], dtype=np.float32).reshape(inp["point_features"].shape)
            == inp["point_features"]).all()
    assert (np.array(back["pixel_features"], dtype=np.float32).reshape(inp["pixel_features"].shape)
            == inp["pixel_features"]).all()
    assert back["expected"]["total_infonce"] == ref["total_infonce"]
    os.makedirs(os.path.dirname(OUT), exist_ok=True)
    with open(OUT, "w") as f:
        f.write(text)
    print(f"wrote {os.path.normpath(OUT)} ({len(text)} bytes): N={doc['num_points']} "
          f"P={len(doc['pairing_point'])} slots={ref['slots']}")
    for key in ("l_sc", "l_tc", "l_d2s_cosine", "l_d2s_infonce", "total_cosine", "total_infonce"):
        print(f"  {key} = {ref[key]!r}")


if __name__ == "__main__":
    main()
