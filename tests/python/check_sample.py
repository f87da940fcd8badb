"""Independent checks of a sample written by `superflow-pipeline sample` (numpy + PIL).

Usage: python3 tests/python/check_sample.py DIR

Reads every array with numpy and checks it against sample.json and against facts
recomputed here: array shapes and counts, pairings inside the resized images, the
superpixel of each pairing equal to the id map at its (row, col), the resized (row, col)
recomputed from the raw (u, v), cylindrical voxel cells recomputed from the points (the
paper's 0.1 m / 1 deg / 0.1 m grid), the point->voxel map and representative features,
the dense cloud's per-sweep counts, and the overlay PNGs' sizes.
Prints one line per check and `N passed, M failed` last.
"""

import json
import sys
from itertools import pairwise
from pathlib import Path

import numpy as np
from PIL import Image

passed = 0
failed = 0


def check(name, ok, detail=""):
    global passed, failed
    if ok:
        passed += 1
        print(f"ok   {name}")
    else:
        failed += 1
        print(f"FAIL {name} {detail}")


def cells(points, grid):
    """Continuous cell coordinates (float64) of each point."""
    p = points[:, :3].astype(np.float64)
    x, y, z = p[:, 0], p[:, 1], p[:, 2]
    if grid["kind"] == "cylindrical":
        phi = np.degrees(np.arctan2(y, x))
        phi = np.where(phi >= 180.0, phi - 360.0, phi)
        return np.stack([np.hypot(x, y) / grid["rho_m"], phi / grid["phi_deg"], z / grid["z_m"]], axis=1)
    return p / np.asarray(grid["size_m"], dtype=np.float64)


def cells_agree(coords, continuous):
    """Cells equal floor(continuous), except within 1e-4 of a cell boundary, where the
    pipeline's f32 arithmetic may round to either side."""
    exact = coords == np.floor(continuous)
    near = np.abs(continuous - np.round(continuous)) < 1e-4
    return bool((exact | (near & (np.abs(coords - np.round(continuous)) <= 1))).all())


def check_cloud(d, prefix, info, config, images, superpixels):
    h, w = config["image_height"], config["image_width"]
    pts = np.load(d / f"{prefix}_points.npy")
    check(f"{prefix}: points shape", pts.shape == (info["points"], 4), pts.shape)
    check(f"{prefix}: points finite", bool(np.isfinite(pts).all()))
    point = np.load(d / f"{prefix}_pairing_point.npy")
    cam = np.load(d / f"{prefix}_pairing_camera.npy")
    uv = np.load(d / f"{prefix}_pairing_uv.npy")
    rc = np.load(d / f"{prefix}_pairing_rowcol.npy").astype(np.int64)
    depth = np.load(d / f"{prefix}_pairing_depth.npy")
    sp = np.load(d / f"{prefix}_pairing_superpixel.npy")
    n = info["pairings"]
    check(
        f"{prefix}: pairing shapes",
        point.shape == (n,) and cam.shape == (n,) and uv.shape == (n, 2) and rc.shape == (n, 2)
        and depth.shape == (n,) and sp.shape == (n,),
    )
    check(f"{prefix}: pairing dtypes", point.dtype == np.uint32 and cam.dtype == np.uint8
          and uv.dtype == np.float32 and sp.dtype == np.uint32)
    check(f"{prefix}: paired points exist", n == 0 or int(point.max()) < info["points"])
    check(f"{prefix}: depth > 1 m", bool((depth > 1.0).all()))
    check(f"{prefix}: (row, col) inside the resized image",
          bool(((rc[:, 0] >= 0) & (rc[:, 0] < h) & (rc[:, 1] >= 0) & (rc[:, 1] < w)).all()))
    # Recompute (row, col) from the raw (u, v) and the flips.
    ok = True
    for slot, meta in enumerate(images):
        sel = cam == slot
        wn, hn = meta["native_width"], meta["native_height"]
        col = np.clip(np.floor((uv[sel, 0].astype(np.float64) + 0.5) * w / wn), 0, w - 1)
        row = np.clip(np.floor((uv[sel, 1].astype(np.float64) + 0.5) * h / hn), 0, h - 1)
        if meta["flipped"]:
            col = w - 1 - col
        ok &= bool((row == rc[sel, 0]).all() and (col == rc[sel, 1]).all())
        ok &= bool(((uv[sel, 0] > 0) & (uv[sel, 0] < wn - 1) & (uv[sel, 1] > 0) & (uv[sel, 1] < hn - 1)).all())
    check(f"{prefix}: (row, col) recomputed from (u, v) and flips", ok)
    check(f"{prefix}: pairing superpixel = id map at (row, col)",
          bool((superpixels[cam, rc[:, 0], rc[:, 1]] == sp).all()))
    # Voxels, recomputed.
    coords = np.load(d / f"{prefix}_voxel_coords.npy").astype(np.int64)
    feats = np.load(d / f"{prefix}_voxel_features.npy")
    p2v = np.load(d / f"{prefix}_point_to_voxel.npy").astype(np.int64)
    check(f"{prefix}: voxel count", coords.shape == (info["voxels"], 3) and feats.shape == (info["voxels"], 4))
    check(f"{prefix}: voxels unique", len(np.unique(coords, axis=0)) == len(coords))
    check(f"{prefix}: point->voxel cells recomputed", cells_agree(coords[p2v], cells(pts, config["voxel"])))
    first = np.full(len(coords), -1, dtype=np.int64)
    seen = set()
    for i, v in enumerate(p2v):
        if v not in seen:
            seen.add(v)
            first[v] = i
    check(f"{prefix}: voxel features are each cell's first point", bool((feats == pts[first]).all()))
    return pts


def main():
    d = Path(sys.argv[1])
    s = json.loads((d / "sample.json").read_text())
    check("format", s["format"] == "superflow.sample/1")
    config = s["config"]
    h, w = config["image_height"], config["image_width"]
    k = len(s["cameras"])
    for f, frame in enumerate(s["frames"]):
        imgs = np.load(d / f"frame{f}_images.npy")
        sps = np.load(d / f"frame{f}_superpixels.npy")
        check(f"frame{f}: images {k}x{h}x{w}x3 u8", imgs.shape == (k, h, w, 3) and imgs.dtype == np.uint8)
        check(f"frame{f}: superpixels {k}x{h}x{w}", sps.shape == (k, h, w))
        check(f"frame{f}: superpixel ids < {frame['num_superpixels']}", int(sps.max()) < frame["num_superpixels"])
        check(f"frame{f}: images are not blank", float(imgs.std()) > 10.0)
        check_cloud(d, f"frame{f}", frame, config, frame["images"], sps)
        for slot, meta in enumerate(frame["images"]):
            for kind in ["depth", "superpixels"]:
                png = d / f"frame{f}_cam{slot}_{meta['camera']}_{kind}.png"
                check(f"{png.name} is {w}x{h}", Image.open(png).size == (w, h))
    key = s["key_frame"]
    key_sps = np.load(d / f"frame{key}_superpixels.npy")
    dense = s["dense"]
    pts = check_cloud(d, "dense", dense, config, s["frames"][key]["images"], key_sps)
    src = np.load(d / "dense_source_sweep.npy")
    counts = [int((src == j).sum()) for j in range(len(dense["stamps_nanos"]))]
    check("dense: points per source sweep", counts == dense["points_per_sweep"], counts)
    check("dense: keyframe points first", bool((src[: counts[0]] == 0).all()))
    if not config["augment"]["enabled"]:
        key_pts = np.load(d / f"frame{key}_points.npy")
        check("dense: keyframe points equal the frame's points", bool((pts[: counts[0]] == key_pts).all()))
    stamps = dense["stamps_nanos"]
    check("dense: earlier sweeps are earlier", all(a > b for a, b in pairwise(stamps)))
    print(f"{passed} passed, {failed} failed")
    return 0 if failed == 0 else 1


if __name__ == "__main__":
    sys.exit(main())
