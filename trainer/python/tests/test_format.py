"""``read_batch`` against the rules of BATCH_FORMAT.md, with no pipeline: the errors it
raises, their one name each, and the deprecated old names."""

import warnings

import numpy as np
import pytest

import superflow
import superflow.format as fmt


def header(version: int = fmt.VERSION) -> bytes:
    """A header of an empty batch (no sections, no payload) in format ``version``."""
    h = np.zeros(1, dtype=fmt.HEADER)
    h["magic"] = fmt.MAGIC
    h["version"] = version
    h["header_size"] = fmt.HEADER_SIZE
    h["run"] = b"run"
    return h.tobytes()


def test_an_empty_batch_reads() -> None:
    record, arrays = superflow.read_batch(header(), np.zeros(0, dtype=np.uint8))
    assert int(record["version"]) == fmt.VERSION and arrays == {}


def test_a_bad_magic_is_a_malformed_batch_naming_the_rule() -> None:
    raw = bytearray(header())
    raw[0] ^= 0xFF
    with pytest.raises(superflow.MalformedBatch, match="rule 1: magic") as e:
        superflow.read_batch(bytes(raw), np.zeros(0, dtype=np.uint8))
    assert isinstance(e.value, ValueError) and isinstance(e.value, superflow.SuperflowError)


def test_a_short_header_is_a_malformed_batch() -> None:
    with pytest.raises(superflow.MalformedBatch, match=f"this reader's BatchHeader is {fmt.HEADER_SIZE}"):
        superflow.read_batch(header()[:100], np.zeros(0, dtype=np.uint8))


def test_another_format_version_carries_its_version() -> None:
    with pytest.raises(superflow.FormatVersionMismatch, match="format version 7") as e:
        superflow.read_batch(header(version=7), np.zeros(0, dtype=np.uint8))
    assert e.value.version == 7
    assert isinstance(e.value, superflow.MalformedBatch)


@pytest.mark.parametrize(("old", "new"), [("BatchFormatError", "MalformedBatch"),
                                          ("FormatVersionError", "FormatVersionMismatch")])
def test_the_old_names_are_the_same_classes_and_warn(old: str, new: str) -> None:
    for module in (superflow, fmt):
        with pytest.warns(DeprecationWarning, match=f"{old} is deprecated: it is {new}"):
            assert getattr(module, old) is getattr(superflow, new)
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        getattr(superflow, new)
    with pytest.raises(AttributeError):
        _ = superflow.NoSuchName  # type: ignore[attr-defined]
