#!/usr/bin/env python3
"""Checks a batch file saved by the Rust writer against expected values, with the numpy
reader of the `superflow` Python package (trainer/python/superflow/format.py).

Usage::

    python3 tests/python/read_batch.py BATCH_FILE EXPECTED_JSON

``BATCH_FILE`` is the 11 400-byte ``BatchHeader`` followed by the payload.
``EXPECTED_JSON`` is::

    {"meta": {"run": ..., "epoch": ..., "step": ..., "seed": ..., "sequence": ...,
              "sample_count": ...},
     "sections": {"<name>": {"dtype": "<f4", "shape": [...], "values": [flat list]}}}

The batch is validated against every rule of the format document (a violation is one
failure naming the rule and the section), then the header fields and every section
(dtype string, shape, values bit-exactly) are compared with the expected ones, there
must be no other section, and every returned array must be a zero-copy view of the
payload buffer. Prints each failure and, as the very last line, ``N passed, M failed``;
exit code 0 only if nothing failed.

Run from the repository (the package is imported from trainer/python, not installed).
"""

from __future__ import annotations

import argparse
import json
import os
import sys
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[2] / "trainer" / "python"))
from superflow.errors import MalformedBatch
from superflow.format import (
    DTYPES,
    HEADER,
    HEADER_SIZE,
    MAGIC,
    SECTION_ALIGN,
    VERSION,
    _address,
    batch_meta,
    dtype_string,
    read_batch,
)

__all__ = ["DTYPES", "HEADER", "HEADER_SIZE", "MAGIC", "VERSION", "load_batch_file", "read_batch"]


def load_batch_file(path: str) -> tuple[np.ndarray, np.ndarray]:
    """(header bytes, payload bytes) of a batch file, read into memory whose payload
    starts 64-byte aligned, as iceoryx2 payloads are at least 8-byte aligned."""
    size = os.path.getsize(path)
    if size < HEADER_SIZE:
        raise MalformedBatch(f"rule 1: {path} has {size} bytes, less than the {HEADER_SIZE}-byte header")
    raw = np.empty(size + SECTION_ALIGN, dtype=np.uint8)
    shift = (-(_address(raw) + HEADER_SIZE)) % SECTION_ALIGN
    buf = raw[shift:shift + size]
    with open(path, "rb") as f:
        if f.readinto(buf.data) != size:
            raise OSError(f"short read of {path}")
    return buf[:HEADER_SIZE], buf[HEADER_SIZE:]


def _values_equal(array: np.ndarray, values: list) -> tuple[bool, str]:
    """Whether the flat expected values equal the array element for element, exactly."""
    flat = array.reshape(-1)
    if len(values) != flat.size:
        return False, f"{len(values)} expected values for {flat.size} elements"
    if array.dtype.kind in "iu":
        got = flat.tolist()  # Python ints: exact for u64 too
        bad = next((i for i, (a, b) in enumerate(zip(got, values, strict=False))
                    if type(b) is not int or a != b), None)  # bool is not a value
        return bad is None, "" if bad is None else f"element {bad}: {got[bad]} != {values[bad]!r}"
    if not all(type(v) in (int, float) for v in values):
        return False, "expected values must be numbers"
    # JSON carries the shortest decimal of each value; rounding it to the section's
    # float type gives back the exact bits (including the sign of zero).
    want = np.asarray(values, dtype=np.float64).astype(array.dtype)
    same = flat.view(f"u{array.dtype.itemsize}") == want.view(f"u{array.dtype.itemsize}")
    bad = None if same.all() else int(np.flatnonzero(~same)[0])
    return bad is None, "" if bad is None else f"element {bad}: {flat[bad].item()!r} != {values[bad]!r}"


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("batch_file")
    parser.add_argument("expected_json")
    parser.add_argument("-v", "--verbose", action="store_true", help="also print passing checks")
    args = parser.parse_args(argv)

    passed = failed = 0

    def check(name: str, ok: bool, detail: str = "") -> None:
        nonlocal passed, failed
        if ok:
            passed += 1
            if args.verbose:
                print(f"  ok    {name}")
        else:
            failed += 1
            print(f"  FAIL  {name}" + (f": {detail}" if detail else ""))

    with open(args.expected_json) as f:
        expected = json.load(f)
    try:
        header_bytes, payload = load_batch_file(args.batch_file)
        h, arrays = read_batch(header_bytes, payload)
    except (ValueError, AssertionError) as e:
        check("batch follows BATCH_FORMAT.md", False, str(e))
        print(f"{passed} passed, {failed} failed")
        return 1
    check("batch follows BATCH_FORMAT.md", True)

    meta = batch_meta(h)
    for key, want in expected["meta"].items():
        check(f"meta {key}", meta.get(key) == want, f"{meta.get(key)!r} != {want!r}")

    want_sections = expected["sections"]
    check("section names", set(arrays) == set(want_sections),
          f"unexpected {sorted(set(arrays) - set(want_sections))}, "
          f"missing {sorted(set(want_sections) - set(arrays))}")
    body = np.frombuffer(payload, dtype=np.uint8)
    for name, want in want_sections.items():
        if name not in arrays:
            continue
        array = arrays[name]
        got_dtype = dtype_string(array.dtype)
        check(f"`{name}` dtype", got_dtype == want["dtype"], f"{got_dtype} != {want['dtype']}")
        check(f"`{name}` shape", list(array.shape) == list(want["shape"]), f"{list(array.shape)} != {want['shape']}")
        ok, detail = _values_equal(array, want["values"]) if got_dtype == want["dtype"] else (False, "dtype differs")
        check(f"`{name}` values", ok, detail)
        shares = array.size == 0 or np.shares_memory(array, body)
        inside = _address(body) <= _address(array) <= _address(body) + body.size
        check(f"`{name}` is a zero-copy view of the payload", shares and inside,
              f"array at {_address(array):#x}, payload at {_address(body):#x}+{body.size}")

    print(f"{args.batch_file}: {len(arrays)} sections, {int(h['payload_len'])} payload bytes, run "
          f"{meta['run']!r}, epoch {meta['epoch']}, step {meta['step']}")
    print(f"{passed} passed, {failed} failed")
    return 0 if failed == 0 else 1


if __name__ == "__main__":
    sys.exit(main())
