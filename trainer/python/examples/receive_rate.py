"""How fast Python receives a superflow stream: batches/s and MB/s over `--count` batches
(after the first, which waits for the pipeline to start), and the median cost of turning a
received sample into a checked `Batch` (validating the header and section table, mapping
every section), of reading every byte of it once (the first touch of its pages), of
`batch.torch()` when torch is installed, and of writing its `images` section: in place
(`images.sub_(1)`, which copies the pages written into this process) against
`images.clone()` (a copy of the section, written afterwards at no further cost).

    superflow-pipeline --mcap DRIVES --run rate --subscribers 2 --batch-size 4 &
    python trainer/python/examples/receive_rate.py --run rate --count 40 &
    superflow-subscriber --run rate --count 41      # the Rust reader on the same stream
"""

from __future__ import annotations

import argparse
import statistics
import sys
import time

import numpy as np

import superflow
from superflow import Batch


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--run", required=True)
    parser.add_argument("--count", type=int, default=40)
    parser.add_argument("--prefix")
    args = parser.parse_args()
    stream = superflow.Stream(args.run, prefix=args.prefix, timeout_s=300)
    next(stream).release()  # the first batch waits for the pipeline to come up
    started = time.perf_counter()
    image_mb = 0.0
    nbytes, checks, reads, tensors, in_place, clones = 0, [], [], [], [], []
    for _ in range(args.count):
        batch = next(stream)
        sample = batch._sample
        nbytes += sample.payload().len()
        t = time.perf_counter()
        Batch(sample, stream.run, stream.service)  # the same sample, checked and mapped again
        checks.append(time.perf_counter() - t)
        t = time.perf_counter()
        for name in batch.names():
            batch[name].view(np.uint8).sum(dtype=np.uint64)
        reads.append(time.perf_counter() - t)
        try:
            t = time.perf_counter()
            images = batch.torch()["images"]
            tensors.append(time.perf_counter() - t)
            t = time.perf_counter()
            images.clone()
            clones.append(time.perf_counter() - t)
            t = time.perf_counter()
            images.sub_(1)
            in_place.append(time.perf_counter() - t)
            image_mb = images.numel() / 1e6
            del images
        except ImportError:
            pass
    elapsed = time.perf_counter() - started
    stream.close()

    def ms(values: list[float]) -> str:
        return f"{1e3 * statistics.median(values):.2f}" if values else "-"

    print("| batches | s | batches/s | MB/s | check + map ms | read all ms | torch() ms | "
          "images MB | images.clone() ms | images.sub_(1) ms |")
    print("|---:|---:|---:|---:|---:|---:|---:|---:|---:|---:|")
    print(f"| {args.count} | {elapsed:.2f} | {args.count / elapsed:.1f} | "
          f"{nbytes / elapsed / 1e6:.0f} | {ms(checks)} | {ms(reads)} | {ms(tensors)} | "
          f"{image_mb if tensors else 0:.1f} | {ms(clones)} | {ms(in_place)} |")
    return 0


if __name__ == "__main__":
    sys.exit(main())
