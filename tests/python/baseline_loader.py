#!/usr/bin/env python3
"""The loader superflow replaces, for comparison: a numpy + Pillow re-implementation of
the official SuperFlow per-sample loading (as its PyTorch dataset does it, on files), timed
on the same drive and recipe as the speed bench.

    python3 tests/python/baseline_loader.py DRIVE.mcap [--samples 24] [--out DIR]

First (not timed) the drive and its class maps (``/<camera>/superpixels``, in the drive or
in its ``<drive>.superpixels.mcap`` sidecar) are unpacked into
files the way nuScenes ships them (``DIR``, by default beside the drive): one float32
``x y z intensity`` file per sweep, the camera JPEGs and class-map PNGs as they are, and a
JSON index of stamps, poses (map from sensor, from the drive's transforms) and camera
intrinsics. Then each sample is built from those files as the official loader builds it:
the keyframe and the keyframes 0.5 s before and after (every 10th sweep at 20 Hz), the
keyframe's cloud densified with its 2 previous sweeps moved into its frame, 3 of the
cameras at random for the whole sample, each image decoded with Pillow (libjpeg-turbo),
resized bilinearly to 448x224 and flipped with p = 0.5, its class map resized (nearest)
and flipped with it, the clouds projected into the images (depth > 1 m, inside the image)
with the superpixel id of each pairing, each cloud augmented (flips, rotation about z,
scale) and voxelized in cylindrical cells (0.1 m, 1 degree, 0.1 m) with ``np.unique``.
No sparse-convolution maps: the official loader leaves them to torchsparse on the GPU.

Reading files instead of MCAP spares this loader the chunks' zstd decompression that
superflow's samples pay for; the comparison leans its way. One process, one thread
(pin it: ``taskset -c 1``); prints ms per sample per stage, medians over the samples.
"""

from __future__ import annotations

import argparse
import json
import sys
import time
from pathlib import Path

import numpy as np
from PIL import Image

sys.path.insert(0, str(Path(__file__).resolve().parent))
from check_drives import FOXGLOVE_NUMERIC, Drive, calibration_of, frame_of, invert, stamp_of

OUT_W, OUT_H = 448, 224
KEYFRAME_INTERVAL_S = 0.5
DENSE_EXTRA = 2
CAMERAS_PER_SAMPLE = 3
MIN_DEPTH_M = 1.0
VOXEL = (0.1, 1.0, 0.1)  # rho m, phi degrees, z m


def unpack(drive_path: Path, out: Path) -> dict:
    """Writes the drive's sweeps, images and class maps as files; returns the index."""
    index_path = out / "index.json"
    if index_path.exists():
        return json.loads(index_path.read_text())
    out.mkdir(parents=True, exist_ok=True)
    drive = Drive(drive_path)
    tf = drive.transforms()
    topics = {t: s for t, (s, _, _) in drive.channels.items()}
    lidar = next((t for t, s in topics.items() if s == "foxglove.PointCloud"), None)
    if lidar is None:
        raise SystemExit(f"{drive_path}: no foxglove.PointCloud channel (this loader reads the nuscenes2mcap layout)")
    sweeps = []
    for i, msg in enumerate(drive.messages[lidar]):
        stride = int(msg.point_stride)
        fields = {f.name: (int(f.offset), FOXGLOVE_NUMERIC[int(f.type)]) for f in msg.fields}
        names = ["x", "y", "z", "intensity"]
        dtype = np.dtype({"names": names, "formats": [fields[n][1] for n in names],
                          "offsets": [fields[n][0] for n in names], "itemsize": stride})
        rec = np.frombuffer(bytes(msg.data), dtype=dtype)
        points = np.stack([rec[n].astype(np.float32) for n in names], axis=1)
        name = f"sweep_{i:05d}.bin"
        points.tofile(out / name)
        frame = frame_of(msg)
        root = tf.root(frame)
        stamp = stamp_of(msg)
        sweeps.append({"file": name, "stamp": stamp, "map_from_lidar": tf.lookup(root, frame, stamp).tolist()})
    sidecar = drive_path.with_suffix(".superpixels.mcap")
    maps = Drive(sidecar) if sidecar.exists() else None
    cameras = {}
    for topic, schema in topics.items():
        if schema != "foxglove.CompressedImage":
            continue
        name = topic.strip("/").split("/")[0]
        info = next(t for t in topics if t.startswith(f"/{name}/") and topics[t] == "foxglove.CameraCalibration")
        w, h, k, _, _ = calibration_of(drive.messages[info][0])
        # Class maps: in the sidecar, or in the drive itself.
        map_topic = f"/{name}/superpixels"
        source = maps if maps is not None and map_topic in maps.messages else drive
        map_by_stamp = {stamp_of(m): m for m in source.messages.get(map_topic, [])}
        images = []
        for i, msg in enumerate(drive.messages[topic]):
            stamp, frame = stamp_of(msg), frame_of(msg)
            root = tf.root(frame)
            jpg = f"{name}_{i:05d}.jpg"
            (out / jpg).write_bytes(bytes(msg.data))
            png = None
            if stamp in map_by_stamp:
                png = f"{name}_{i:05d}.png"
                label = map_by_stamp[stamp]
                if hasattr(label, "encoding"):  # foxglove.RawImage, mono8: stored as PNG
                    if label.encoding != "mono8":
                        raise SystemExit(f"{map_topic}: class maps in {label.encoding!r}, expected mono8")
                    grey = Image.frombuffer("L", (label.width, label.height), bytes(label.data),
                                            "raw", "L", label.step, 1)
                    grey.save(out / png)
                else:
                    (out / png).write_bytes(bytes(label.data))
            images.append({"jpg": jpg, "png": png, "stamp": stamp,
                           "map_from_cam": tf.lookup(root, frame, stamp).tolist()})
        cameras[name] = {"width": w, "height": h, "K": k.tolist(), "images": images}
    index = {"sweeps": sweeps, "cameras": cameras}
    index_path.write_text(json.dumps(index))
    return index


class Timer:
    """Seconds per stage of one sample."""

    def __init__(self) -> None:
        self.stages: dict[str, float] = {}
        self.at = time.perf_counter()

    def lap(self, stage: str) -> None:
        now = time.perf_counter()
        self.stages[stage] = self.stages.get(stage, 0.0) + now - self.at
        self.at = now


def load_image(root: Path, cam: dict, image: dict, flip: bool, timer: Timer) -> tuple[np.ndarray, np.ndarray]:
    """The resized (and maybe flipped) RGB image and class map of one camera image."""
    rgb = Image.open(root / image["jpg"]).convert("RGB")
    labels = Image.open(root / image["png"]) if image["png"] else None
    if labels is not None:
        labels.load()
    timer.lap("decode")
    rgb = np.asarray(rgb.resize((OUT_W, OUT_H), Image.BILINEAR))
    if flip:
        rgb = rgb[:, ::-1]
    timer.lap("images")
    if labels is None:
        ids = np.zeros((OUT_H, OUT_W), np.uint8)
    else:
        ids = np.asarray(labels.resize((OUT_W, OUT_H), Image.NEAREST))
    if flip:
        ids = ids[:, ::-1]
    timer.lap("superpixels")
    return rgb, ids


def pair(points: np.ndarray, cam: dict, cam_from_lidar: np.ndarray, flip: bool, ids: np.ndarray) -> np.ndarray:
    """(point, row, col, superpixel) of the points the camera sees."""
    p = points[:, :3].astype(np.float64) @ cam_from_lidar[:3, :3].T + cam_from_lidar[:3, 3]
    front = np.nonzero(p[:, 2] > MIN_DEPTH_M)[0]
    uvw = p[front] @ np.asarray(cam["K"]).T
    u, v = uvw[:, 0] / uvw[:, 2], uvw[:, 1] / uvw[:, 2]
    inside = (u > 0) & (u < cam["width"] - 1) & (v > 0) & (v < cam["height"] - 1)
    u, v, index = u[inside], v[inside], front[inside]
    col = np.minimum((u * OUT_W / cam["width"]).astype(np.int64), OUT_W - 1)
    row = np.minimum((v * OUT_H / cam["height"]).astype(np.int64), OUT_H - 1)
    if flip:
        col = OUT_W - 1 - col
    return np.stack([index, row, col, ids[row, col]], axis=1)


def augment_and_voxelize(points: np.ndarray, rng: np.random.Generator) -> tuple:
    """Flips, rotation about z, scale; cylindrical cells, their first points, each point's cell."""
    xyz = points[:, :3].astype(np.float64)
    if rng.random() < 0.5:
        xyz[:, 0] = -xyz[:, 0]
    if rng.random() < 0.5:
        xyz[:, 1] = -xyz[:, 1]
    yaw = rng.uniform(0.0, np.pi)
    c, s = np.cos(yaw), np.sin(yaw)
    xyz = xyz @ np.array([[c, -s, 0.0], [s, c, 0.0], [0.0, 0.0, 1.0]]).T
    xyz *= rng.uniform(0.95, 1.05)
    rho = np.hypot(xyz[:, 0], xyz[:, 1])
    phi = np.degrees(np.arctan2(xyz[:, 1], xyz[:, 0]))
    cells = np.floor(np.stack([rho / VOXEL[0], phi / VOXEL[1], xyz[:, 2] / VOXEL[2]], axis=1)).astype(np.int64)
    cells -= cells.min(axis=0)
    span = cells.max(axis=0) + 1
    keys = (cells[:, 0] * span[1] + cells[:, 1]) * span[2] + cells[:, 2]
    _, first, inverse = np.unique(keys, return_index=True, return_inverse=True)
    features = np.concatenate([xyz[first], points[first, 3:4]], axis=1).astype(np.float32)
    return cells[first], features, inverse


def keyframe_step(index: dict) -> int:
    """Sweeps per keyframe interval, from the sweeps' median period."""
    stamps = np.array([s["stamp"] for s in index["sweeps"]], dtype=np.int64)
    period = float(np.median(np.diff(stamps))) if len(stamps) > 1 else 1e9
    return max(1, round(KEYFRAME_INTERVAL_S * 1e9 / period))


def build_sample(root: Path, index: dict, step: int, key: int, rng: np.random.Generator) -> dict[str, float]:
    """One sample around sweep ``key`` (``step`` sweeps per keyframe interval); seconds per stage."""
    timer = Timer()
    sweeps = index["sweeps"]
    names = sorted(index["cameras"])
    chosen = rng.choice(len(names), min(CAMERAS_PER_SAMPLE, len(names)), replace=False)
    frames = [key - step, key, key + step]
    clouds = {s: np.fromfile(root / sweeps[s]["file"], dtype=np.float32).reshape(-1, 4)
              for s in frames + [key - d for d in range(1, DENSE_EXTRA + 1)]}
    timer.lap("decode")
    key_from_map = invert(np.asarray(sweeps[key]["map_from_lidar"]))
    layers = [clouds[key]]
    for d in range(1, DENSE_EXTRA + 1):
        m = key_from_map @ np.asarray(sweeps[key - d]["map_from_lidar"])
        earlier = clouds[key - d]
        moved = earlier[:, :3].astype(np.float64) @ m[:3, :3].T + m[:3, 3]
        layers.append(np.concatenate([moved.astype(np.float32), earlier[:, 3:4]], axis=1))
    dense = np.concatenate(layers)
    timer.lap("sweeps")
    pairings = []
    for s in frames:
        stamp = sweeps[s]["stamp"]
        for c in chosen:
            cam = index["cameras"][names[c]]
            image = cam["images"][int(np.argmin(np.abs(cam["stamps"] - stamp)))]
            flip = bool(rng.random() < 0.5)
            _, ids = load_image(root, cam, image, flip, timer)
            cam_from_lidar = invert(np.asarray(image["map_from_cam"])) @ np.asarray(sweeps[s]["map_from_lidar"])
            pairings.append(pair(clouds[s], cam, cam_from_lidar, flip, ids))
            if s == key:
                pairings.append(pair(dense, cam, cam_from_lidar, flip, ids))
            timer.lap("projection")
    for cloud in [clouds[s] for s in frames] + [dense]:
        augment_and_voxelize(cloud, rng)
    timer.lap("voxels")
    return timer.stages


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("drive", type=Path)
    parser.add_argument("--samples", type=int, default=24)
    parser.add_argument("--out", type=Path, default=None)
    args = parser.parse_args(argv)
    out = args.out or args.drive.with_name(args.drive.stem + ".files")
    index = unpack(args.drive, out)
    for cam in index["cameras"].values():  # looked up per image in every sample
        cam["stamps"] = np.array([im["stamp"] for im in cam["images"]], dtype=np.int64)
    n_sweeps = len(index["sweeps"])
    step = keyframe_step(index)
    first = max(step, DENSE_EXTRA)
    keys = list(range(first, n_sweeps - step, step))
    if not keys:
        raise SystemExit(f"{args.drive}: {n_sweeps} sweeps, too few for a keyframe with neighbours")
    rng = np.random.default_rng(0)
    for key in keys[:2]:  # warm-up: file cache, imports
        build_sample(out, index, step, key, rng)
    totals: list[float] = []
    stages: dict[str, list[float]] = {}
    for _ in range(args.samples):
        key = keys[int(rng.integers(len(keys)))]
        started = time.perf_counter()
        times = build_sample(out, index, step, key, rng)
        totals.append(time.perf_counter() - started)
        for name, seconds in times.items():
            stages.setdefault(name, []).append(seconds)
    order = ["decode", "sweeps", "images", "projection", "superpixels", "voxels"]
    print(f"numpy + Pillow loader, {args.samples} samples of {args.drive.name}, 1 thread: medians, ms per sample")
    print("| ms/sample | " + " | ".join(order) + " |")
    print("|---:|" + "---:|" * len(order))
    cells = [f"{1e3 * np.median(stages.get(name, [0.0])):.1f}" for name in order]
    print(f"| {1e3 * np.median(totals):.1f} | " + " | ".join(cells) + " |")
    return 0


if __name__ == "__main__":
    sys.exit(main())
