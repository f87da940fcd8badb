"""A received batch's memory, as this process sees it.

iceoryx2 maps the pipeline's shared memory read-only into a subscriber, and torch has no
read-only tensors: an in-place op on a tensor over that mapping (``img.sub_(mean)``)
would kill the process. So each batch's payload is mapped a second time, *privately*:
the same file pages, copy-on-write (``MAP_PRIVATE``). Reading costs what reading the
shared mapping costs (the pages are shared until written); a write copies only the
pages it touches, into this process, and the pipeline and the other readers never see
it. Until the batch's memory goes back to the pipeline every untouched page still reads
the pipeline's bytes; before a hand-back that views outlive (``Stream.close``) every
page is made private first (:meth:`Memory.detach`).

Where the file is comes from ``/proc/self/maps`` (the shared mapping's path and file
offset). Where that is unavailable (not Linux) the payload is copied once into private
memory instead, with a warning.
"""

from __future__ import annotations

import ctypes
import mmap
import os
import threading
import warnings
import weakref
from typing import Any

import numpy as np

_PAGE = mmap.ALLOCATIONGRANULARITY


class _Segment:
    """A shared-memory mapping of this process: its address range and the file (path,
    file offset of its start, device and inode) it maps."""

    __slots__ = ("dev", "high", "inode", "low", "offset", "path", "span")

    def __init__(self, line: str):
        parts = line.split(maxsplit=5)
        low, high = parts[0].split("-")
        self.span = parts[0]
        self.low, self.high = int(low, 16), int(high, 16)
        self.offset = int(parts[2], 16)
        major, minor = (int(x, 16) for x in parts[3].split(":"))
        self.dev = os.makedev(major, minor)
        self.inode = int(parts[4])
        self.path = parts[5].strip() if len(parts) > 5 else ""


class _Segments:
    """The process's shared-memory mappings, looked up by address; ``/proc/self/maps``
    is read again only for an address outside those known (a new publisher's segment)."""

    def __init__(self) -> None:
        self._known: list[_Segment] = []
        self._lock = threading.Lock()

    def find(self, address: int, fresh: bool = False) -> _Segment | None:
        """The mapping holding ``address``; ``fresh``: read the process's maps again (an
        address range unmapped and reused by another file)."""
        with self._lock:
            for segment in [] if fresh else self._known:
                if segment.low <= address < segment.high:
                    return segment
            try:
                with open("/proc/self/maps") as maps:
                    lines = [line for line in maps if " r--s " in line or " rw-s " in line]
            except OSError:
                return None
            self._known = [_Segment(line) for line in lines]
            for segment in self._known:
                if segment.low <= address < segment.high:
                    return segment
            return None


_segments = _Segments()
_warned = False


def _open_segment(segment: _Segment) -> int | None:
    """A read-only descriptor of the file ``segment`` maps (checked by device and inode:
    a path reused by a newer file is not it), or None."""
    candidates = []
    if segment.path.startswith("/") and not segment.path.endswith("(deleted)"):
        candidates.append(segment.path)
    # The mapping itself, even once its name is unlinked (needs CAP_SYS_ADMIN or
    # CAP_CHECKPOINT_RESTORE; root has them).
    candidates.append(f"/proc/self/map_files/{segment.span}")
    for path in candidates:
        try:
            fd = os.open(path, os.O_RDONLY | os.O_CLOEXEC)
        except OSError:
            continue
        info = os.fstat(fd)
        if (info.st_dev, info.st_ino) == (segment.dev, segment.inode):
            return fd
        os.close(fd)
    return None


class PrivateView:
    """``length`` bytes at ``address`` of a shared mapping, mapped again copy-on-write
    (or copied, see the module docs). ``address`` is where they start in this mapping.
    Views of a batch refer to it (numpy's ``base`` chain, torch's storage); the mapping
    goes when the last one does."""

    __slots__ = ("__array_interface__", "__weakref__", "_anchor", "_map", "address", "length")

    def __init__(self, address: int, length: int):
        self.length = length
        self._map: Any = None
        self._anchor: Any = None
        data = self._map_private(address, length) if length else None
        if data is None:
            data = self._copy(address, length)
        self.address = data
        self.__array_interface__ = {"shape": (length,), "typestr": "|u1",
                                    "data": (data, False), "version": 3}

    def _map_private(self, address: int, length: int) -> int | None:
        fd = None
        for fresh in (False, True):
            segment = _segments.find(address, fresh)
            if segment is None or address + length > segment.high:
                continue
            fd = _open_segment(segment)
            if fd is not None:
                break
        if fd is None or segment is None:
            return None
        try:
            start = segment.offset + (address - segment.low)
            aligned = start - start % _PAGE
            self._map = mmap.mmap(fd, length + (start - aligned), flags=mmap.MAP_PRIVATE,
                                  prot=mmap.PROT_READ | mmap.PROT_WRITE, offset=aligned)
        except (OSError, ValueError):
            return None
        finally:
            os.close(fd)
        self._anchor = ctypes.c_char.from_buffer(self._map)
        return ctypes.addressof(self._anchor) + (start - aligned)

    def _copy(self, address: int, length: int) -> int:
        global _warned
        if not _warned and length:
            _warned = True
            warnings.warn("superflow: the shared memory could not be mapped copy-on-write "
                          "(no /proc/self/maps?): each batch is copied once into this "
                          "process instead", RuntimeWarning, stacklevel=4)
        self._anchor = (ctypes.c_char * max(length, 1))()
        if length:
            ctypes.memmove(self._anchor, address, length)
        return ctypes.addressof(self._anchor)

    @property
    def mapped(self) -> bool:
        """Whether this is a copy-on-write mapping of the shared memory (not a copy)."""
        return self._map is not None

    def make_private(self) -> None:
        """Copies every page still shared with the pipeline into this process (a write to
        each page), so the bytes stay once the pipeline reuses its memory."""
        if self._map is None:
            return
        pages = np.frombuffer(self._map, dtype=np.uint8)
        pages[::_PAGE] = pages[::_PAGE].copy()
        del pages


class Memory:
    """A received sample's shared memory: handed back to the pipeline (``sample.delete()``)
    when the batch is released and its views are gone, whichever comes last."""

    __slots__ = ("held", "port", "position", "released", "sample", "view", "views_alive")

    def __init__(self, sample: Any, position: tuple[int, int], held: set[Memory], port: Any,
                 view: PrivateView | None):
        self.sample = sample
        self.port = port  # the subscriber it came from, kept open until the hand-back
        self.released = False
        self.views_alive = True
        self.position = position
        self.held = held
            # Weakly: the views own the mapping; this only reaches it to detach them.
        self.view = None if view is None else weakref.ref(view)
        held.add(self)

    def release(self) -> None:
        self.released = True
        if not self.views_alive:
            self._hand_back()

    def views_gone(self) -> None:
        self.views_alive = False
        if self.released:
            self._hand_back()

    def detach(self) -> None:
        """Hands the memory back now, whatever views are alive: they keep private copies
        of the pages they had not written yet."""
        view = self.view() if self.view is not None else None
        if view is not None:
            view.make_private()
        self.released = True
        self._hand_back()

    def _hand_back(self) -> None:
        sample, self.sample = self.sample, None
        self.held.discard(self)
        if sample is not None:
            sample.delete()
        self.port = None

