#!/usr/bin/env python3
"""Independent reference check of the superflow sample drives.

Usage::

    pip install -r tests/python/requirements.txt
    python3 tests/python/check_drives.py recordings/drives

For every ``<name>.truth.json`` in the directory, the drive ``<name>.mcap`` next to it is
read with the ``mcap`` package's readers and its ROS 2 (CDR) and protobuf decoder
factories, and compared with the ground truth using numpy only (no superflow code):

* **container** - MCAP header profile, chunk compression, the set of channels
  (topic, schema name, schema encoding, message encoding) and message counts per topic;
* **LiDAR** - per sweep message, in order: the sensor stamp (``timestamp`` of a
  ``foxglove.PointCloud``, ``header.stamp`` of a ``PointCloud2``, never ``log_time``), the
  frame, the point count (data length / point stride, and width x height), finite points;
* **cameras** - image stamps and frames; every calibration message's width, height, K,
  distortion model and D; the first JPEG of each camera decodes to width x height (needs
  pillow, skipped with a note otherwise); every superpixel image is mono8, width x height
  bytes, stamped like the images, with classes below ``len(truth.classes)``;
* **transforms** - a small transform buffer built here from ``/tf`` (and ``/tf_static``),
  interpolating stamped transforms linearly in translation and by slerp in rotation:
  ``map_from_ego`` at every ground-truth pose stamp (1 mm, 1e-5 rad), ``ego_from_lidar``
  and ``ego_from_camera`` (optical frame) within 1e-9;
* **landmarks** - every observation re-projected with calibration and transforms decoded
  from the MCAP (pinhole, plus the OpenCV Brown model for ``plumb_bob``): pixel within
  0.5 px, depth within 1 cm, and the ``visible`` flag consistent with the projection;
* **LiDAR vs camera** - the sweep nearest 1 s after the drive start is put in the map frame
  and projected into CAM_FRONT at the nearest image: points on ``driveable_surface`` pixels
  must lie on the ground plane z = 0 (within 0.15 m, >= 90 %) and points on ``manmade``
  pixels above it (z > 0.15 m, >= 80 %). Motion-compensated clouds use the pose at the
  sweep stamp; raw clouds (``motion_compensated: false``) are de-skewed point by point
  with their per-point ``time`` field.

Transforms map child-frame points into the parent frame. A transform published on
``/tf`` whose samples are all identical (the foxglove dialect republishes its extrinsics)
is treated as static; any other stamped transform is interpolated and never extrapolated.

Prints every failure, a summary line per drive and, as the very last line,
``N passed, M failed`` (counting checks). Exit code 0 only if nothing failed.
"""

from __future__ import annotations

import argparse
import io
import json
import math
import sys
from collections import defaultdict
from collections.abc import Callable
from pathlib import Path
from typing import Any

import numpy as np
from mcap.decoder import DecoderFactory
from mcap.reader import make_reader
from mcap_protobuf.decoder import DecoderFactory as ProtobufDecoderFactory
from mcap_ros2.decoder import DecoderFactory as Ros2DecoderFactory

try:  # optional: only the JPEG decode sub-check needs it
    from PIL import Image
except ImportError:  # pragma: no cover - depends on the environment
    Image = None

# Tolerances of the checks.
POSE_TRANSLATION_TOL_M = 1e-3
# Between odometry samples, interpolation cannot follow a turning vehicle exactly: the
# error at mid-interval is |yaw''| dt^2 / 8, which is 1.04e-5 rad for the ROS 2 drive's
# 50 Hz odom->base_link (its yaw changes by up to -8.3e-5 rad per step squared). So the
# interpolated poses get 2e-5 rad, and the poses at the sample stamps themselves must
# agree to SAMPLED_POSE_TOL.
POSE_ROTATION_TOL_RAD = 2e-5
SAMPLED_POSE_TOL = 1e-9
EXTRINSIC_TOL = 1e-9
CALIBRATION_TOL = 1e-9
PIXEL_TOL = 0.5
DEPTH_TOL_M = 0.01
GROUND_Z_TOL_M = 0.15
GROUND_MIN_FRACTION = 0.90
MANMADE_MIN_FRACTION = 0.80
CONSISTENCY_MIN_POINTS = 20
CONSISTENCY_OFFSET_NANOS = 1_000_000_000
CONSISTENCY_CAMERA = "CAM_FRONT"

# Element types of foxglove.PackedElementField.NumericType and of
# sensor_msgs/msg/PointField, as numpy little-endian dtypes.
FOXGLOVE_NUMERIC = {1: "u1", 2: "i1", 3: "<u2", 4: "<i2", 5: "<u4", 6: "<i4", 7: "<f4", 8: "<f8"}
ROS_POINT_FIELD = {1: "i1", 2: "u1", 3: "<i2", 4: "<u2", 5: "<i4", 6: "<u4", 7: "<f4", 8: "<f8"}

TRANSFORM_SCHEMAS = {"foxglove.FrameTransform", "foxglove.FrameTransforms", "tf2_msgs/msg/TFMessage"}
STATIC_TF_TOPIC = "/tf_static"


class JsonDecoderFactory(DecoderFactory):
    """Decodes ``json`` channels (the foxglove drive's ``/odom``) with the standard library."""

    def decoder_for(self, message_encoding: str, schema: Any) -> Callable[[bytes], Any] | None:
        if message_encoding == "json":
            return lambda data: json.loads(data)
        return None


# --------------------------------------------------------------------------- geometry


def quat_to_matrix(q_xyzw) -> np.ndarray:
    """Rotation matrix of a (normalised here) quaternion given as x, y, z, w."""
    x, y, z, w = np.asarray(q_xyzw, dtype=np.float64) / np.linalg.norm(q_xyzw)
    return np.array(
        [
            [1 - 2 * (y * y + z * z), 2 * (x * y - z * w), 2 * (x * z + y * w)],
            [2 * (x * y + z * w), 1 - 2 * (x * x + z * z), 2 * (y * z - x * w)],
            [2 * (x * z - y * w), 2 * (y * z + x * w), 1 - 2 * (x * x + y * y)],
        ]
    )


def make_transform(translation, rotation_xyzw) -> np.ndarray:
    """4x4 homogeneous transform parent_from_child."""
    m = np.eye(4)
    m[:3, :3] = quat_to_matrix(rotation_xyzw)
    m[:3, 3] = np.asarray(translation, dtype=np.float64)
    return m


def invert(m: np.ndarray) -> np.ndarray:
    """Inverse of a rigid 4x4 transform."""
    inv = np.eye(4)
    inv[:3, :3] = m[:3, :3].T
    inv[:3, 3] = -m[:3, :3].T @ m[:3, 3]
    return inv


def apply(m: np.ndarray, points: np.ndarray) -> np.ndarray:
    """Applies a 4x4 transform to an (N, 3) array of points."""
    return points @ m[:3, :3].T + m[:3, 3]


def slerp(q0: np.ndarray, q1: np.ndarray, a: float) -> np.ndarray:
    """Spherical linear interpolation of unit quaternions (x, y, z, w), shortest arc."""
    q0 = q0 / np.linalg.norm(q0)
    q1 = q1 / np.linalg.norm(q1)
    dot = float(np.dot(q0, q1))
    if dot < 0.0:
        q1, dot = -q1, -dot
    theta = math.atan2(float(np.linalg.norm(q1 - dot * q0)), dot)  # accurate for tiny angles too
    if theta < 1e-9:  # (nearly) equal: normalised lerp is exact to far below 1e-18 rad
        q = q0 + a * (q1 - q0)
        return q / np.linalg.norm(q)
    s = math.sin(theta)
    return (math.sin((1.0 - a) * theta) * q0 + math.sin(a * theta) * q1) / s


def rotation_angle_between(r_a: np.ndarray, r_b: np.ndarray) -> float:
    """Angle of r_a^T r_b in radians, accurate for tiny angles (chordal formula)."""
    chord = np.linalg.norm(r_a - r_b) / (2.0 * math.sqrt(2.0))
    return 2.0 * math.asin(min(chord, 1.0))


def project(points_cam: np.ndarray, k: np.ndarray, model: str, d: np.ndarray) -> np.ndarray:
    """Pixels (N, 2) of camera-frame points (N, 3) (Z > 0 assumed by the caller).

    Pinhole with skew ``u = fx x' + s y' + cx, v = fy y' + cy``; for ``plumb_bob`` the
    normalised coordinates go through the OpenCV Brown model (k1, k2, p1, p2, k3) first.
    """
    x = points_cam[:, 0] / points_cam[:, 2]
    y = points_cam[:, 1] / points_cam[:, 2]
    if model == "plumb_bob":
        k1, k2, p1, p2, k3 = (list(d) + [0.0] * 5)[:5]
        r2 = x * x + y * y
        radial = 1.0 + k1 * r2 + k2 * r2 * r2 + k3 * r2 * r2 * r2
        xd = x * radial + 2.0 * p1 * x * y + p2 * (r2 + 2.0 * x * x)
        yd = y * radial + p1 * (r2 + 2.0 * y * y) + 2.0 * p2 * x * y
    elif model in ("", "none") and not np.any(d):
        xd, yd = x, y
    else:
        raise ValueError(f"distortion model {model!r} with D={list(d)} is not supported")
    u = k[0, 0] * xd + k[0, 1] * yd + k[0, 2]
    v = k[1, 1] * yd + k[1, 2]
    return np.stack([u, v], axis=1)


# --------------------------------------------------------------------------- transforms


class TransformBuffer:
    """A minimal tf buffer: a tree of parent <- child edges, static or stamped."""

    def __init__(self) -> None:
        # child -> parent, and child -> list of (stamp, translation, quaternion xyzw)
        self.parent: dict[str, str] = {}
        self.samples: dict[str, list[tuple[int, np.ndarray, np.ndarray]]] = defaultdict(list)
        self.static: set[str] = set()

    def add(self, parent: str, child: str, stamp: int, translation, rotation_xyzw, static: bool) -> None:
        known = self.parent.setdefault(child, parent)
        if known != parent:
            raise ValueError(f"frame {child!r} has two parents: {known!r} and {parent!r}")
        t = np.asarray(translation, dtype=np.float64)
        q = np.asarray(rotation_xyzw, dtype=np.float64)
        if not (np.all(np.isfinite(t)) and np.all(np.isfinite(q)) and np.linalg.norm(q) > 0.5):
            raise ValueError(f"invalid transform {parent}->{child} at {stamp}: t={t} q={q}")
        self.samples[child].append((stamp, t, q))
        if static:
            self.static.add(child)

    def finalize(self) -> None:
        """Sorts samples by stamp; /tf edges whose samples never change become static."""
        for child, samples in self.samples.items():
            samples.sort(key=lambda s: s[0])
            stamps = [s[0] for s in samples]
            if len(set(stamps)) != len(stamps) and child not in self.static:
                raise ValueError(f"transform {self.parent[child]}->{child} has duplicate stamps")
            first = samples[0]
            if all(np.array_equal(s[1], first[1]) and np.array_equal(s[2], first[2]) for s in samples):
                self.static.add(child)
            elif child in self.static:
                raise ValueError(f"static transform {self.parent[child]}->{child} changes")

    def edge(self, child: str, stamp: int) -> np.ndarray:
        """parent_from_child at ``stamp`` (interpolated; no extrapolation)."""
        samples = self.samples[child]
        if child in self.static:
            _, t, q = samples[-1]
            return make_transform(t, q)
        stamps = [s[0] for s in samples]
        i = int(np.searchsorted(stamps, stamp, side="right")) - 1
        if i < 0 or (i == len(samples) - 1 and stamp != stamps[-1]):
            raise LookupError(
                f"{self.parent[child]}->{child} at {stamp} is outside its data "
                f"[{stamps[0]}, {stamps[-1]}] (no extrapolation)"
            )
        t0, p0, q0 = samples[i]
        if stamp == t0:
            return make_transform(p0, q0)
        t1, p1, q1 = samples[i + 1]
        a = (stamp - t0) / (t1 - t0)
        return make_transform(p0 + a * (p1 - p0), slerp(q0, q1, a))

    def is_sampled(self, target: str, source: str, stamp: int) -> bool:
        """Whether every stamped edge between the two frames has a sample at ``stamp``."""
        up_target = self._chain(target)
        edges = [f for f in self._chain(source) if f not in up_target]
        edges += [f for f in up_target if f not in self._chain(source)]
        return all(child in self.static or any(s[0] == stamp for s in self.samples[child])
                   for child in edges)

    def _chain(self, frame: str) -> list[str]:
        chain = [frame]
        while chain[-1] in self.parent:
            chain.append(self.parent[chain[-1]])
            if len(chain) > 64:
                raise ValueError(f"transform cycle through {frame!r}")
        return chain

    def root(self, frame: str) -> str:
        """The top of ``frame``'s tree (the fixed frame, e.g. ``map``)."""
        return self._chain(frame)[-1]

    def _ancestor_from(self, frame: str, ancestor: str, stamp: int) -> np.ndarray:
        m = np.eye(4)
        while frame != ancestor:
            m = self.edge(frame, stamp) @ m
            frame = self.parent[frame]
        return m

    def lookup(self, target: str, source: str, stamp: int) -> np.ndarray:
        """target_from_source at ``stamp``: maps source-frame points into ``target``."""
        up_source = self._chain(source)
        up_target = set(self._chain(target))
        common = next((f for f in up_source if f in up_target), None)
        if common is None:
            raise LookupError(f"frames {target!r} and {source!r} are not connected")
        return invert(self._ancestor_from(target, common, stamp)) @ self._ancestor_from(source, common, stamp)


# --------------------------------------------------------------------------- reading


def stamp_of(msg: Any) -> int:
    """Sensor stamp in nanoseconds: ROS ``header.stamp`` or foxglove ``timestamp``."""
    if hasattr(msg, "header"):
        s = msg.header.stamp
        return int(s.sec) * 1_000_000_000 + int(s.nanosec)
    s = msg.timestamp
    return int(s.seconds) * 1_000_000_000 + int(s.nanos)


def frame_of(msg: Any) -> str:
    return msg.header.frame_id if hasattr(msg, "header") else msg.frame_id


class Drive:
    """Every message of one MCAP file, decoded, grouped by topic in log-time order."""

    def __init__(self, path: Path) -> None:
        self.path = path
        self.messages: dict[str, list[Any]] = defaultdict(list)
        self.channels: dict[str, tuple[str, str, str]] = {}
        factories = [Ros2DecoderFactory(), ProtobufDecoderFactory(), JsonDecoderFactory()]
        with open(path, "rb") as f:
            reader = make_reader(f, decoder_factories=factories)
            self.header = reader.get_header()
            self.summary = reader.get_summary()
            for schema, channel, _message, decoded in reader.iter_decoded_messages(log_time_order=True):
                self.channels[channel.topic] = (schema.name, schema.encoding, channel.message_encoding)
                self.messages[channel.topic].append(decoded)
        if self.summary is not None:  # channels without messages exist only in the summary
            for channel in self.summary.channels.values():
                schema = self.summary.schemas.get(channel.schema_id)
                key = (schema.name if schema else "", schema.encoding if schema else "", channel.message_encoding)
                self.channels.setdefault(channel.topic, key)

    def transforms(self) -> TransformBuffer:
        buf = TransformBuffer()
        for topic, (schema_name, _, _) in self.channels.items():
            if schema_name not in TRANSFORM_SCHEMAS:
                continue
            static = topic == STATIC_TF_TOPIC
            for msg in self.messages[topic]:
                if hasattr(msg, "transforms") and schema_name == "tf2_msgs/msg/TFMessage":
                    for ts in msg.transforms:
                        tr, rot = ts.transform.translation, ts.transform.rotation
                        buf.add(ts.header.frame_id, ts.child_frame_id, stamp_of(ts),
                                (tr.x, tr.y, tr.z), (rot.x, rot.y, rot.z, rot.w), static)
                else:
                    for ft in getattr(msg, "transforms", None) or [msg]:
                        tr, rot = ft.translation, ft.rotation
                        buf.add(ft.parent_frame_id, ft.child_frame_id, stamp_of(ft),
                                (tr.x, tr.y, tr.z), (rot.x, rot.y, rot.z, rot.w), static)
        buf.finalize()
        return buf


def cloud_points(msg: Any) -> tuple[np.ndarray, np.ndarray | None, int]:
    """(points (N, 3) float64, per-point ``time`` or None, N) of a point cloud message.

    The count is the data length divided by the point stride; for ``PointCloud2`` it
    must also equal width x height (checked by the caller through the returned N).
    """
    data = bytes(msg.data)
    if hasattr(msg, "point_step"):  # sensor_msgs/msg/PointCloud2
        if msg.is_bigendian:
            raise ValueError("big-endian PointCloud2 is not supported")
        stride = int(msg.point_step)
        types = ROS_POINT_FIELD
        fields = {f.name: (int(f.offset), int(f.datatype)) for f in msg.fields}
        declared = int(msg.width) * int(msg.height)
        if int(msg.row_step) != int(msg.width) * stride:
            raise ValueError(f"row_step {msg.row_step} != width {msg.width} x point_step {stride}")
    else:  # foxglove.PointCloud
        stride = int(msg.point_stride)
        types = FOXGLOVE_NUMERIC
        fields = {f.name: (int(f.offset), int(f.type)) for f in msg.fields}
        declared = None
    if stride <= 0 or len(data) % stride:
        raise ValueError(f"data length {len(data)} is not a multiple of the point stride {stride}")
    n = len(data) // stride
    if declared is not None and declared != n:
        raise ValueError(f"width x height = {declared} but the data holds {n} points")
    names = [name for name in ("x", "y", "z", "time") if name in fields]
    if not {"x", "y", "z"} <= set(names):
        raise ValueError(f"point fields {sorted(fields)} lack x, y or z")
    dtype = np.dtype({
        "names": names,
        "formats": [types[fields[name][1]] for name in names],
        "offsets": [fields[name][0] for name in names],
        "itemsize": stride,
    })
    rec = np.frombuffer(data, dtype=dtype, count=n)
    xyz = np.stack([rec["x"], rec["y"], rec["z"]], axis=1).astype(np.float64)
    if not hasattr(msg, "point_step") and msg.HasField("pose"):  # foxglove cloud origin
        p, o = msg.pose.position, msg.pose.orientation
        xyz = apply(make_transform((p.x, p.y, p.z), (o.x, o.y, o.z, o.w)), xyz)
    time = rec["time"].astype(np.float64) if "time" in names else None
    return xyz, time, n


def calibration_of(msg: Any) -> tuple[int, int, np.ndarray, str, np.ndarray]:
    """(width, height, K 3x3, distortion model, D) of a CameraInfo / CameraCalibration."""
    if hasattr(msg, "header"):  # sensor_msgs/msg/CameraInfo
        k, d = msg.k, msg.d
    else:  # foxglove.CameraCalibration
        k, d = msg.K, msg.D
    return (int(msg.width), int(msg.height), np.asarray(list(k), dtype=np.float64).reshape(3, 3),
            str(msg.distortion_model), np.asarray(list(d), dtype=np.float64))


def first_difference(a: list, b: list) -> int | None:
    """Index of the first differing element (or of the shorter end), None if equal."""
    if a == b:
        return None
    return next((i for i, (x, y) in enumerate(zip(a, b, strict=False)) if x != y), min(len(a), len(b)))


def nearest(stamps: list[int], stamp: int) -> int:
    """Index of the stamp nearest to ``stamp``."""
    return int(np.argmin(np.abs(np.asarray(stamps, dtype=np.int64) - stamp)))


# --------------------------------------------------------------------------- checks


class Checker:
    """Counts checks and prints each failure with its drive and name."""

    def __init__(self, verbose: bool) -> None:
        self.verbose = verbose
        self.passed = 0
        self.failed = 0
        self.drive = ""

    def check(self, name: str, ok: bool, detail: str = "") -> bool:
        if ok:
            self.passed += 1
            if self.verbose:
                print(f"  ok    {self.drive}: {name}" + (f" ({detail})" if detail else ""))
        else:
            self.failed += 1
            print(f"  FAIL  {self.drive}: {name}" + (f": {detail}" if detail else ""))
        return ok

    def guard(self, name: str, fn: Callable[[], None]) -> None:
        """Runs a group of checks; an exception in it counts as one failed check."""
        try:
            fn()
        except Exception as e:  # every error becomes a reported failure
            self.check(name, False, f"{type(e).__name__}: {e}")


def check_container(c: Checker, drive: Drive, truth: dict) -> None:
    c.check("mcap profile", drive.header.profile == truth["profile"],
            f"mcap {drive.header.profile!r}, truth {truth['profile']!r}")
    if drive.summary is not None:
        compressions = {ci.compression for ci in drive.summary.chunk_indexes}
        c.check("chunk compression", compressions == {truth["compression"]},
                f"mcap {sorted(compressions)}, truth {truth['compression']!r}")
    else:
        c.check("summary section present", False, "the MCAP has no summary")
    got = {(t, *key) for t, key in drive.channels.items()}
    want = {(ch["topic"], ch["schema_name"], ch["schema_encoding"], ch["message_encoding"])
            for ch in truth["channels"]}
    c.check("channel set", got == want,
            f"{len(got)} channels; only in mcap: {sorted(got - want)}; only in truth: {sorted(want - got)}")
    bad = {ch["topic"]: (len(drive.messages.get(ch["topic"], [])), ch["message_count"])
           for ch in truth["channels"]
           if len(drive.messages.get(ch["topic"], [])) != ch["message_count"]}
    c.check("message counts per topic", not bad,
            f"{sum(len(m) for m in drive.messages.values())} messages; topic: (mcap, truth) {bad}")


def check_lidar(c: Checker, drive: Drive, truth: dict) -> None:
    lidar = truth["lidar"]
    msgs = drive.messages.get(lidar["topic"], [])
    sweeps = lidar["sweeps"]
    got_stamps = [stamp_of(m) for m in msgs]
    want_stamps = [s["stamp_nanos"] for s in sweeps]
    c.check("lidar sweep stamps", got_stamps == want_stamps,
            f"{len(got_stamps)} sweeps in the mcap, {len(want_stamps)} in truth, first difference at "
            f"index {first_difference(got_stamps, want_stamps)}")
    frames = {frame_of(m) for m in msgs}
    c.check("lidar frame_id", frames == {lidar["frame_id"]}, f"mcap {sorted(frames)}, truth {lidar['frame_id']!r}")
    counts, finite = [], True
    for m in msgs:
        xyz, _, n = cloud_points(m)
        counts.append(n)
        finite &= bool(np.all(np.isfinite(xyz)))
    want_counts = [s["points"] for s in sweeps]
    c.check("lidar point counts", counts == want_counts,
            f"{sum(counts)} points, first difference at sweep {first_difference(counts, want_counts)}")
    c.check("lidar points finite", finite)


def check_cameras(c: Checker, drive: Drive, truth: dict, notes: list[str]) -> None:
    n_classes = len(truth["classes"])
    for cam in truth["cameras"]:
        name = cam["name"]
        images = drive.messages.get(cam["image_topic"], [])
        calibs = drive.messages.get(cam["calibration_topic"], [])
        supers = drive.messages.get(cam["superpixel_topic"], [])
        image_stamps = [stamp_of(m) for m in images]
        c.check(f"{name} image stamps", image_stamps == cam["stamps_nanos"],
                f"{len(image_stamps)} images, {len(cam['stamps_nanos'])} truth stamps, first difference at "
                f"index {first_difference(image_stamps, cam['stamps_nanos'])}")
        c.check(f"{name} image frame_id", {frame_of(m) for m in images} == {cam["frame_id"]})

        k_truth = np.asarray(cam["k"], dtype=np.float64).reshape(3, 3)
        d_truth = np.asarray(cam["d"], dtype=np.float64)
        problems = []
        for m in calibs:
            w, h, k, model, d = calibration_of(m)
            if (w, h) != (cam["width"], cam["height"]):
                problems.append(f"size {w}x{h}")
            if not np.allclose(k, k_truth, rtol=0, atol=CALIBRATION_TOL):
                problems.append(f"K {k.ravel().tolist()}")
            if model != cam["distortion_model"]:
                problems.append(f"model {model!r}")
            if d.shape != d_truth.shape or not np.allclose(d, d_truth, rtol=0, atol=CALIBRATION_TOL):
                problems.append(f"D {d.tolist()}")
            if frame_of(m) != cam["frame_id"]:
                problems.append(f"frame {frame_of(m)!r}")
        c.check(f"{name} calibration", bool(calibs) and not problems,
                f"{len(calibs)} messages; " + "; ".join(sorted(set(problems))[:4]))

        if not images:
            c.check(f"{name} first JPEG", False, "no image messages")
        elif Image is None:
            notes.append("pillow not installed: JPEG decode sub-check skipped")
        else:
            first = images[0]
            fmt = str(first.format)
            img = Image.open(io.BytesIO(bytes(first.data)))
            img.load()
            c.check(f"{name} first JPEG decodes to {cam['width']}x{cam['height']}",
                    "jpeg" in fmt.lower() and img.format == "JPEG"
                    and img.size == (cam["width"], cam["height"]),
                    f"format {fmt!r}/{img.format}, size {img.size}")

        problems = []
        for m in supers:
            w, h = int(m.width), int(m.height)
            data = np.frombuffer(bytes(m.data), dtype=np.uint8)
            if (w, h) != (cam["width"], cam["height"]) or m.encoding != "mono8" or int(m.step) != w:
                problems.append(f"{w}x{h} {m.encoding} step {m.step}")
            if data.size != w * h:
                problems.append(f"{data.size} bytes for {w}x{h}")
            elif data.size and int(data.max()) >= n_classes:
                problems.append(f"class {int(data.max())} >= {n_classes}")
        c.check(f"{name} superpixels", bool(supers) and not problems,
                f"{len(supers)} messages; " + "; ".join(sorted(set(problems))[:4]))
        super_stamps = [stamp_of(m) for m in supers]
        c.check(f"{name} superpixel stamps equal image stamps", super_stamps == image_stamps,
                f"first difference at index {first_difference(super_stamps, image_stamps)}")


def check_transforms(c: Checker, tf: TransformBuffer, truth: dict) -> None:
    frames = truth["frames"]
    worst = {True: [0.0, 0.0, 0], False: [0.0, 0.0, 0]}  # sampled? -> [m, rad, count]
    misses = []
    for pose in truth["ego_poses"]:
        stamp = pose["stamp_nanos"]
        want = make_transform(pose["map_from_ego"]["translation"], pose["map_from_ego"]["rotation_xyzw"])
        try:
            got = tf.lookup(frames["map"], frames["ego"], stamp)
        except LookupError as e:
            misses.append(str(e))
            continue
        w = worst[tf.is_sampled(frames["map"], frames["ego"], stamp)]
        w[0] = max(w[0], float(np.linalg.norm(got[:3, 3] - want[:3, 3])))
        w[1] = max(w[1], rotation_angle_between(got[:3, :3], want[:3, :3]))
        w[2] += 1
    (st, sr, sn), (it, ir, n_interp) = worst[True], worst[False]
    missing = f"; {len(misses)} stamps not found, e.g. {misses[0]}" if misses else ""
    if sn:
        c.check(f"map_from_ego at {sn} sampled stamps",
                st <= SAMPLED_POSE_TOL and sr <= SAMPLED_POSE_TOL,
                f"max error {st:.2e} m, {sr:.2e} rad")
    if n_interp or misses:
        c.check(f"map_from_ego at {n_interp} interpolated stamps",
                not misses and it <= POSE_TRANSLATION_TOL_M and ir <= POSE_ROTATION_TOL_RAD,
                f"max error {it * 1e3:.4f} mm, {ir:.2e} rad{missing}")

    stamp = truth["ego_poses"][0]["stamp_nanos"]
    sensors = [("ego_from_lidar", truth["lidar"]["frame_id"], truth["lidar"]["ego_from_lidar"])]
    sensors += [(f"ego_from_camera {cam['name']}", cam["frame_id"], cam["ego_from_camera"])
                for cam in truth["cameras"]]
    for label, frame, extrinsic in sensors:
        want = make_transform(extrinsic["translation"], extrinsic["rotation_xyzw"])
        got = tf.lookup(frames["ego"], frame, stamp)
        err = float(np.max(np.abs(got - want)))
        c.check(label, err <= EXTRINSIC_TOL, f"max element error {err:.2e}")


def check_landmarks(c: Checker, drive: Drive, tf: TransformBuffer, truth: dict) -> None:
    frames = truth["frames"]
    cams = {cam["name"]: cam for cam in truth["cameras"]}
    for landmark in truth["landmarks"]:
        p_map = np.asarray(landmark["point_in_map"], dtype=np.float64)
        for obs in landmark["observations"]:
            cam = cams[obs["camera"]]
            stamp = obs["stamp_nanos"]
            calibs = drive.messages[cam["calibration_topic"]]
            calib_stamps = [stamp_of(m) for m in calibs]
            # the calibration in force at the stamp: the latest one not after it
            i = max(0, int(np.searchsorted(calib_stamps, stamp, side="right")) - 1)
            w, h, k, model, d = calibration_of(calibs[i])
            frame = frame_of(calibs[i])
            map_from_cam = tf.lookup(frames["map"], frames["ego"], stamp) @ tf.lookup(frames["ego"], frame, stamp)
            p_cam = apply(invert(map_from_cam), p_map[None, :])
            depth = float(p_cam[0, 2])
            uv = project(p_cam, k, model, d)[0]
            err_px = float(np.linalg.norm(uv - np.asarray(obs["pixel"])))
            err_depth = abs(depth - obs["depth"])
            inside = depth > 0 and 0 <= uv[0] < w and 0 <= uv[1] < h
            c.check(f"landmark {landmark['name']} in {cam['name']}",
                    err_px <= PIXEL_TOL and err_depth <= DEPTH_TOL_M and inside == bool(obs["visible"]),
                    f"pixel ({uv[0]:.3f}, {uv[1]:.3f}) vs {obs['pixel']} ({err_px:.3f} px), "
                    f"depth {depth:.4f} vs {obs['depth']:.4f}, visible {obs['visible']}")


def check_lidar_camera(c: Checker, drive: Drive, tf: TransformBuffer, truth: dict) -> str:
    """Points on road pixels lie on z = 0, points on manmade pixels above it."""
    frames, lidar = truth["frames"], truth["lidar"]
    classes = truth["classes"]
    road, manmade = classes.index("driveable_surface"), classes.index("manmade")
    cam = next(cam for cam in truth["cameras"] if cam["name"] == CONSISTENCY_CAMERA)

    start = drive.summary.statistics.message_start_time
    clouds = drive.messages[lidar["topic"]]
    sweep = clouds[nearest([stamp_of(m) for m in clouds], start + CONSISTENCY_OFFSET_NANOS)]
    sweep_stamp = stamp_of(sweep)
    xyz, time, _ = cloud_points(sweep)
    lidar_frame = frame_of(sweep)
    if lidar["motion_compensated"]:
        map_from_lidar = tf.lookup(frames["map"], lidar_frame, sweep_stamp)
        p_map = apply(map_from_lidar, xyz)
    else:  # de-skew: each point at its own firing time, seconds after the sweep stamp
        if time is None:
            raise ValueError("raw (not motion compensated) cloud without a per-point time field")
        p_map = np.empty_like(xyz)
        offsets = np.round(time.astype(np.float64) * 1e9).astype(np.int64)
        for offset in np.unique(offsets):
            sel = offsets == offset
            p_map[sel] = apply(tf.lookup(frames["map"], lidar_frame, sweep_stamp + int(offset)), xyz[sel])

    images = drive.messages[cam["image_topic"]]
    image = images[nearest([stamp_of(m) for m in images], sweep_stamp)]
    image_stamp = stamp_of(image)
    labels_msg = next(m for m in drive.messages[cam["superpixel_topic"]] if stamp_of(m) == image_stamp)
    w, h = int(labels_msg.width), int(labels_msg.height)
    labels = np.frombuffer(bytes(labels_msg.data), dtype=np.uint8).reshape(h, int(labels_msg.step))[:, :w]
    calibs = drive.messages[cam["calibration_topic"]]
    _, _, k, model, d = calibration_of(next(m for m in calibs if stamp_of(m) == image_stamp))

    map_from_cam = (tf.lookup(frames["map"], frames["ego"], image_stamp)
                    @ tf.lookup(frames["ego"], cam["frame_id"], image_stamp))
    p_cam = apply(invert(map_from_cam), p_map)
    front = p_cam[:, 2] > 1.0
    uv = project(p_cam[front], k, model, d)
    ui, vi = np.rint(uv[:, 0]).astype(np.int64), np.rint(uv[:, 1]).astype(np.int64)
    inside = (ui >= 0) & (ui < w) & (vi >= 0) & (vi < h)
    z = p_map[front][inside, 2]
    cls = labels[vi[inside], ui[inside]]

    z_road, z_manmade = z[cls == road], z[cls == manmade]
    road_ok = float(np.mean(np.abs(z_road) <= GROUND_Z_TOL_M)) if z_road.size else 0.0
    manmade_ok = float(np.mean(z_manmade > GROUND_Z_TOL_M)) if z_manmade.size else 0.0
    dt_ms = (image_stamp - sweep_stamp) / 1e6
    c.check(f"lidar/{cam['name']} driveable_surface points on z=0",
            z_road.size >= CONSISTENCY_MIN_POINTS and road_ok >= GROUND_MIN_FRACTION,
            f"{road_ok:.1%} of {z_road.size} points")
    c.check(f"lidar/{cam['name']} manmade points above ground",
            z_manmade.size >= CONSISTENCY_MIN_POINTS and manmade_ok >= MANMADE_MIN_FRACTION,
            f"{manmade_ok:.1%} of {z_manmade.size} points")
    return (f"sweep {sweep_stamp} vs {cam['name']} image {dt_ms:+.1f} ms: {int(inside.sum())} points in view, "
            f"driveable {road_ok:.1%} of {z_road.size} on z=0, manmade {manmade_ok:.1%} of {z_manmade.size} above")


def check_drive(c: Checker, mcap_path: Path, truth_path: Path) -> None:
    before_pass, before_fail = c.passed, c.failed
    c.drive = mcap_path.stem
    notes: list[str] = []
    truth = json.loads(truth_path.read_text())
    if not mcap_path.exists():
        c.check("mcap file exists", False, f"{mcap_path} is missing")
        print(f"{c.drive}: {c.passed - before_pass} passed, {c.failed - before_fail} failed")
        return
    try:
        drive = Drive(mcap_path)
    except Exception as e:  # an unreadable file is a reported failure
        c.check("mcap file reads", False, f"{type(e).__name__}: {e}")
        print(f"{c.drive}: {c.passed - before_pass} passed, {c.failed - before_fail} failed")
        return
    c.guard("container", lambda: check_container(c, drive, truth))
    c.guard("lidar", lambda: check_lidar(c, drive, truth))
    c.guard("cameras", lambda: check_cameras(c, drive, truth, notes))
    try:
        tf = drive.transforms()
    except Exception as e:
        c.check("transform tree", False, f"{type(e).__name__}: {e}")
        tf = None
    consistency = "not run"
    if tf is not None:
        c.guard("transforms", lambda: check_transforms(c, tf, truth))
        c.guard("landmarks", lambda: check_landmarks(c, drive, tf, truth))
        try:
            consistency = check_lidar_camera(c, drive, tf, truth)
        except Exception as e:
            c.check("lidar/camera consistency", False, f"{type(e).__name__}: {e}")
    n_obs = sum(len(lm["observations"]) for lm in truth["landmarks"])
    print(f"{c.drive} ({truth['dialect']}): {c.passed - before_pass} passed, {c.failed - before_fail} failed; "
          f"{len(truth['lidar']['sweeps'])} sweeps, {len(truth['cameras'])} cameras, "
          f"{len(truth['ego_poses'])} poses, {n_obs} landmark observations; {consistency}")
    for note in sorted(set(notes)):
        print(f"  note: {note}")


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("directory", type=Path, help="folder holding <drive>.mcap and <drive>.truth.json")
    parser.add_argument("-v", "--verbose", action="store_true", help="also print passing checks")
    args = parser.parse_args(argv)

    c = Checker(args.verbose)
    truths = sorted(args.directory.glob("*.truth.json"))
    if not truths:
        c.drive = str(args.directory)
        c.check("drives present", False, f"no *.truth.json in {args.directory}")
    for truth_path in truths:
        name = truth_path.name[: -len(".truth.json")]
        check_drive(c, truth_path.with_name(name + ".mcap"), truth_path)
    print(f"{c.passed} passed, {c.failed} failed")
    return 0 if c.failed == 0 else 1


if __name__ == "__main__":
    sys.exit(main())
