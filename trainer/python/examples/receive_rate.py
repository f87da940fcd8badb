"""How fast Python receives a superflow stream: batches/s and MB/s over `--count` batches
(after the first, which waits for the pipeline to start), and the median cost of turning a
received sample into a checked `Batch` (validating the header and section table, mapping
every section) and of `batch.torch()` when torch is installed.

    superflow-pipeline --mcap DRIVES --run rate --subscribers 2 --batch-size 4 &
    python trainer/python/examples/receive_rate.py --run rate --count 40 &
    superflow-subscriber --run rate --count 41      # the Rust reader on the same stream
"""

from __future__ import annotations

import argparse
import statistics
import sys
import time

import superflow
from superflow.stream import Batch


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--run", required=True)
    parser.add_argument("--count", type=int, default=40)
    parser.add_argument("--prefix")
    args = parser.parse_args()
    stream = superflow.Stream(args.run, prefix=args.prefix, timeout_s=300)
    next(stream).release()  # the first batch waits for the pipeline to come up
    started = time.perf_counter()
    nbytes, checks, tensors = 0, [], []
    for _ in range(args.count):
        batch = next(stream)
        sample = batch._sample
        nbytes += sample.payload().len()
        t = time.perf_counter()
        Batch(sample, stream.run, stream.service)  # the same sample, checked and mapped again
        checks.append(time.perf_counter() - t)
        try:
            t = time.perf_counter()
            batch.torch()
            tensors.append(time.perf_counter() - t)
        except ImportError:
            pass
    elapsed = time.perf_counter() - started
    stream.close()
    print("| batches | s | batches/s | MB/s | check + map ms | torch() ms |")
    print("|---:|---:|---:|---:|---:|---:|")
    torch_ms = f"{1e3 * statistics.median(tensors):.2f}" if tensors else "-"
    print(f"| {args.count} | {elapsed:.2f} | {args.count / elapsed:.1f} | "
          f"{nbytes / elapsed / 1e6:.0f} | {1e3 * statistics.median(checks):.2f} | {torch_ms} |")
    return 0


if __name__ == "__main__":
    sys.exit(main())
