"""One received batch: its sections as numpy arrays over the batch's memory (a private
copy-on-write mapping of the pipeline's shared memory, see ``memory``), and the same as
torch tensors."""

from __future__ import annotations

import weakref
from typing import Any, cast

import numpy as np

from .errors import BatchReleased, FormatVersionMismatch, MalformedBatch
from .format import HEADER, LOST, batch_meta, read_batch
from .memory import Memory, PrivateView
from .sections import section_dtype


class SectionArray(np.ndarray):
    """A numpy view of a batch section. While it (or any array or tensor made from it
    without a copy) is alive, the batch's memory stays this process's: the batch's
    release hands it back to the pipeline only once the last view is gone. Writing to it
    is allowed and stays in this process (copy-on-write pages)."""


def header_bytes(sample: Any) -> np.ndarray:
    """The user header of a received sample, as bytes (a view, no copy)."""
    return np.ctypeslib.as_array(sample.user_header().contents.words).view(np.uint8)


def header_record(sample: Any) -> np.void:
    """The header record of a received sample, unchecked (for its position fields)."""
    return cast(np.void, np.frombuffer(header_bytes(sample), dtype=HEADER, count=1)[0])


def position_of(sample: Any) -> tuple[int, int]:
    """(epoch, step) of a received sample."""
    h = header_record(sample)
    return int(h["epoch"]), int(h["step"])


def _read(sample: Any, payload: np.ndarray, run: str,
          service: str) -> tuple[np.void, dict[str, np.ndarray]]:
    """The header and sections of a received sample (``payload``: its payload bytes),
    checked against the format and the section table; :class:`MalformedBatch` names the
    run and service otherwise."""
    where = f"run {run!r}, service {service!r}"
    try:
        h, arrays = read_batch(header_bytes(sample), payload)
    except FormatVersionMismatch as e:
        raise FormatVersionMismatch(f"{where}: {e}", run, service, e.version) from None
    except MalformedBatch as e:
        raise MalformedBatch(f"{where}: {e}", run, service) from None
    for name, array in arrays.items():
        want = section_dtype(name)
        if want is None:
            raise MalformedBatch(f"{where}: section `{name}` is not a section of the SuperFlow "
                                 "batch format", run, service)
        if array.dtype != want:
            raise MalformedBatch(f"{where}: section `{name}` is {array.dtype.str}, the format "
                                 f"says {want.str}", run, service)
    return h, arrays


class Batch:
    """One batch of SuperFlow samples, its sections numpy arrays with no copy.

    ``epoch``, ``step``, ``sequence`` (publisher-wide counter), ``seed``, ``run``;
    ``sample_ids``: each sample's index in its epoch; ``keyframes``: each sample's
    keyframe index in the drive (the full rows are ``batch["sample_ids"]``: epoch,
    index in epoch, keyframe, drive, sweep); ``cameras``: each sample's camera count
    (samples of different rigs have different counts, and only their own images).
    ``batch[name]`` is a section (see ``names()``); ``batch.torch()`` the same as
    ``torch.Tensor``s sharing the memory; ``batch.sample_images(b)`` sample ``b``'s
    images as ``F×K_b×H×W×3``. ``lost``: every sample of this batch failed in the
    pipeline (its log says why): it has no sections and ``len(batch) == 0``, and it is
    still yielded so that every rank counts the same batches.

    The sections may be written in place (``batch.torch()["images"].sub_(mean)``): the
    pages written are copied into this process (copy-on-write); the pipeline and other
    readers never see the change.
    """

    def __init__(self, sample: Any, run: str, service: str, held: set[Memory] | None = None,
                 port: Any = None):
        self.run_service = (run, service)
        payload = sample.payload()
        try:
            h = header_record(sample)
            lost = bool(int(h["flags"]) & LOST) and int(h["payload_len"]) == 0
            view = PrivateView(payload.as_ptr(), 0 if lost else payload.len())
            h, arrays = _read(sample, np.asarray(view), run, service)
        except MalformedBatch:
            # Hand the memory back: the stream goes on with the next batch.
            sample.delete()
            raise
        meta = batch_meta(h)
        self.epoch: int = meta["epoch"]
        self.step: int = meta["step"]
        self.sequence: int = meta["sequence"]
        self.seed: int = meta["seed"]
        self.run: str = meta["run"]
        self.lost: bool = bool(meta["flags"] & LOST)
        self.publisher: int = sample.header.publisher_id.value
        # Set by the stream from the pipeline's schedule (None while it is unknown).
        self.last_in_epoch: bool | None = None
        self.last_in_stream: bool | None = None
        self._memory = Memory(sample, (self.epoch, self.step),
                              set() if held is None else held, port, view)
        self._mapped = (view.address, view.address + view.length)
        # Runs when the last view of the payload is gone (at once if the batch has none);
        # not at interpreter exit, when iceoryx2 may already be torn down (the process's
        # ports go with it then).
        weakref.finalize(view, self._memory.views_gone).atexit = False
        self._arrays: dict[str, SectionArray] = {
            name: array.view(SectionArray) for name, array in arrays.items()}
        del view, arrays
        ids = self._arrays.get("sample_ids", np.zeros((0, 5), np.uint64))
        self.sample_ids: list[int] = [int(i) for i in ids[:, 1]]
        self.keyframes: list[int] = [int(k) for k in ids[:, 2]]
        del ids
        slots = self._arrays.get("sample_cameras", np.zeros(1, np.uint32))
        self.cameras: list[int] = [int(k) for k in np.diff(slots.astype(np.int64))]
        self._first_slot: list[int] = [int(s) for s in slots]
        del slots

    @property
    def _sample(self) -> Any:
        """The iceoryx2 sample while this process holds its memory, else None."""
        return self._memory.sample

    @property
    def released(self) -> bool:
        """Whether the batch was released (its views taken before stay valid)."""
        return self._memory.released

    @property
    def returned(self) -> bool:
        """Whether the batch's shared memory went back to the pipeline (released, and no
        view of it alive)."""
        return self._memory.sample is None

    def __len__(self) -> int:
        """The samples of the batch (0 for a lost batch)."""
        return len(self.sample_ids)

    def __bool__(self) -> bool:
        # A lost batch has no samples but is still a batch (`if batch:` stays true).
        return True

    def names(self) -> list[str]:
        """Every section name, in payload order."""
        return list(self._arrays)

    def __contains__(self, name: str) -> bool:
        return name in self._arrays

    def _check(self) -> None:
        if self._memory.released:
            raise BatchReleased(
                f"batch (epoch {self.epoch}, step {self.step}) of run {self.run_service[0]!r} "
                "was released: take sections before releasing it (views taken before stay valid)",
                *self.run_service)

    def __getitem__(self, name: str) -> SectionArray:
        self._check()
        try:
            return self._arrays[name]
        except KeyError:
            if self.lost:
                raise KeyError(f"batch (epoch {self.epoch}, step {self.step}) is lost: every "
                               "sample failed in the pipeline (its log says why), so it has no "
                               "sections; check batch.lost") from None
            raise KeyError(f"no section `{name}` in this batch (sections: {', '.join(self._arrays)})") from None

    def image_index(self, sample: int, frame: int, camera: int) -> int:
        """The row of ``images`` (and ``superpixels``, ``image_stamps``, the number in
        ``pairing_image``) of camera slot ``camera`` of ``frame`` of ``sample``:
        ``F · sample_cameras[b] + f · K_b + k``."""
        frames = len(self["frame_offsets"])
        if not (0 <= sample < len(self.cameras) and 0 <= frame < frames
                and 0 <= camera < self.cameras[sample]):
            raise IndexError(f"no image (sample {sample}, frame {frame}, camera {camera}): the "
                             f"batch has {len(self.cameras)} samples of {frames} frames, with "
                             f"{self.cameras} cameras")
        return frames * self._first_slot[sample] + frame * self.cameras[sample] + camera

    def sample_images(self, sample: int, name: str = "images") -> SectionArray:
        """Sample ``sample``'s rows of an image section (``images``, ``superpixels``,
        ``image_stamps``, ``image_flipped``) as ``F × K_b × ...``: a view, no copy."""
        first = self.image_index(sample, 0, 0)
        frames = len(self["frame_offsets"])
        rows = self[name][first:first + frames * self.cameras[sample]]
        return cast(SectionArray, rows.reshape((frames, self.cameras[sample], *rows.shape[1:])))

    def torch(self) -> dict[str, Any]:
        """Every section as a ``torch.Tensor`` sharing the batch's memory
        (``torch.from_numpy``, no copy); ``{}`` for a lost batch. In-place ops are fine:
        they copy the pages they write into this process. A tensor kept past the release
        keeps the memory from going back to the pipeline until it is gone (``max_held``
        bounds how many batches a stream holds that way): copy what you keep for long
        (``.clone()``, or ``.to(device)``)."""
        self._check()
        import torch  # optional dependency: pip install superflow[torch]

        return {name: torch.from_numpy(a.view(np.ndarray)) for name, a in self._arrays.items()}

    def release(self) -> None:
        """Hands the batch's memory back to the pipeline, at once or, while views of it are
        alive, when the last one is garbage-collected."""
        if self._memory.released:
            return
        self._arrays = {}
        self._memory.release()

    def __enter__(self) -> Batch:
        return self

    def __exit__(self, *exc: Any) -> None:
        self.release()

    def __repr__(self) -> str:
        if self.lost:
            state = "lost"
        elif not self.released:
            state = f"{len(self._arrays)} sections"
        else:
            state = "released" if self.returned else "released, views alive"
        return f"Batch(run={self.run!r}, epoch={self.epoch}, step={self.step}, {state})"
