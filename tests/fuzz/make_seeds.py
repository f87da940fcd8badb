#!/usr/bin/env python3
"""Writes the seed corpus of the fuzz targets (tests/fuzz/corpus/<target>/) from the
sample drives in recordings/drives/ and a batch written by `superflow-pipeline batch`.

Needs the packages of tests/python/requirements.txt (mcap, mcap-ros2-support,
mcap-protobuf-support, protobuf, pillow). The committed corpus is these seeds (named
files) plus inputs the fuzzer found (named by hash), minimized with `cargo fuzz cmin`
and trimmed to a size budget, plus every input that crashed a target (`crash-*`).
Rerun this only to rebuild the seeds:

    python3 tests/fuzz/make_seeds.py [--batch FILE]

Seeds per target:
* mcap_drive: the head of each real drive (its real messages, compression and CRCs,
  one camera), and small drives of both dialects with shrunk messages (a few LiDAR
  points, 16x9 images, scaled calibrations), uncompressed and without CRCs so that
  mutations reach the decoders, chunked (small chunks, full summary) and unchunked.
* message_decoders: one selector byte, then a single message of each type the drives
  hold (real size and shrunk), plus PNG and raw-encoding variants of the images.
* batch_reader: the batch file given (header + payload) with every section cut to its
  first rows, and a batch with no sections.
"""

import argparse
import copy
import io
import struct
from pathlib import Path

from mcap.reader import make_reader
from mcap.writer import CompressionType, Writer
from mcap_protobuf.decoder import DecoderFactory as ProtobufDecoders
from mcap_ros2._dynamic import generate_dynamic, serialize_dynamic
from PIL import Image

ROOT = Path(__file__).resolve().parents[2]
DRIVES = ROOT / "recordings" / "drives"
CORPUS = Path(__file__).resolve().parent / "corpus"

SMALL_W, SMALL_H = 16, 9
POINTS = 48


def read_drive(path):
    """Every message of a drive: (schema, channel, message), in log-time order."""
    with open(path, "rb") as f:
        reader = make_reader(f)
        header = reader.get_header()
        out = list(reader.iter_messages(log_time_order=True))
    return header, out


def pick(messages, t_end, cameras, lidar_count):
    """tf_static, /tf up to t_end, `lidar_count` sweeps, and for each camera in `cameras`
    (a topic prefix) its calibration, images and class maps up to t_end."""
    t0 = messages[0][2].log_time
    lidar = 0
    kept = []
    for schema, channel, message in messages:
        topic = channel.topic
        name = schema.name if schema else ""
        if "tf_static" in topic:
            kept.append((schema, channel, message))
        elif message.log_time - t0 > t_end:
            continue
        elif topic == "/tf":
            kept.append((schema, channel, message))
        elif name.endswith("PointCloud2") or name == "foxglove.PointCloud":
            if lidar < lidar_count:
                kept.append((schema, channel, message))
                lidar += 1
        elif any(topic.lower().startswith(c) for c in cameras):
            kept.append((schema, channel, message))
        elif name == "Pose":
            kept.append((schema, channel, message))
    return kept


def write_mcap(path, header, messages, compression, crcs, chunking=True, chunk_size=1 << 20):
    buf = io.BytesIO()
    writer = Writer(
        buf,
        chunk_size=chunk_size,
        compression=compression,
        use_chunking=chunking,
        enable_crcs=crcs,
        enable_data_crcs=False,
    )
    writer.start(profile=header.profile, library=header.library)
    schemas, channels = {}, {}
    for schema, channel, message in messages:
        sid = 0
        if schema is not None:
            if schema.id not in schemas:
                schemas[schema.id] = writer.register_schema(schema.name, schema.encoding, schema.data)
            sid = schemas[schema.id]
        if channel.id not in channels:
            channels[channel.id] = writer.register_channel(
                channel.topic, channel.message_encoding, sid, channel.metadata
            )
        writer.add_message(
            channels[channel.id],
            log_time=message.log_time,
            data=message.data,
            publish_time=message.publish_time,
            sequence=message.sequence,
        )
    writer.finish()
    path.write_bytes(buf.getvalue())
    return buf.getvalue()


def small_jpeg(data, fmt="JPEG", mode=None):
    image = Image.open(io.BytesIO(data))
    image = image.convert(mode or image.mode).resize((SMALL_W, SMALL_H))
    out = io.BytesIO()
    image.save(out, format=fmt, quality=60) if fmt == "JPEG" else image.save(out, format=fmt)
    return out.getvalue()


def small_mono(data, width, height, step):
    rows = [data[int(r * height / SMALL_H) * step :][:width] for r in range(SMALL_H)]
    return b"".join(bytes(row[int(c * width / SMALL_W)] for c in range(SMALL_W)) for row in rows)


def scale_k(k, width, height):
    sx, sy = SMALL_W / width, SMALL_H / height
    k = list(k)
    k[0] *= sx
    k[2] *= sx
    k[4] *= sy
    k[5] *= sy
    return k


class Ros2Codec:
    def __init__(self):
        self.dec, self.enc = {}, {}

    def _load(self, schema):
        if schema.name not in self.dec:
            text = schema.data.decode()
            self.dec[schema.name] = generate_dynamic(schema.name, text)[schema.name]
            self.enc[schema.name] = serialize_dynamic(schema.name, text)[schema.name]

    def decode(self, schema, data):
        self._load(schema)
        return self.dec[schema.name](data)

    def encode(self, schema, msg):
        self._load(schema)
        return self.enc[schema.name](msg)


def shrink_ros2(messages):
    codec = Ros2Codec()
    out = []
    for schema, channel, message in messages:
        name = schema.name
        msg = codec.decode(schema, message.data)
        if name.endswith("PointCloud2"):
            n = min(POINTS, msg.width * msg.height)
            msg.data = bytes(msg.data[: n * msg.point_step])
            msg.height, msg.width, msg.row_step = 1, n, n * msg.point_step
        elif name.endswith("CompressedImage"):
            msg.data = small_jpeg(bytes(msg.data))
        elif name.endswith("msg/Image"):
            msg.data = small_mono(bytes(msg.data), msg.width, msg.height, msg.step)
            msg.width, msg.height, msg.step = SMALL_W, SMALL_H, SMALL_W
        elif name.endswith("CameraInfo"):
            msg.k = scale_k(msg.k, msg.width, msg.height)
            msg.p = scale_k(msg.p[:3] + msg.p[4:7] + msg.p[8:11], msg.width, msg.height)
            msg.p = msg.p[:3] + [0.0] + msg.p[3:6] + [0.0] + msg.p[6:9] + [0.0]
            msg.width, msg.height = SMALL_W, SMALL_H
        else:
            out.append((schema, channel, message))
            continue
        out.append((schema, channel, copy.copy(message)))
        out[-1][2].data = codec.encode(schema, msg)
    return out


def shrink_foxglove(messages):
    decoders = ProtobufDecoders()
    out = []
    for schema, channel, message in messages:
        if channel.message_encoding != "protobuf":
            out.append((schema, channel, message))
            continue
        msg = decoders.decoder_for("protobuf", schema)(message.data)
        name = schema.name
        if name == "foxglove.PointCloud":
            msg.data = msg.data[: POINTS * msg.point_stride]
        elif name == "foxglove.CompressedImage":
            msg.data = small_jpeg(msg.data)
        elif name == "foxglove.RawImage":
            msg.data = small_mono(msg.data, msg.width, msg.height, msg.step)
            msg.width, msg.height, msg.step = SMALL_W, SMALL_H, SMALL_W
        elif name == "foxglove.CameraCalibration":
            k = scale_k(msg.K, msg.width, msg.height)
            del msg.K[:]
            msg.K.extend(k)
            msg.width, msg.height = SMALL_W, SMALL_H
        else:
            out.append((schema, channel, message))
            continue
        out.append((schema, channel, copy.copy(message)))
        out[-1][2].data = msg.SerializeToString()
    return out


# Selectors of the message_decoders target (see fuzz_targets/message_decoders.rs).
SELECTOR = {
    "sensor_msgs/msg/PointCloud2": 0,
    "foxglove.PointCloud": 1,
    "sensor_msgs/msg/CompressedImage": 2,
    "sensor_msgs/msg/Image": 3 | 0x10,
    "foxglove.CompressedImage": 4,
    "foxglove.RawImage": 5 | 0x10,
    "sensor_msgs/msg/CameraInfo": 6,
    "foxglove.CameraCalibration": 7,
    "tf2_msgs/msg/TFMessage": 8,
    "foxglove.FrameTransform": 9,
}


def decoder_seeds(tag, messages, out_dir, seen):
    for schema, channel, message in messages:
        if schema is None or schema.name not in SELECTOR:
            continue
        key = (tag, schema.name, "static" in channel.topic)
        if key in seen:
            continue
        seen.add(key)
        stem = schema.name.replace("/", "_").replace(".", "_")
        static = "_static" if key[2] else ""
        selector = SELECTOR[schema.name] | (0x10 if key[2] else 0)
        (out_dir / f"{tag}_{stem}{static}").write_bytes(bytes([selector]) + message.data)


def extra_decoder_seeds(ros2_small, fox_small, out_dir):
    """PNG, raw colour encodings with padding, a FrameTransforms list."""
    codec = Ros2Codec()
    for schema, _, message in ros2_small:
        if schema.name.endswith("CompressedImage"):
            msg = codec.decode(schema, message.data)
            jpeg = bytes(msg.data)
            msg.format, msg.data = "png", small_jpeg(jpeg, "PNG", "RGB")
            (out_dir / "ros2_png_rgb").write_bytes(bytes([2]) + codec.encode(schema, msg))
            msg.format, msg.data = "mono8; png compressed", small_jpeg(jpeg, "PNG", "L")
            (out_dir / "ros2_png_mono").write_bytes(bytes([2 | 0x10]) + codec.encode(schema, msg))
            break
    for schema, _, message in ros2_small:
        if schema.name == "sensor_msgs/msg/Image":
            msg = codec.decode(schema, message.data)
            for encoding, channels, pad in [("rgb8", 3, 0), ("bgra8", 4, 4), ("mono16", 2, 2)]:
                step = SMALL_W * channels + pad
                msg.encoding, msg.step = encoding, step
                msg.data = bytes((i * 7) % 251 for i in range(step * SMALL_H))
                (out_dir / f"ros2_raw_{encoding}").write_bytes(bytes([3]) + codec.encode(schema, msg))
            break
    decoders = ProtobufDecoders()
    transforms = [m.data for s, _, m in fox_small if s and s.name == "foxglove.FrameTransform"][:3]
    body = b"".join(b"\x0a" + varint(len(t)) + t for t in transforms)
    (out_dir / "foxglove_FrameTransforms").write_bytes(bytes([10]) + body)
    for schema, _, message in fox_small:
        if schema and schema.name == "foxglove.CompressedImage":
            msg = decoders.decoder_for("protobuf", schema)(message.data)
            msg.format, msg.data = "png", small_jpeg(msg.data, "PNG", "RGB")
            (out_dir / "foxglove_png").write_bytes(bytes([4]) + msg.SerializeToString())
            break


def varint(n):
    out = b""
    while True:
        b = n & 0x7F
        n >>= 7
        if n:
            out += bytes([b | 0x80])
        else:
            return out + bytes([b])


# BatchHeader layout (schemas/BATCH_FORMAT.md): 136 bytes of fields, then 128 x 88-byte
# section descriptors (name[32], dtype u32, ndim u32, shape u64[4], offset u64, len u64).
HEADER_FIELDS = 136
DESC = 88
MAX_SECTIONS = 128
HEADER_SIZE = HEADER_FIELDS + MAX_SECTIONS * DESC
DTYPE_SIZE = {1: 1, 2: 2, 3: 4, 4: 4, 5: 8, 6: 8, 7: 4, 8: 8}


def cut_batch(data, rows):
    """The batch with every dimension of every section cut to at most `rows` (the view
    checks structure, not what the sections mean)."""
    header = bytearray(data[:HEADER_SIZE])
    payload = data[HEADER_SIZE:]
    (count,) = struct.unpack_from("<I", header, 12)
    new_payload = bytearray()
    for i in range(count):
        at = HEADER_FIELDS + i * DESC
        dtype, ndim = struct.unpack_from("<II", header, at + 32)
        shape = list(struct.unpack_from("<4Q", header, at + 40))
        offset, length = struct.unpack_from("<QQ", header, at + 72)
        shape = [min(d, rows) for d in shape]
        size = DTYPE_SIZE[dtype]
        for d in shape[:ndim]:
            size *= d
        start = len(new_payload)
        new_payload += payload[offset : offset + size]
        new_payload += b"\0" * (-len(new_payload) % 64)
        struct.pack_into("<4Q", header, at + 40, *shape)
        struct.pack_into("<QQ", header, at + 72, start, size)
    struct.pack_into("<Q", header, 16, len(new_payload))
    return bytes(header) + bytes(new_payload)


def main():
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--batch", type=Path, help="a batch file from `superflow-pipeline batch`")
    args = parser.parse_args()
    drive_dir = CORPUS / "mcap_drive"
    decoder_dir = CORPUS / "message_decoders"
    batch_dir = CORPUS / "batch_reader"
    for d in (drive_dir, decoder_dir, batch_dir):
        d.mkdir(parents=True, exist_ok=True)

    seen = set()
    smalls = {}
    for tag, file, camera, compression in [
        ("ros2", "street_ros2.mcap", "/cam_front/", CompressionType.ZSTD),
        ("foxglove", "street_foxglove.mcap", "/cam_front/", CompressionType.LZ4),
    ]:
        header, messages = read_drive(DRIVES / file)
        head = pick(messages, 0.15e9, [camera], 1)
        write_mcap(drive_dir / f"{tag}_head.mcap", header, head, compression, True)
        small = pick(messages, 0.3e9, [camera, "/cam_back/"], 4)
        small = (shrink_ros2 if tag == "ros2" else shrink_foxglove)(small)
        smalls[tag] = small
        none = CompressionType.NONE
        write_mcap(drive_dir / f"{tag}_small.mcap", header, small, none, False, chunk_size=4096)
        write_mcap(drive_dir / f"{tag}_small_unchunked.mcap", header, small, none, False, False)
        decoder_seeds(tag, small, decoder_dir, seen)
        decoder_seeds(tag + "_real", [m for m in head if len(m[2].data) < 20000], decoder_dir, seen)
    extra_decoder_seeds(smalls["ros2"], smalls["foxglove"], decoder_dir)

    if args.batch:
        data = args.batch.read_bytes()
        (batch_dir / "batch_cut2").write_bytes(cut_batch(data, 2))
        (batch_dir / "batch_cut5").write_bytes(cut_batch(data, 5))
        empty = bytearray(data[:HEADER_SIZE])
        struct.pack_into("<IQ", empty, 12, 0, 0)
        empty[HEADER_FIELDS:] = bytes(MAX_SECTIONS * DESC)
        (batch_dir / "batch_empty").write_bytes(bytes(empty))

    for d in (drive_dir, decoder_dir, batch_dir):
        files = sorted(d.iterdir())
        print(f"{d.name}: {len(files)} files, {sum(f.stat().st_size for f in files)} bytes")


if __name__ == "__main__":
    main()
