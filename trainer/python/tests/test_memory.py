"""The copy-on-write mapping of a batch's memory, on a file of /dev/shm standing in for
the pipeline's segment (mapped shared and read-only, as iceoryx2 maps it)."""

from __future__ import annotations

import ctypes
import mmap
import os
from collections.abc import Iterator

import numpy as np
import pytest

from superflow import memory
from superflow.memory import PrivateView

SIZE = 64 * 4096


@pytest.fixture()
def segment(tmp_path_factory: pytest.TempPathFactory) -> Iterator[tuple[str, mmap.mmap]]:
    """A shared-memory file and its read-only shared mapping."""
    directory = "/dev/shm" if os.path.isdir("/dev/shm") else str(tmp_path_factory.mktemp("shm"))
    path = os.path.join(directory, f"superflow-test-{os.getpid()}")
    with open(path, "wb") as f:
        f.write(bytes(range(256)) * (SIZE // 256))
    fd = os.open(path, os.O_RDONLY)
    shared = mmap.mmap(fd, SIZE, flags=mmap.MAP_SHARED, prot=mmap.PROT_READ)
    os.close(fd)
    try:
        yield path, shared
    finally:
        shared.close()
        os.unlink(path)


def address_of(shared: mmap.mmap) -> int:
    view = np.frombuffer(shared, dtype=np.uint8)
    return int(view.__array_interface__["data"][0])


def test_writes_stay_private_and_copy_only_their_pages(segment: tuple[str, mmap.mmap]) -> None:
    path, shared = segment
    offset, length = 3 * 4096 + 100, 10 * 4096
    view = PrivateView(address_of(shared) + offset, length)
    assert view.mapped
    array = np.asarray(view)
    assert array.flags.writeable
    original = np.frombuffer(shared, dtype=np.uint8)[offset:offset + length]
    assert np.array_equal(array, original)
    array[:10] = 0
    assert not array[:10].any()
    # The file and its shared mapping are untouched.
    assert np.array_equal(np.frombuffer(shared, dtype=np.uint8)[offset:offset + 10],
                          np.arange(100, 110, dtype=np.uint8))
    with open(path, "rb") as f:
        f.seek(offset)
        assert f.read(10) == bytes(range(100, 110))


def test_unwritten_pages_follow_the_file_until_made_private(
        segment: tuple[str, mmap.mmap]) -> None:
    path, shared = segment
    view = PrivateView(address_of(shared), 8 * 4096)
    array = np.asarray(view)
    fd = os.open(path, os.O_RDWR)
    writer = mmap.mmap(fd, SIZE)
    os.close(fd)
    writer[0] = 7  # the pipeline reusing memory this process still maps
    assert array[0] == 7
    view.make_private()
    writer[0] = 9
    writer[4096] = 9
    assert array[0] == 7 and array[4096] == 0
    writer.close()


def test_without_a_file_to_map_the_bytes_are_copied(monkeypatch: pytest.MonkeyPatch) -> None:
    monkeypatch.setattr(memory, "_warned", False)
    anonymous = (ctypes.c_uint8 * 4096)(*range(256), *range(256))
    with pytest.warns(RuntimeWarning, match="copied"):
        view = PrivateView(ctypes.addressof(anonymous), 512)
    assert not view.mapped
    array = np.asarray(view)
    assert array.tolist() == list(range(256)) * 2
    array[0] = 99
    assert anonymous[0] == 0
