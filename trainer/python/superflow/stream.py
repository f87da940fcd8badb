"""Receiving batches from a running ``superflow-pipeline`` over iceoryx2 shared memory.

A :class:`Stream` subscribes to one run's batches (broadcast, or one rank's shard) and
yields :class:`Batch` objects whose sections are numpy arrays *inside* the shared memory:
nothing is copied. The lifetime rule: a batch's shared memory goes back to the pipeline
only when the batch is released (``batch.release()``, the end of a ``with batch:``
block, or the next iteration) *and* no view of it is alive (its numpy sections, the
tensors of ``batch.torch()``, anything made from them without a copy). A view kept past
the release stays valid; the hand-back waits until the last one is garbage-collected.
A stream holds at most ``max_held`` batches that way; the receive that would hold more
raises :class:`TooManyBatchesHeld` naming them.
"""

from __future__ import annotations

import ctypes
import gc
import os
import time
import warnings
import weakref
from typing import Any, Iterator, NamedTuple

import iceoryx2 as iox2
import numpy as np

from .format import (HEADER, HEADER_SIZE, RUN_CHARS, BatchFormatError, FormatVersionError,
                     batch_meta, read_batch)
from .sections import section_dtype

# The service settings every superflow process uses (schemas/src/service.rs, `qos`):
# iceoryx2 refuses to open a service with other ones. MAX_BORROWED bounds the batches a
# subscriber holds at once, so `max_held` too.
MAX_SUBSCRIBERS, MAX_BUFFER, MAX_BORROWED, MAX_PUBLISHERS, MAX_NODES = 8, 4, 2, 2, 16

# How long one wait on the ready event lasts before the queue is looked at again (a
# wake-up sent before the listener existed is not lost).
_WAIT_SLICE_MS = 100


class SuperflowError(Exception):
    """An error of a stream; ``run`` and ``service`` name where it happened."""

    def __init__(self, message: str, run: str = "", service: str = ""):
        super().__init__(message)
        self.run = run
        self.service = service


class PipelineTimeout(SuperflowError, TimeoutError):
    """No batch arrived within the stream's ``timeout_s``."""


class MalformedBatch(SuperflowError, ValueError):
    """A received batch breaks the batch format (the message names the rule and section)."""


class FormatVersionMismatch(MalformedBatch):
    """A received batch was written in another version of the batch format."""

    def __init__(self, message: str, run: str, service: str, version: int):
        super().__init__(message, run, service)
        self.version = version


class BatchReleased(SuperflowError, RuntimeError):
    """A released batch was asked for a section (``batch[name]``, ``batch.torch()``).
    Views taken before the release stay valid."""


class TooManyBatchesHeld(SuperflowError, RuntimeError):
    """Receiving another batch would hold more than the stream's ``max_held``: released
    batches whose views are still alive keep their shared memory. ``held`` lists their
    ``(epoch, step)``."""

    def __init__(self, message: str, run: str, service: str, held: list[tuple[int, int]]):
        super().__init__(message, run, service)
        self.held = held


class ResumeRefused(SuperflowError):
    """The pipeline refused to move the stream (no such stream, or past the last epoch)."""


class _BatchHeader(ctypes.Structure):
    """The 11 400-byte user header, as opaque 8-byte words (the format module parses it)."""

    _fields_ = [("words", ctypes.c_uint64 * (HEADER_SIZE // 8))]

    @staticmethod
    def type_name() -> str:
        return "superflow::BatchHeader"


# A field of a resume request that is not known (schemas/src/service.rs `UNKNOWN`).
_UNKNOWN = (1 << 64) - 1


class _ResumeRequest(ctypes.Structure):
    """`superflow::ResumeRequest` (schemas/src/service.rs)."""

    _fields_ = [("rank", ctypes.c_uint32), ("broadcast", ctypes.c_uint32),
                ("epoch", ctypes.c_uint64), ("step", ctypes.c_uint64),
                ("sample", ctypes.c_uint64), ("global_batch", ctypes.c_uint64)]

    @staticmethod
    def type_name() -> str:
        return "superflow::ResumeRequest"


class _ResumeReply(ctypes.Structure):
    """`superflow::ResumeReply` (schemas/src/service.rs)."""

    _fields_ = [("accepted", ctypes.c_uint32), ("reason", ctypes.c_uint32),
                ("next_sequence", ctypes.c_uint64), ("publisher_lo", ctypes.c_uint64),
                ("publisher_hi", ctypes.c_uint64), ("epoch", ctypes.c_uint64),
                ("step", ctypes.c_uint64)]

    @staticmethod
    def type_name() -> str:
        return "superflow::ResumeReply"


class _ScheduleRequest(ctypes.Structure):
    """`superflow::ScheduleRequest` (schemas/src/service.rs)."""

    _fields_ = [("rank", ctypes.c_uint32), ("broadcast", ctypes.c_uint32)]

    @staticmethod
    def type_name() -> str:
        return "superflow::ScheduleRequest"


class _ScheduleReply(ctypes.Structure):
    """`superflow::ScheduleReply` (schemas/src/service.rs)."""

    _fields_ = [("known", ctypes.c_uint32), ("reserved", ctypes.c_uint32),
                ("steps", ctypes.c_uint64), ("min_steps", ctypes.c_uint64),
                ("epochs", ctypes.c_uint64), ("publisher_lo", ctypes.c_uint64),
                ("publisher_hi", ctypes.c_uint64), ("samples", ctypes.c_uint64),
                ("global_batch", ctypes.c_uint64), ("start_epoch", ctypes.c_uint64),
                ("start_sample", ctypes.c_uint64), ("start_steps", ctypes.c_uint64),
                ("start_min_steps", ctypes.c_uint64)]

    @staticmethod
    def type_name() -> str:
        return "superflow::ScheduleReply"


class Schedule(NamedTuple):
    """How the pipeline schedules this stream: ``steps`` batches per epoch (this rank's),
    ``min_steps`` the fewest of any rank, ``epochs`` served (0: endless), the
    ``publisher`` (pipeline process) that said so; ``samples`` per epoch and
    ``global_batch`` samples per step of the whole job (every rank and host); epoch
    ``start_epoch`` starts at sample ``start_sample`` (a job resumed on another size),
    with ``start_steps`` / ``start_min_steps`` batches."""

    steps: int
    min_steps: int
    epochs: int
    publisher: int
    samples: int = 0
    global_batch: int = 0
    start_epoch: int = 0
    start_sample: int = 0
    start_steps: int = 0
    start_min_steps: int = 0

    def _part_way(self, epoch: int) -> bool:
        return epoch == self.start_epoch and self.start_sample > 0

    def steps_in(self, epoch: int) -> int:
        """This rank's batches in ``epoch``."""
        return self.start_steps if self._part_way(epoch) else self.steps

    def min_steps_in(self, epoch: int) -> int:
        """The fewest batches of any rank in ``epoch``."""
        return self.start_min_steps if self._part_way(epoch) else self.min_steps

    def consumed(self, epoch: int, steps: int) -> int:
        """Samples of ``epoch`` the whole job has consumed once every rank took its first
        ``steps`` batches of it (data-parallel ranks step together): what a checkpoint
        keeps to resume on any number of ranks."""
        first = min(self.start_sample, self.samples) if self._part_way(epoch) else 0
        return first + min(steps * self.global_batch, self.samples - first)


# How long a stream waits for the schedule of a pipeline that just sent it a batch (it
# answers from a thread of its own); without an answer the stream does not know where
# epochs end and goes on without ending.
_SCHEDULE_WAIT_S = 5.0

_REFUSALS = {1: "no such stream (rank out of range, or the pipeline runs in the other mode)",
             2: "the position is past the end of the configured epochs",
             3: "the step was saved by a job of another size: resume by sample "
                "(stream.resume(epoch, sample=...), or load_state_dict of a state_dict)"}


class SectionArray(np.ndarray):
    """A read-only numpy view into a batch's shared memory. While it (or any array or
    tensor made from it without a copy) is alive, the memory stays this process's: the
    batch's release hands it back to the pipeline only once the last view is gone."""


class _Buffer:
    """The payload of one received sample as a numpy-readable buffer. Every view of the
    batch refers to it (through numpy's ``base`` chain, and torch's storage for
    ``torch.from_numpy``), so its finalizer runs when the last view is gone."""

    __slots__ = ("__array_interface__", "__weakref__")

    def __init__(self, address: int, length: int):
        self.__array_interface__ = {"shape": (length,), "typestr": "|u1",
                                    "data": (address, True), "version": 3}


class _Memory:
    """A received sample's shared memory: handed back to the pipeline (``sample.delete()``)
    when the batch is released and its views are gone, whichever comes last."""

    __slots__ = ("sample", "released", "views_alive", "position", "held", "port")

    def __init__(self, sample: Any, position: tuple[int, int], held: set[_Memory], port: Any):
        self.sample = sample
        self.port = port  # the subscriber it came from, kept open until the hand-back
        self.released = False
        self.views_alive = True
        self.position = position
        self.held = held
        held.add(self)

    def release(self) -> None:
        self.released = True
        if not self.views_alive:
            self._hand_back()

    def views_gone(self) -> None:
        self.views_alive = False
        if self.released:
            self._hand_back()

    def _hand_back(self) -> None:
        sample, self.sample = self.sample, None
        self.held.discard(self)
        if sample is not None:
            sample.delete()
        self.port = None


def _header_bytes(sample: Any) -> np.ndarray:
    """The user header of a received sample, as bytes (a view, no copy)."""
    return np.ctypeslib.as_array(sample.user_header().contents.words).view(np.uint8)


def _header(sample: Any) -> np.void:
    """The header record of a received sample, unchecked (for its position fields)."""
    return np.frombuffer(_header_bytes(sample), dtype=HEADER, count=1)[0]


def _position(sample: Any) -> tuple[int, int]:
    """(epoch, step) of a received sample."""
    h = _header(sample)
    return int(h["epoch"]), int(h["step"])


def _step_at(schedule: Schedule, epoch: int, sample: int) -> int:
    """The step at which a resume after ``sample`` samples of ``epoch`` continues: a step
    boundary of ``schedule``, or 0 when the pipeline will start the epoch there."""
    first = schedule.start_sample if schedule._part_way(epoch) else 0
    taken = sample - first
    if schedule.global_batch <= 0 or taken < 0:
        return 0
    if taken % schedule.global_batch == 0:
        return taken // schedule.global_batch
    if sample == schedule.samples:
        return -(-taken // schedule.global_batch)
    return 0


def _read(sample: Any, payload: np.ndarray, run: str,
          service: str) -> tuple[np.void, dict[str, np.ndarray]]:
    """The header and sections of a received sample (``payload``: its payload bytes),
    checked against the format and the section table; :class:`MalformedBatch` names the
    run and service otherwise."""
    header = _header_bytes(sample)
    where = f"run {run!r}, service {service!r}"
    try:
        h, arrays = read_batch(header, payload)
    except FormatVersionError as e:
        raise FormatVersionMismatch(f"{where}: {e}", run, service, e.version) from None
    except BatchFormatError as e:
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
    """One batch of SuperFlow samples, its sections zero-copy numpy arrays.

    ``epoch``, ``step``, ``sequence`` (publisher-wide counter), ``seed``, ``run``;
    ``sample_ids``: each sample's index in its epoch; ``keyframes``: each sample's
    keyframe index in the drive (the full rows are ``batch["sample_ids"]``: epoch,
    index in epoch, keyframe, drive, sweep); ``cameras``: each sample's camera count
    (samples of different rigs have different counts, and only their own images).
    ``batch[name]`` is a section (see ``names()``); ``batch.torch()`` the same as
    ``torch.Tensor``s sharing the memory; ``batch.sample_images(b)`` sample ``b``'s
    images as ``F×K_b×H×W×3``.
    """

    def __init__(self, sample: Any, run: str, service: str, held: set[_Memory] | None = None,
                 port: Any = None):
        self.run_service = (run, service)
        payload = sample.payload()
        buffer = _Buffer(payload.as_ptr(), payload.len())
        try:
            h, arrays = _read(sample, np.asarray(buffer), run, service)
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
        self.publisher: int = sample.header.publisher_id.value
        # Set by the stream from the pipeline's schedule (None while it is unknown).
        self.last_in_epoch: bool | None = None
        self.last_in_stream: bool | None = None
        self._memory = _Memory(sample, (self.epoch, self.step),
                              set() if held is None else held, port)
        # Runs when the last view of the payload is gone (at once if the batch has none);
        # not at interpreter exit, when iceoryx2 may already be torn down (the process's
        # ports go with it then).
        weakref.finalize(buffer, self._memory.views_gone).atexit = False
        self._arrays: dict[str, SectionArray] = {
            name: array.view(SectionArray) for name, array in arrays.items()}
        del buffer, arrays
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
            raise KeyError(f"no section `{name}` in this batch (sections: {', '.join(self._arrays)})")

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
        return rows.reshape((frames, self.cameras[sample]) + rows.shape[1:])

    def torch(self) -> dict[str, Any]:
        """Every section as a ``torch.Tensor`` sharing the shared memory (``torch.from_numpy``,
        no copy). The memory is the pipeline's: read it, do not write it. A tensor kept past
        the release keeps the memory from going back to the pipeline until it is gone
        (``max_held`` bounds how many batches a stream holds that way): copy what you keep
        for long (``.clone()``, or ``.to(device)``)."""
        self._check()
        import torch  # optional dependency: pip install superflow[torch]

        with warnings.catch_warnings():
            # The views are read-only; torch warns that its tensors would not be.
            warnings.simplefilter("ignore", UserWarning)
            return {name: torch.from_numpy(np.asarray(a)) for name, a in self._arrays.items()}

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
        if not self.released:
            state = f"{len(self._arrays)} sections"
        else:
            state = "released" if self.returned else "released, views alive"
        return f"Batch(run={self.run!r}, epoch={self.epoch}, step={self.step}, {state})"


def _env_int(name: str) -> int | None:
    value = os.environ.get(name)
    if value is None or value == "":
        return None
    try:
        return int(value)
    except ValueError:
        raise ValueError(f"environment variable {name}={value!r} is not an integer") from None


class Stream:
    """The batches of run ``run`` from a ``superflow-pipeline``.

    ``rank`` / ``world_size`` select the shard stream ``superflow/<run>/rank/<rank>`` of a
    pipeline started with ``--world-size W``; by default they are the ``RANK`` /
    ``WORLD_SIZE`` environment variables that torchrun sets, when ``WORLD_SIZE`` is above 1
    (a single process reads the broadcast stream ``superflow/<run>/batches``, as it does
    without them). ``prefix`` is the iceoryx2 prefix of the deployment
    (default ``SUPERFLOW_IOX_PREFIX``). ``timeout_s``: how long to wait for a batch
    before raising :class:`PipelineTimeout` (None: wait as long as it takes). Waiting
    blocks on the pipeline's ready event; nothing spins.

    Iterating yields :class:`Batch` objects; each iteration releases the batch before.
    When the pipeline is restarted (another publisher), the stream asks it to continue
    after the last batch received, so the steps go on where they were (``auto_resume``).

    ``max_held`` (1 to ``MAX_BORROWED``, 2): how many batches the stream may hold at once,
    the current one and released ones whose views (numpy sections, ``batch.torch()``
    tensors) are still alive. The receive that would hold more raises
    :class:`TooManyBatchesHeld`; views never read memory the pipeline reused.
    """

    def __init__(self, run: str, rank: int | None = None, world_size: int | None = None,
                 prefix: str | None = None, timeout_s: float | None = None, buffer: int = 2,
                 auto_resume: bool = True, max_held: int = MAX_BORROWED):
        if not 1 <= max_held <= MAX_BORROWED:
            raise ValueError(f"max_held {max_held} must be 1 to {MAX_BORROWED} (the service's "
                             "subscriber_max_borrowed_samples)")
        if not (1 <= len(run) <= 63 and set(run.encode()) <= RUN_CHARS):
            raise ValueError(f"run name {run!r} must be 1 to 63 characters of A-Z a-z 0-9 - _ .")
        world_size = _env_int("WORLD_SIZE") if world_size is None else world_size
        if rank is None and world_size is not None and world_size > 1:
            rank = _env_int("RANK")
            if rank is None:
                raise ValueError(f"world size {world_size} without a rank (set RANK or pass rank=)")
        if rank is not None and (rank < 0 or (world_size is not None and rank >= world_size)):
            raise ValueError(f"rank {rank} is outside world size {world_size}")
        self.run = run
        self.rank = rank
        self.world_size = world_size
        self.timeout_s = timeout_s
        self.auto_resume = auto_resume
        self.service = f"superflow/{run}/batches" if rank is None else f"superflow/{run}/rank/{rank}"
        prefix = os.environ.get("SUPERFLOW_IOX_PREFIX") if prefix is None else prefix
        config = iox2.config.default()
        if prefix:
            config.global_cfg.prefix = iox2.FileName.new(prefix + "_")
        try:
            self._node = iox2.NodeBuilder.new().config(config).create(iox2.ServiceType.Ipc)
            self._batches = (
                self._node.service_builder(iox2.ServiceName.new(self.service))
                .publish_subscribe(iox2.Slice[ctypes.c_uint8])
                .user_header(_BatchHeader)
                .enable_safe_overflow(False)
                .history_size(0)
                .subscriber_max_buffer_size(MAX_BUFFER)
                .subscriber_max_borrowed_samples(MAX_BORROWED)
                .max_subscribers(MAX_SUBSCRIBERS)
                .max_publishers(MAX_PUBLISHERS)
                .max_nodes(MAX_NODES)
                .open_or_create()
            )
            self._ready = (
                self._node.service_builder(iox2.ServiceName.new(self.service + "/ready"))
                .event()
                .max_nodes(MAX_NODES)
                .max_listeners(MAX_SUBSCRIBERS)
                .max_notifiers(MAX_PUBLISHERS)
                .open_or_create()
            )
            self._subscriber = (self._batches.subscriber_builder()
                                .buffer_size(max(1, min(buffer, MAX_BUFFER))).create())
            self._listener = self._ready.listener_builder().create()
        except Exception as e:
            raise SuperflowError(f"run {run!r}: opening {self.service!r}: {e}", run, self.service) from e
        self.max_held = max_held
        self._held: set[_Memory] = set()
        self._current: Batch | None = None
        self._pending: Batch | None = None  # received, handed out by the next next()
        self._stash: Any = None
        self._schedule: Schedule | None = None
        self._schedule_client: Any = None
        self._schedule_missing: set[int] = set()  # publishers that did not answer
        self._position: tuple[int, int] | None = None  # of the next batch, once known
        self._ended = False
        self._last: tuple[int, int, int] | None = None  # publisher, epoch, step
        # After a resume: batches of that publisher numbered below this belong to the old
        # position (one may still be on its way when the answer comes): dropped.
        self._floor: tuple[int, int] | None = None

    # -- receiving -------------------------------------------------------------------

    def _receive_sample(self) -> Any:
        try:
            return self._subscriber.receive()
        except Exception as e:
            raise SuperflowError(f"run {self.run!r}: receiving on {self.service!r}: {e}",
                                 self.run, self.service) from e

    def _wait(self, deadline: float | None) -> Any:
        """The next sample, blocking on the ready event until ``deadline``."""
        if self._stash is not None:
            sample, self._stash = self._stash, None
            return sample
        while True:
            sample = self._receive_sample()
            if sample is not None and self._before_floor(sample):
                sample.delete()
                continue
            if sample is not None:
                return sample
            now = time.monotonic()
            if deadline is not None and now >= deadline:
                attached = self.pipeline_attached()
                raise PipelineTimeout(
                    f"run {self.run!r}: no batch on {self.service!r} within {self.timeout_s} s "
                    f"({'a pipeline is attached' if attached else 'no pipeline publishes on it'})",
                    self.run, self.service)
            slice_ms = _WAIT_SLICE_MS if deadline is None else max(1, min(
                _WAIT_SLICE_MS, int((deadline - now) * 1000)))
            self._listener.timed_wait(iox2.Duration.from_millis(slice_ms))

    def _before_floor(self, sample: Any) -> bool:
        """Whether ``sample`` is a batch of the position a resume left."""
        return (self._floor is not None
                and sample.header.publisher_id.value == self._floor[0]
                and int(_header(sample)["sequence"]) < self._floor[1])

    def pipeline_attached(self) -> bool:
        """Whether a pipeline publishes on this stream (dead ones are cleaned up first)."""
        try:
            self._node.try_cleanup_dead_nodes()
        except Exception:  # noqa: BLE001 - best effort, as the Rust subscriber does
            pass
        return self._batches.dynamic_config.number_of_publishers > 0

    def held(self) -> list[tuple[int, int]]:
        """``(epoch, step)`` of the batches this stream holds: the current one and released
        ones whose views are alive."""
        # A copy first: a finalizer (garbage collection, or another thread dropping the
        # last view) may hand a batch back while this runs.
        return sorted(m.position for m in list(self._held))

    def _room(self, limit: int) -> None:
        """Raises :class:`TooManyBatchesHeld` unless fewer than ``limit`` batches are held."""
        if len(self._held) < limit:
            return
        gc.collect()  # views caught in reference cycles go now
        if len(self._held) < limit:
            return
        held = self.held()
        raise TooManyBatchesHeld(
            f"run {self.run!r}: {self.service!r}: receiving another batch would hold more than "
            f"{limit} (max_held {self.max_held}): batches {held} (epoch, step) are released but "
            "views of them (numpy sections, batch.torch() tensors, or arrays made from them "
            "without a copy) are alive. Drop them (del) or keep copies instead "
            "(tensor.clone(), np.array(view))", self.run, self.service, held)

    def next(self) -> Batch:
        """The next batch (releasing the one before); ``StopIteration`` once the stream
        ended (the last batch of the pipeline's last epoch was handed out)."""
        if self._pending is not None:
            batch, self._pending = self._pending, None
            return batch
        if self._ended:
            raise StopIteration
        self.release_current()
        self._room(self.max_held)
        deadline = None if self.timeout_s is None else time.monotonic() + self.timeout_s
        sample = self._wait(deadline)
        publisher = sample.header.publisher_id.value
        if (self.auto_resume and self._last is not None and publisher != self._last[0]):
            # Another pipeline (a restart): continue after the last batch received, by the
            # samples the job had consumed when the old pipeline said how it deals them
            # (the new one may start the epoch elsewhere).
            _, epoch, step = self._last
            sample.delete()
            schedule = self._schedule
            if schedule is not None and schedule.publisher == self._last[0] and schedule.global_batch:
                self.resume(epoch, sample=schedule.consumed(epoch, step + 1))
            else:
                self.resume(epoch, step + 1)
            sample = self._wait(deadline)
            publisher = sample.header.publisher_id.value
        batch = Batch(sample, self.run, self.service, self._held, self._subscriber)
        self._last = (publisher, batch.epoch, batch.step)
        self._current = batch
        self._mark(batch)
        return batch

    def _mark(self, batch: Batch) -> None:
        """Marks whether ``batch`` ends its epoch and the stream, from the schedule of the
        pipeline that sent it."""
        schedule = self._schedule
        if schedule is None or schedule.publisher != batch.publisher:
            if batch.publisher in self._schedule_missing:
                schedule = None
            else:
                schedule = self._ask_schedule(time.monotonic() + _SCHEDULE_WAIT_S)
                if schedule is None:
                    self._schedule_missing.add(batch.publisher)
                    warnings.warn(f"run {self.run!r}: the pipeline publishing {self.service!r} "
                                  "did not say how its epochs are scheduled: the stream will "
                                  "not end by itself", RuntimeWarning, stacklevel=3)
        if schedule is None:
            self._position = None
            return
        batch.last_in_epoch = batch.step + 1 >= schedule.steps_in(batch.epoch)
        batch.last_in_stream = (batch.last_in_epoch and schedule.epochs > 0
                                and batch.epoch + 1 >= schedule.epochs)
        self._ended = batch.last_in_stream
        self._position = ((batch.epoch + 1, 0) if batch.last_in_epoch
                          else (batch.epoch, batch.step + 1))

    def __iter__(self) -> Iterator[Batch]:
        return self

    def __next__(self) -> Batch:
        return self.next()

    @property
    def ended(self) -> bool:
        """Whether the stream's last batch (of the pipeline's last epoch) was handed out;
        iteration stops then (``stream.resume`` rewinds it)."""
        return self._ended and self._pending is None

    def position(self) -> tuple[int, int] | None:
        """``(epoch, step)`` of the next batch this stream hands out, when known (after a
        batch whose schedule is known, or a resume)."""
        if self._pending is not None:
            return (self._pending.epoch, self._pending.step)
        return self._position

    def epoch(self, drop_uneven: bool = False) -> Epoch:
        """This rank's batches of the current epoch (the one of the next batch), then
        stops; ``len()`` is the epoch's batch count from the pipeline's schedule.
        ``drop_uneven``: stop every rank at the fewest batches any rank has in an epoch
        (keyframes that do not divide evenly give some ranks one more): data-parallel
        ranks then stay in step; the extra batch is received and released unused."""
        return Epoch(self, drop_uneven)

    def schedule(self, timeout_s: float | None = None) -> Schedule:
        """The pipeline's schedule of this stream, asked on ``superflow/<run>/schedule``
        (waiting ``timeout_s``, default the stream's, for a pipeline to answer)."""
        timeout_s = self.timeout_s if timeout_s is None else timeout_s
        if self._schedule is not None:
            return self._schedule
        deadline = None if timeout_s is None else time.monotonic() + timeout_s
        schedule = self._ask_schedule(deadline)
        if schedule is None:
            raise PipelineTimeout(f"run {self.run!r}: no pipeline answered the schedule request "
                                  f"of {self.service!r} within {timeout_s} s",
                                  self.run, self.service)
        return schedule

    def _ask_schedule(self, deadline: float | None) -> Schedule | None:
        """Asks the pipeline for this stream's schedule; None when none answers by
        ``deadline``. The answer is kept (it belongs to the publisher named in it)."""
        try:
            if self._schedule_client is None:
                service = (
                    self._node.service_builder(
                        iox2.ServiceName.new(f"superflow/{self.run}/schedule"))
                    .request_response(_ScheduleRequest, _ScheduleReply)
                    .max_clients(MAX_SUBSCRIBERS * 4)
                    .max_servers(MAX_PUBLISHERS)
                    .max_nodes(MAX_NODES * 2)
                    .open_or_create()
                )
                self._schedule_client = (service, service.client_builder().create())
        except Exception as e:
            raise SuperflowError(f"run {self.run!r}: opening its schedule service: {e}",
                                 self.run, self.service) from e
        client = self._schedule_client[1]
        request = _ScheduleRequest(rank=self.rank or 0, broadcast=int(self.rank is None))
        while True:
            # A fresh client may not be connected to the server yet: resend until one
            # answers.
            pending = client.send_copy(request)
            attempt = time.monotonic()
            while time.monotonic() - attempt < 0.5:
                response = pending.receive()
                if response is not None:
                    reply = _ScheduleReply.from_buffer_copy(response.payload().contents)
                    response.delete()
                    if not reply.known:
                        raise SuperflowError(
                            f"run {self.run!r}: the pipeline has no stream {self.service!r} "
                            f"({_REFUSALS[1]})", self.run, self.service)
                    self._schedule = Schedule(
                        reply.steps, reply.min_steps, reply.epochs,
                        (reply.publisher_hi << 64) | reply.publisher_lo, reply.samples,
                        reply.global_batch, reply.start_epoch, reply.start_sample,
                        reply.start_steps, reply.start_min_steps)
                    return self._schedule
                if deadline is not None and time.monotonic() >= deadline:
                    return None
                time.sleep(0.005)

    def release_current(self) -> None:
        """Releases the batch handed out last, if it is still held."""
        if self._current is not None:
            self._current.release()
            self._current = None

    # -- resuming --------------------------------------------------------------------

    def resume(self, epoch: int, step: int | None = None, *, sample: int | None = None,
               global_batch: int | None = None, timeout_s: float = 30.0) -> None:
        """Asks the pipeline to continue this stream at ``step`` of ``epoch`` (a position
        of a job of this size), or after ``sample`` samples of ``epoch`` consumed by the
        whole job (every rank and host; ``global_batch``: the samples per step of the job
        that saved it, when known): that one holds whatever the job's size, and a job of
        another size continues the epoch there, dealt to its own ranks. The next batch
        received is the one there. Batches of the old position still queued are dropped
        (told apart by the reply's sequence number). Raises :class:`ResumeRefused` when
        the pipeline refuses, :class:`PipelineTimeout` when none answers in
        ``timeout_s``."""
        if (step is None) == (sample is None):
            raise ValueError("resume(epoch, step) or resume(epoch, sample=...): one of them")
        if self._pending is not None:
            self._pending.release()
            self._pending = None
        self.release_current()
        # The requests go out while batches are taken off the queue: room for one.
        self._room(MAX_BORROWED)
        try:
            control = (
                self._node.service_builder(iox2.ServiceName.new(f"superflow/{self.run}/control"))
                .request_response(_ResumeRequest, _ResumeReply)
                .max_clients(MAX_SUBSCRIBERS * 4)
                .max_servers(MAX_PUBLISHERS)
                .max_nodes(MAX_NODES * 2)
                .open_or_create()
            )
            client = control.client_builder().create()
        except Exception as e:
            raise SuperflowError(f"run {self.run!r}: opening its control service: {e}",
                                 self.run, self.service) from e
        if sample is None:
            expected = step
            request = _ResumeRequest(rank=self.rank or 0, broadcast=int(self.rank is None),
                                     epoch=epoch, step=step, sample=_UNKNOWN,
                                     global_batch=_UNKNOWN)
        else:
            # The step the answer will name: a step boundary of the pipeline's schedule, or
            # step 0 of an epoch made to start at `sample`.
            schedule = self._ask_schedule(time.monotonic() + 2.0)
            expected = 0 if schedule is None else _step_at(schedule, epoch, sample)
            request = _ResumeRequest(rank=self.rank or 0, broadcast=int(self.rank is None),
                                     epoch=epoch, step=_UNKNOWN, sample=sample,
                                     global_batch=_UNKNOWN if global_batch is None
                                     else global_batch)
        if self._stash is not None:
            self._stash.delete()
            self._stash = None
        started = time.monotonic()
        # The pipeline's server may not have connected to this fresh client yet (or the
        # pipeline is restarting): resend until one answers.
        while time.monotonic() - started < timeout_s:
            pending = client.send_copy(request)
            attempt = time.monotonic()
            while time.monotonic() - attempt < 0.5 and time.monotonic() - started < timeout_s:
                response = pending.receive()
                if response is not None:
                    reply = _ResumeReply.from_buffer_copy(response.payload().contents)
                    response.delete()
                    return self._accept(reply, epoch, step if sample is None else None, sample)
                # No answer yet: keep the queue moving (a pipeline blocked on this full
                # queue could not answer); keep only a batch at the asked position.
                sample = self._receive_sample()
                if sample is None:
                    time.sleep(0.002)
                elif self._stash is None and _position(sample) == (epoch, expected):
                    self._stash = sample
                else:
                    sample.delete()
        where = f"({epoch}, {step})" if sample is None else f"epoch {epoch} sample {sample}"
        raise PipelineTimeout(f"run {self.run!r}: no pipeline answered the request to resume "
                              f"{self.service!r} at {where} within {timeout_s} s",
                              self.run, self.service)

    def _accept(self, reply: _ResumeReply, epoch: int, step: int | None,
                sample: int | None) -> None:
        if not reply.accepted:
            where = f"({epoch}, {step})" if sample is None else f"epoch {epoch} sample {sample}"
            raise ResumeRefused(
                f"run {self.run!r}: the pipeline refused to resume {self.service!r} at "
                f"{where}: {_REFUSALS.get(reply.reason, f'reason {reply.reason}')}",
                self.run, self.service)
        publisher = (reply.publisher_hi << 64) | reply.publisher_lo
        self._floor = (publisher, int(reply.next_sequence))

        def new(sample: Any) -> bool:
            return (sample.header.publisher_id.value == publisher
                    and int(_header(sample)["sequence"]) >= reply.next_sequence)

        if self._stash is not None and not new(self._stash):
            self._stash.delete()
            self._stash = None
        while self._stash is None:
            sample = self._receive_sample()
            if sample is None:
                break
            if new(sample):
                self._stash = sample
            else:
                sample.delete()
        self._last = None
        self._ended = False
        self._position = (int(reply.epoch), int(reply.step))
        # The pipeline may deal the epoch differently now (a resume by sample): ask again.
        self._schedule = None

    def state_dict(self) -> dict[str, int]:
        """Where the whole job stands, for a checkpoint: ``{"epoch", "samples",
        "global_batch"}``, the samples of the epoch of the next batch that every rank
        together consumed (data-parallel ranks step together). ``load_state_dict`` of it
        resumes there on any number of ranks and hosts (``torchrun`` with another
        ``--nproc-per-node``, a pipeline with another ``--world-size``)."""
        at = self.position()
        schedule = self.schedule()
        if at is None:
            at = (schedule.start_epoch, 0)
        return {"epoch": at[0], "samples": schedule.consumed(at[0], at[1]),
                "global_batch": schedule.global_batch}

    def load_state_dict(self, state: dict[str, int]) -> None:
        """Continues where ``state`` (a ``state_dict()``, of a job of any size) stopped."""
        self.resume(int(state["epoch"]), sample=int(state["samples"]),
                    global_batch=state.get("global_batch"))

    # -- lifetime --------------------------------------------------------------------

    def close(self) -> None:
        """Releases the current batch and leaves the service (the port stays open, unseen,
        while views of held batches are alive: their memory is its to hand back)."""
        if self._pending is not None:
            self._pending.release()
            self._pending = None
        self.release_current()
        if self._stash is not None:
            self._stash.delete()
            self._stash = None
        if self._schedule_client is not None:
            self._schedule_client[1].delete()
            self._schedule_client = None
        ports = ("_listener",) if self._held else ("_subscriber", "_listener")
        for port in ports:
            obj = getattr(self, port, None)
            if obj is not None:
                obj.delete()
                setattr(self, port, None)

    def __enter__(self) -> Stream:
        return self

    def __exit__(self, *exc: Any) -> None:
        self.close()

    def __repr__(self) -> str:
        return f"Stream(run={self.run!r}, service={self.service!r})"


class Epoch:
    """The batches of one epoch of a :class:`Stream` (``stream.epoch()``): iterating
    yields this rank's batches of the current epoch and stops after its last one (or
    when a batch of a later epoch comes first: it is kept for the next iteration).
    Breaking out and iterating again continues the same epoch."""

    def __init__(self, stream: Stream, drop_uneven: bool = False):
        self.stream = stream
        self.drop_uneven = drop_uneven

    def __len__(self) -> int:
        schedule = self.stream.schedule()
        at = self.stream.position()
        # A stream that has received nothing yet starts where the pipeline starts.
        epoch = schedule.start_epoch if at is None else at[0]
        return schedule.min_steps_in(epoch) if self.drop_uneven else schedule.steps_in(epoch)

    def __iter__(self) -> Iterator[Batch]:
        stream = self.stream
        if stream.ended:
            return
        stream.schedule()  # where the epoch ends
        epoch = None
        while not stream.ended:
            batch = stream.next()
            if epoch is None:
                epoch = batch.epoch
            elif batch.epoch != epoch:
                stream._pending = batch
                return
            schedule = stream._schedule
            if not (self.drop_uneven and schedule is not None
                    and schedule.publisher == batch.publisher
                    and batch.step >= schedule.min_steps_in(batch.epoch)):
                yield batch
            if batch.last_in_epoch:
                return

    def __repr__(self) -> str:
        return f"Epoch({self.stream!r}, drop_uneven={self.drop_uneven})"
