"""Independent checks of a sample written as MCAP for Foxglove (`superflow-pipeline sample
--out-mcap`): read with the reference `mcap` reader, every message decoded with Foxglove's
published protobuf classes (`foxglove-schemas-protobuf`), against the facts the Rust test
took from the sample itself (EXPECTED, JSON):

* every schema is Foxglove's, and every message decodes with its published class;
* counts: points per cloud, one image, calibration, superpixel image and pairing
  annotation per chosen camera and frame;
* geometry: each paired point, moved through the written transforms and projected with
  the written calibration (its lens model included), lands within 0.5 px of its pairing's
  pixel centre, and the annotations sit on those centres.

Usage: python3 check_sample_mcap.py FILE.mcap [EXPECTED.json]
Without EXPECTED, only the first check (any view file: `superflow-trainer features` too).
Prints one line per failed check and ends with `N passed, M failed`.
"""

from __future__ import annotations

import importlib
import json
import sys
from collections import defaultdict
from typing import Any

import numpy as np
from mcap.reader import make_reader

PASSED = 0
FAILED = 0


def check(ok: bool, what: str) -> None:
    global PASSED, FAILED
    if ok:
        PASSED += 1
    else:
        FAILED += 1
        print(f"FAIL: {what}")


def published_class(schema_name: str) -> Any:
    """foxglove.PointCloud -> foxglove_schemas_protobuf.PointCloud_pb2.PointCloud."""
    package, name = schema_name.split(".")
    assert package == "foxglove", schema_name
    module = importlib.import_module(f"foxglove_schemas_protobuf.{name}_pb2")
    return getattr(module, name)


def quaternion_matrix(q: Any) -> np.ndarray:
    x, y, z, w = q.x, q.y, q.z, q.w
    return np.array(
        [
            [1 - 2 * (y * y + z * z), 2 * (x * y - z * w), 2 * (x * z + y * w)],
            [2 * (x * y + z * w), 1 - 2 * (x * x + z * z), 2 * (y * z - x * w)],
            [2 * (x * z - y * w), 2 * (y * z + x * w), 1 - 2 * (x * x + y * y)],
        ]
    )


def distort(model: str, d: list[float], x: np.ndarray, y: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """ROS / OpenCV lens models on normalised coordinates."""
    if model == "" or not any(d):
        return x, y
    if model == "kannala_brandt":
        k1, k2, k3, k4 = d[:4]
        r = np.hypot(x, y)
        theta = np.arctan(r)
        t2 = theta * theta
        theta_d = theta * (1 + k1 * t2 + k2 * t2**2 + k3 * t2**3 + k4 * t2**4)
        scale = np.where(r > 1e-12, theta_d / np.maximum(r, 1e-12), 1.0)
        return x * scale, y * scale
    k = list(d) + [0.0] * (8 - len(d))
    k1, k2, p1, p2, k3, k4, k5, k6 = k[:8]
    if model not in ("plumb_bob", "rational_polynomial"):
        raise ValueError(f"unknown distortion model {model!r}")
    r2 = x * x + y * y
    radial = (1 + k1 * r2 + k2 * r2**2 + k3 * r2**3) / (1 + k4 * r2 + k5 * r2**2 + k6 * r2**3)
    xd = x * radial + 2 * p1 * x * y + p2 * (r2 + 2 * x * x)
    yd = y * radial + p1 * (r2 + 2 * y * y) + 2 * p2 * x * y
    return xd, yd


def cloud_points(cloud: Any) -> dict[str, np.ndarray]:
    types = {7: "<f4", 1: "u1", 6: "<i4", 5: "<u4"}
    fields = {f.name: (f.offset, types[f.type]) for f in cloud.fields}
    n = len(cloud.data) // cloud.point_stride
    dtype = np.dtype(
        {
            "names": list(fields),
            "formats": [fmt for _, fmt in fields.values()],
            "offsets": [off for off, _ in fields.values()],
            "itemsize": cloud.point_stride,
        }
    )
    raw = np.frombuffer(cloud.data, dtype=dtype, count=n)
    return {name: raw[name] for name in fields}


def main() -> None:
    path = sys.argv[1]
    expected_path = sys.argv[2] if len(sys.argv) > 2 else None
    by_topic_time: dict[tuple[str, int], Any] = {}
    counts: dict[str, int] = defaultdict(int)
    with open(path, "rb") as f:
        reader = make_reader(f)
        for schema, channel, message in reader.iter_messages():
            check(schema.encoding == "protobuf", f"{channel.topic}: schema encoding {schema.encoding}")
            check(channel.message_encoding == "protobuf", f"{channel.topic}: message encoding")
            cls = published_class(schema.name)
            decoded = cls()
            decoded.ParseFromString(message.data)
            # The embedded schema names the same message as the published one.
            check(
                cls.DESCRIPTOR.full_name == schema.name,
                f"{channel.topic}: {schema.name} is not Foxglove's {cls.DESCRIPTOR.full_name}",
            )
            check(
                (channel.topic, message.log_time) not in by_topic_time,
                f"{channel.topic} twice at {message.log_time}",
            )
            by_topic_time[(channel.topic, message.log_time)] = decoded
            counts[channel.topic] += 1
    check(bool(counts), "the file has messages")
    if expected_path is None:
        print(", ".join(f"{topic}: {n}" for topic, n in sorted(counts.items())))
        print(f"{PASSED} passed, {FAILED} failed")
        sys.exit(1 if FAILED else 0)
    with open(expected_path) as f:
        expected = json.load(f)

    frames = expected["frames"]
    check(counts["/superflow/cloud"] == len(frames), f"{counts['/superflow/cloud']} clouds, {len(frames)} frames")
    check(counts["/tf"] == len(frames), f"{counts['/tf']} /tf messages")
    check(counts["/superflow/dense"] == len(expected["dense"]), "dense clouds")
    for dense in expected["dense"]:
        cloud = by_topic_time.get(("/superflow/dense", dense["stamp"]))
        check(cloud is not None, f"dense cloud at {dense['stamp']}")
        if cloud is None:
            continue
        fields = cloud_points(cloud)
        check(len(fields["x"]) == dense["points"], f"dense: {len(fields['x'])} points, {dense['points']} expected")
        check(int(fields["paired"].sum()) == dense["paired"], "dense: paired points")
        check(sorted(set(fields["source_sweep"].tolist())) == dense["sources"], "dense: source sweeps")

    worst = 0.0
    projected = 0
    for frame in frames:
        stamp = frame["stamp"]
        cloud = by_topic_time.get(("/superflow/cloud", stamp))
        tf = by_topic_time.get(("/tf", stamp))
        check(cloud is not None and tf is not None, f"cloud and /tf at {stamp}")
        if cloud is None or tf is None:
            continue
        fields = cloud_points(cloud)
        check(len(fields["x"]) == frame["points"], f"{stamp}: {len(fields['x'])} points, {frame['points']} expected")
        xyz = np.stack([fields["x"], fields["y"], fields["z"]], axis=1).astype(np.float64)
        paired_points = {p[0] for p in frame["pairs"]}
        check(int(fields["paired"].sum()) == len(paired_points), f"{stamp}: paired field")
        check(cloud.frame_id == frame["lidar_frame"], f"{stamp}: cloud frame {cloud.frame_id}")
        transforms = {(t.parent_frame_id, t.child_frame_id): t for t in tf.transforms}
        width, height = frame["image_size"]
        for slot, camera in enumerate(frame["cameras"]):
            topic = "/superflow/" + camera["topic"]
            image = by_topic_time.get((topic + "/image", stamp))
            cal = by_topic_time.get((topic + "/calibration", stamp))
            sp = by_topic_time.get((topic + "/superpixels", stamp))
            notes = by_topic_time.get((topic + "/pairings", stamp))
            check(None not in (image, cal, sp, notes), f"{topic} at {stamp}: image, calibration, superpixels, pairings")
            if image is None or cal is None or sp is None or notes is None:
                continue
            check(image.format == "png" and image.data[:8] == b"\x89PNG\r\n\x1a\n", f"{topic}: PNG")
            check((cal.width, cal.height) == (width, height), f"{topic}: calibration size {cal.width}x{cal.height}")
            check(
                cal.frame_id == image.frame_id == camera["frame_id"],
                f"{topic}: frames {cal.frame_id} {image.frame_id}",
            )
            t = transforms.get((frame["lidar_frame"], cal.frame_id))
            check(t is not None, f"{topic}: a transform {frame['lidar_frame']} -> {cal.frame_id}")
            if t is None:
                continue
            lidar_from_camera_r = quaternion_matrix(t.rotation)
            lidar_from_camera_t = np.array([t.translation.x, t.translation.y, t.translation.z])
            pairs = [p for p in frame["pairs"] if p[1] == slot]
            idx = np.array([p[0] for p in pairs], dtype=np.int64)
            rowcol = np.array([[p[2], p[3]] for p in pairs], dtype=np.float64).reshape(-1, 2)
            # camera_from_lidar = inverse of the written lidar_from_camera.
            in_camera = (xyz[idx] - lidar_from_camera_t) @ lidar_from_camera_r
            z = in_camera[:, 2]
            check(bool(np.all(z > 0)), f"{topic}: paired points in front of the camera")
            xd, yd = distort(cal.distortion_model, list(cal.D), in_camera[:, 0] / z, in_camera[:, 1] / z)
            k = cal.K
            u = k[0] * xd + k[1] * yd + k[2]
            v = k[4] * yd + k[5]
            if len(pairs):
                err = np.maximum(np.abs(u - rowcol[:, 1]), np.abs(v - rowcol[:, 0]))
                worst = max(worst, float(err.max()))
                bad = int((err > 0.5 + 1e-6).sum())
                check(bad == 0, f"{topic} at {stamp}: {bad} of {len(pairs)} pairings project > 0.5 px away")
                projected += len(pairs)
            marks = notes.points[0].points if notes.points else []
            centres = sorted((m.x, m.y) for m in marks)
            check(
                centres == sorted((c + 0.5, r + 0.5) for r, c in rowcol.tolist()),
                f"{topic}: annotations are the pairings' pixel centres",
            )
            check(
                len(notes.points[0].outline_colors) == len(pairs) if notes.points else not pairs,
                f"{topic}: a colour per paired point",
            )
    check(projected > 0, "some pairings were projected")
    print(f"{projected} pairings projected, worst {worst:.3f} px")
    print(f"{PASSED} passed, {FAILED} failed")
    sys.exit(1 if FAILED else 0)


if __name__ == "__main__":
    main()
