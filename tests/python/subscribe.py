"""Reads superflow batches from shared memory with the iceoryx2 Python package and numpy,
without copying: the few lines a PyTorch user needs (`torch.from_numpy` on the arrays).

Usage: python3 tests/python/subscribe.py --run NAME [--rank R] [--count N]
       [--prefix P] [--timeout-secs S]

For each batch prints one JSON line: sequence, epoch, step, and for every section its
dtype, shape and a checksum of its bytes (what the end-to-end test compares with
the Rust reader), plus whether every array lies inside the shared-memory payload.
`--prefix` is the iceoryx2 isolation prefix the pipeline runs with
(`SUPERFLOW_IOX_PREFIX`).

The arrays are keyed by the names in the header's section table: the sections of
schemas/BATCH_FORMAT.md ("SuperFlow sections"), e.g. `torch.from_numpy(arrays["points"])`
for the N×4 points. Every literal key this file reads the arrays with must be in that
table (`cargo test -p superflow-schemas --test batch_sections` checks).
"""

import argparse
import ctypes
import json
import os
import sys
import time
from pathlib import Path

import iceoryx2 as iox2
import numpy as np

sys.path.insert(0, str(Path(__file__).parent))
from read_batch import read_batch  # noqa: E402  (the numpy reader of BATCH_FORMAT.md)


class BatchHeader(ctypes.Structure):
    """The 11 400-byte user header, as opaque 8-byte-aligned words (numpy parses it)."""

    _fields_ = [("words", ctypes.c_uint64 * (11_400 // 8))]

    @staticmethod
    def type_name() -> str:
        return "superflow::BatchHeader"


# The service settings every superflow process uses (schemas/src/service.rs, `qos`).
MAX_SUBSCRIBERS, MAX_BUFFER, MAX_BORROWED, MAX_PUBLISHERS, MAX_NODES = 8, 4, 2, 2, 16


def checksum(data: np.ndarray) -> int:
    """sum_i (b_i + 1) * (i * K + 1) mod 2^64 over the bytes (the Rust probe's too)."""
    b = np.ascontiguousarray(data).reshape(-1).view(np.uint8).astype(np.uint64) + np.uint64(1)
    weights = np.arange(b.size, dtype=np.uint64) * np.uint64(0x9E3779B97F4A7C15) + np.uint64(1)
    with np.errstate(over="ignore"):
        return int(np.sum(b * weights, dtype=np.uint64))


def open_stream(run: str, rank, prefix):
    config = iox2.config.default()
    if prefix:
        config.global_cfg.prefix = iox2.FileName.new(prefix + "_")
    node = iox2.NodeBuilder.new().config(config).create(iox2.ServiceType.Ipc)
    name = f"superflow/{run}/batches" if rank is None else f"superflow/{run}/rank/{rank}"
    service = (
        node.service_builder(iox2.ServiceName.new(name))
        .publish_subscribe(iox2.Slice[ctypes.c_uint8])
        .user_header(BatchHeader)
        .enable_safe_overflow(False)
        .history_size(0)
        .subscriber_max_buffer_size(MAX_BUFFER)
        .subscriber_max_borrowed_samples(MAX_BORROWED)
        .max_subscribers(MAX_SUBSCRIBERS)
        .max_publishers(MAX_PUBLISHERS)
        .max_nodes(MAX_NODES)
        .open_or_create()
    )
    event = (
        node.service_builder(iox2.ServiceName.new(name + "/ready"))
        .event()
        .max_nodes(MAX_NODES)
        .max_listeners(MAX_SUBSCRIBERS)
        .max_notifiers(MAX_PUBLISHERS)
        .open_or_create()
    )
    subscriber = service.subscriber_builder().buffer_size(2).create()
    listener = event.listener_builder().create()
    return node, service, event, subscriber, listener


def main() -> int:
    parser = argparse.ArgumentParser()
    parser.add_argument("--run", required=True)
    parser.add_argument("--rank", type=int)
    parser.add_argument("--count", type=int, default=1)
    parser.add_argument("--prefix", default=os.environ.get("SUPERFLOW_IOX_PREFIX"))
    parser.add_argument("--timeout-secs", type=float, default=60.0)
    args = parser.parse_args()
    _node, _service, _event, subscriber, listener = open_stream(args.run, args.rank, args.prefix)
    for _ in range(args.count):
        deadline = time.monotonic() + args.timeout_secs
        sample = subscriber.receive()
        while sample is None:
            if time.monotonic() > deadline:
                print(f"no batch within {args.timeout_secs} s", file=sys.stderr)
                return 3
            listener.timed_wait(iox2.Duration.from_millis(100))  # blocks, no spinning
            sample = subscriber.receive()
        # Zero-copy views: the header and payload memory of the sample.
        header = np.ctypeslib.as_array(sample.user_header().contents.words).view(np.uint8)
        payload_view = sample.payload().as_memory_view()
        h, arrays = read_batch(header, payload_view)
        start = sample.payload().as_ptr()
        end = start + sample.payload().len()
        inside = all(
            a.size == 0 or start <= a.__array_interface__["data"][0] < end for a in arrays.values()
        )
        sections = {
            name: {"dtype": a.dtype.str.replace("|", "<"), "shape": list(a.shape), "checksum": checksum(a)}
            for name, a in arrays.items()
        }
        print(
            json.dumps(
                {
                    "sequence": int(h["sequence"]),
                    "epoch": int(h["epoch"]),
                    "step": int(h["step"]),
                    "zero_copy": inside,
                    "sections": sections,
                }
            ),
            flush=True,
        )
        del arrays, header, payload_view
        del sample
    return 0


if __name__ == "__main__":
    sys.exit(main())
