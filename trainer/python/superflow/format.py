"""The superflow batch format (version 2, schemas/BATCH_FORMAT.md in the repository), read
with numpy: ``read_batch(header_bytes, payload)`` validates a batch against every rule of
the format (header constants, section table, dtypes, shapes and sizes, bounds, overlaps,
alignment in memory, zeroed padding) and returns ``(header record, {name: array})``,
each array a view into ``payload`` (no copy; read-only when the payload is). A violation
raises :class:`~superflow.MalformedBatch` naming the rule and the section; a batch of
another format version raises :class:`~superflow.FormatVersionMismatch`.

The arrays stay valid only while the payload buffer does: :class:`superflow.Stream`
keeps each batch's memory until its last view is gone.
"""

from __future__ import annotations

import math
import warnings
from itertools import pairwise
from typing import Any

import numpy as np

from .errors import FormatVersionMismatch, MalformedBatch

MAGIC = 0x424C4653  # the bytes "SFLB", little-endian
VERSION = 2
HEADER_SIZE = 11_400
MAX_SECTIONS = 128
MAX_DIMS = 4
SECTION_NAME_LEN = 32
RUN_NAME_LEN = 64
SECTION_ALIGN = 64
RUN_CHARS = frozenset(b"ABCDEFGHIJKLMNOPQRSTUVWXYZabcdefghijklmnopqrstuvwxyz0123456789-_.")
# `flags` bit 0: every sample of the batch failed in the pipeline; the batch is announced
# all the same (no sections, no samples) so that every reader counts it.
LOST = 1

SECTION = np.dtype({
    "names": ["name", "dtype", "ndim", "shape", "offset", "len_bytes"],
    "formats": ["S32", "<u4", "<u4", ("<u8", (MAX_DIMS,)), "<u8", "<u8"],
    "offsets": [0, 32, 36, 40, 72, 80],
    "itemsize": 88,
})
HEADER = np.dtype({
    "names": ["magic", "version", "header_size", "section_count", "payload_len", "epoch",
              "step", "seed", "sequence", "created_unix_nanos", "sample_count", "flags",
              "run", "sections"],
    "formats": ["<u4", "<u4", "<u4", "<u4", "<u8", "<u8", "<u8", "<u8", "<u8", "<u8",
                "<u4", "<u4", "S64", (SECTION, (MAX_SECTIONS,))],
    "offsets": [0, 4, 8, 12, 16, 24, 32, 40, 48, 56, 64, 68, 72, 136],
    "itemsize": HEADER_SIZE,
})
DTYPES = {1: "<u1", 2: "<u2", 3: "<i4", 4: "<u4", 5: "<i8", 6: "<u8", 7: "<f4", 8: "<f8"}
assert HEADER.itemsize == HEADER_SIZE and SECTION.itemsize == 88


# The old names of two errors (one name per error now), kept for one release as the same
# classes with a DeprecationWarning.
DEPRECATED_NAMES = {"BatchFormatError": MalformedBatch, "FormatVersionError": FormatVersionMismatch}


def deprecated_name(module: str, name: str) -> Any:
    """The class an old error name stands for, with a DeprecationWarning; AttributeError
    for any other name (a module's ``__getattr__``)."""
    if name in DEPRECATED_NAMES:
        new = DEPRECATED_NAMES[name]
        warnings.warn(f"{module}.{name} is deprecated: it is {new.__name__} (superflow.{new.__name__})",
                      DeprecationWarning, stacklevel=3)
        return new
    raise AttributeError(f"module {module!r} has no attribute {name!r}")


def __getattr__(name: str) -> Any:
    return deprecated_name(__name__, name)


def _fail(rule: str, message: str) -> None:
    raise MalformedBatch(f"{rule}: {message}")


def _address(array: np.ndarray) -> int:
    return int(array.__array_interface__["data"][0])


def _nul_padded(field: bytes, rule: str, what: str) -> bytes:
    """The text of a NUL-padded fixed-size field whose last byte must be NUL."""
    end = field.find(b"\0")
    if end < 0:
        _fail(rule, f"{what} {field!r} is not NUL-terminated (uses all {len(field)} bytes)")
    if any(field[end:]):
        _fail(rule, f"{what} {field!r} is not NUL-padded (non-zero bytes after the first NUL)")
    return field[:end]


def read_batch(header_bytes: Any, payload: Any) -> tuple[np.void, dict[str, np.ndarray]]:
    """Validates a batch and returns ``(header record, {name: zero-copy array})``.

    Raises :class:`~superflow.MalformedBatch` (a ``ValueError``) when any rule of
    BATCH_FORMAT.md is broken; the batch is then rejected whole.
    """
    raw_header = np.frombuffer(header_bytes, dtype=np.uint8)
    if raw_header.size != HEADER_SIZE:
        _fail("rule 1", f"the header is {raw_header.size} bytes, this reader's BatchHeader is {HEADER_SIZE}")
    h = np.frombuffer(header_bytes, dtype=HEADER, count=1)[0]
    body = np.frombuffer(payload, dtype=np.uint8)
    base = _address(body)

    # Rule 1: constants and lengths.
    if int(h["magic"]) != MAGIC:
        _fail("rule 1", f"magic {int(h['magic']):#010x}, expected {MAGIC:#010x} (\"SFLB\")")
    if int(h["version"]) != VERSION:
        raise FormatVersionMismatch(
            f"rule 1: format version {int(h['version'])}, this reader knows version {VERSION} only",
            version=int(h["version"]))
    if int(h["header_size"]) != HEADER_SIZE:
        _fail("rule 1", f"header_size {int(h['header_size'])}, this reader's BatchHeader is {HEADER_SIZE}")
    count = int(h["section_count"])
    if count > MAX_SECTIONS:
        _fail("rule 1", f"section_count {count} exceeds {MAX_SECTIONS}")
    payload_len = int(h["payload_len"])
    if payload_len > body.size:
        _fail("rule 1", f"payload_len {payload_len} exceeds the {body.size}-byte payload received")

    # Header fields with fixed values; the one flag is LOST, on a batch with nothing in it.
    flags = int(h["flags"])
    if flags & ~LOST:
        _fail("header", f"flags {flags:#x}: version {VERSION} defines only LOST ({LOST:#x})")
    if flags & LOST and (count or payload_len or int(h["sample_count"])):
        _fail("header", f"a lost batch (flags {flags:#x}) has {count} sections, payload_len "
              f"{payload_len} and sample_count {int(h['sample_count'])}: all must be 0")
    run = _nul_padded(bytes(raw_header[72:72 + RUN_NAME_LEN]), "header", "run name")
    if not run or not set(run) <= RUN_CHARS:
        _fail("header", f"run name {run!r} must be 1 to 63 characters of A-Z a-z 0-9 - _ .")
    table = raw_header[136:].reshape(MAX_SECTIONS, SECTION.itemsize)
    for index in range(count, MAX_SECTIONS):
        if table[index].any():
            _fail("header", f"unused section entry #{index} is not all zero")

    # Rule 2: every used entry.
    sections = []  # (name, dtype, shape, offset, len_bytes)
    seen: set[str] = set()
    for index in range(count):
        s = h["sections"][index]
        raw_name = _nul_padded(bytes(table[index][:SECTION_NAME_LEN]), "rule 2", f"section #{index} name")
        try:
            name = raw_name.decode("utf-8")
        except UnicodeDecodeError:
            _fail("rule 2", f"section #{index} name {raw_name!r} is not UTF-8")
        label = f"section #{index} `{name}`"
        if not name:
            _fail("rule 2", f"section #{index} has an empty name")
        if name in seen:
            _fail("rule 2", f"{label}: name used twice")
        seen.add(name)
        code = int(s["dtype"])
        if code not in DTYPES:
            _fail("rule 2", f"{label}: unknown dtype code {code}")
        dtype = np.dtype(DTYPES[code])
        ndim = int(s["ndim"])
        if not 1 <= ndim <= MAX_DIMS:
            _fail("rule 2", f"{label}: ndim {ndim} is not in 1..{MAX_DIMS}")
        dims = [int(d) for d in s["shape"]]
        if any(dims[ndim:]):
            _fail("rule 2", f"{label}: shape entries past ndim are not zero: {dims}")
        shape = tuple(dims[:ndim])
        expected_len = math.prod(shape) * dtype.itemsize  # Python ints: no overflow
        len_bytes = int(s["len_bytes"])
        if len_bytes != expected_len:
            _fail("rule 2", f"{label}: len_bytes {len_bytes}, but shape {list(shape)} of {dtype.str} "
                  f"needs {expected_len}")
        offset = int(s["offset"])
        if offset % SECTION_ALIGN:
            _fail("section table", f"{label}: offset {offset} is not a multiple of {SECTION_ALIGN}")
        sections.append((name, dtype, shape, offset, len_bytes))

    # Rule 3: bounds, overlaps, alignment in memory.
    for name, dtype, _, offset, len_bytes in sections:
        if offset + len_bytes > payload_len:
            _fail("rule 3", f"section `{name}`: bytes {offset}..{offset + len_bytes} lie outside "
                  f"payload_len {payload_len}")
        if (base + offset) % dtype.itemsize:
            _fail("rule 3", f"section `{name}`: first byte at address {base + offset:#x} is not "
                  f"aligned to its {dtype.itemsize}-byte elements")
    filled = sorted((offset, offset + len_bytes, name) for name, _, _, offset, len_bytes in sections
                    if len_bytes > 0)  # an empty section holds no bytes, so overlaps nothing
    for (_, end_a, name_a), (start_b, _, name_b) in pairwise(filled):
        if start_b < end_a:
            _fail("rule 3", f"sections `{name_a}` and `{name_b}` overlap")

    # Rule 4: bytes of the payload (up to payload_len) not covered by a section are zero.
    cursor = 0
    for start, end, section in [*filled, (payload_len, payload_len, None)]:
        if start > cursor and body[cursor:start].any():
            where = f"before section `{section}`" if section else "after the last section"
            first = cursor + int(np.flatnonzero(body[cursor:start])[0])
            _fail("rule 4", f"padding byte {first} ({where}) is not zero")
        cursor = max(cursor, end)

    arrays: dict[str, np.ndarray] = {}
    for name, dtype, shape, offset, len_bytes in sections:
        array = np.frombuffer(payload, dtype=dtype, count=len_bytes // dtype.itemsize,
                              offset=offset).reshape(shape)
        # Zero copy: the array is the payload's own memory at the section's offset.
        assert _address(array) == base + offset, f"section `{name}` was copied"
        assert array.size == 0 or np.shares_memory(array, body), f"section `{name}` was copied"
        arrays[name] = array
    return h, arrays


def batch_meta(h: np.void) -> dict[str, Any]:
    """The stream fields of a header record as plain Python values."""
    return {
        "run": bytes(h["run"]).rstrip(b"\0").decode("ascii"),
        **{k: int(h[k]) for k in ("epoch", "step", "seed", "sequence", "created_unix_nanos",
                                  "sample_count", "flags")},
    }


def dtype_string(dtype: np.dtype) -> str:
    """The format document's numpy spelling of a section dtype (``<u1`` where numpy says ``|u1``)."""
    return next(text for text in DTYPES.values() if np.dtype(text) == dtype)
