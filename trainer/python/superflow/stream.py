"""Receiving batches from a running ``superflow-pipeline`` over iceoryx2 shared memory.

A :class:`Stream` subscribes to one run's batches (broadcast, or one rank's shard) and
yields :class:`Batch` objects whose sections are numpy arrays *inside* the shared memory:
nothing is copied. A batch stays valid until it is released (``batch.release()``, the
end of a ``with batch:`` block, or the next iteration); an array read after that raises
:class:`BatchReleased` instead of reading memory the pipeline may already have reused.
"""

from __future__ import annotations

import ctypes
import os
import time
import warnings
from typing import Any, Iterator

import iceoryx2 as iox2
import numpy as np

from .format import (HEADER, HEADER_SIZE, RUN_CHARS, BatchFormatError, FormatVersionError,
                     batch_meta, read_batch)
from .sections import section_dtype

# The service settings every superflow process uses (schemas/src/service.rs, `qos`):
# iceoryx2 refuses to open a service with other ones.
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
    """An array of a batch was used after the batch was released."""


class ResumeRefused(SuperflowError):
    """The pipeline refused to move the stream (no such stream, or past the last epoch)."""


class _BatchHeader(ctypes.Structure):
    """The 11 400-byte user header, as opaque 8-byte words (the format module parses it)."""

    _fields_ = [("words", ctypes.c_uint64 * (HEADER_SIZE // 8))]

    @staticmethod
    def type_name() -> str:
        return "superflow::BatchHeader"


class _ResumeRequest(ctypes.Structure):
    """`superflow::ResumeRequest` (schemas/src/service.rs)."""

    _fields_ = [("rank", ctypes.c_uint32), ("broadcast", ctypes.c_uint32),
                ("epoch", ctypes.c_uint64), ("step", ctypes.c_uint64)]

    @staticmethod
    def type_name() -> str:
        return "superflow::ResumeRequest"


class _ResumeReply(ctypes.Structure):
    """`superflow::ResumeReply` (schemas/src/service.rs)."""

    _fields_ = [("accepted", ctypes.c_uint32), ("reason", ctypes.c_uint32),
                ("next_sequence", ctypes.c_uint64), ("publisher_lo", ctypes.c_uint64),
                ("publisher_hi", ctypes.c_uint64)]

    @staticmethod
    def type_name() -> str:
        return "superflow::ResumeReply"


_REFUSALS = {1: "no such stream (rank out of range, or the pipeline runs in the other mode)",
             2: "the position is past the end of the configured epochs"}


class _Lease:
    """Whether the shared memory of a batch is still this process's to read."""

    __slots__ = ("released", "what")

    def __init__(self, what: str):
        self.released = False
        self.what = what

    def check(self) -> None:
        if self.released:
            raise BatchReleased(f"{self.what} was released: its shared memory may already hold "
                                "another batch (copy what you keep before releasing)")


class SectionArray(np.ndarray):
    """A numpy view into a batch's shared memory. Indexing, ufuncs (arithmetic,
    reductions), numpy functions and the usual methods check that the batch is still
    held and raise :class:`BatchReleased` otherwise. A plain array taken out of it
    (``np.asarray``, ``torch.from_numpy``) is not guarded: keep it only while the batch
    is held, or copy it."""

    _lease: _Lease | None = None

    def __array_finalize__(self, obj: Any) -> None:
        self._lease = getattr(obj, "_lease", None)

    def _check(self) -> None:
        if self._lease is not None:
            self._lease.check()

    def __getitem__(self, key: Any) -> Any:
        self._check()
        return super().__getitem__(key)

    def __array_ufunc__(self, ufunc: Any, method: str, *inputs: Any, **kwargs: Any) -> Any:
        for x in inputs + tuple(kwargs.get("out", ())):
            if isinstance(x, SectionArray):
                x._check()
        plain = tuple(np.asarray(x) if isinstance(x, SectionArray) else x for x in inputs)
        if "out" in kwargs:
            kwargs["out"] = tuple(np.asarray(x) if isinstance(x, SectionArray) else x
                                  for x in kwargs["out"])
        return getattr(ufunc, method)(*plain, **kwargs)

    def __array_function__(self, func: Any, types: Any, args: Any, kwargs: Any) -> Any:
        self._check()
        return super().__array_function__(func, types, args, kwargs)

    def _guarded(name: str):  # noqa: N805 - builds methods below
        method = getattr(np.ndarray, name)

        def guarded(self: SectionArray, *args: Any, **kwargs: Any) -> Any:
            self._check()
            return method(self, *args, **kwargs)

        guarded.__name__ = name
        guarded.__doc__ = method.__doc__
        return guarded

    for _name in ("copy", "astype", "tolist", "tobytes", "item", "__iter__", "__bool__",
                  "__float__", "__int__", "__index__", "__array__", "__reduce__",
                  "__reduce_ex__", "__copy__", "__deepcopy__"):
        locals()[_name] = _guarded(_name)
    del _name, _guarded

    def __repr__(self) -> str:
        if self._lease is not None and self._lease.released:
            return f"SectionArray(<{self._lease.what} was released>)"
        return super().__repr__()

    __str__ = __repr__


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


def _read(sample: Any, run: str, service: str) -> tuple[np.void, dict[str, np.ndarray]]:
    """The header and sections of a received sample, checked against the format and the
    section table; :class:`MalformedBatch` names the run and service otherwise."""
    header = _header_bytes(sample)
    payload = sample.payload().as_memory_view()
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
    index in epoch, keyframe, drive, sweep). ``batch[name]`` is a section (see
    ``names()``); ``batch.torch()`` the same as ``torch.Tensor``s sharing the memory.
    """

    def __init__(self, sample: Any, run: str, service: str):
        self._sample = sample
        self.run_service = (run, service)
        try:
            h, arrays = _read(sample, run, service)
        except MalformedBatch:
            # Hand the memory back: the stream goes on with the next batch.
            self._sample = None
            sample.delete()
            raise
        meta = batch_meta(h)
        self.epoch: int = meta["epoch"]
        self.step: int = meta["step"]
        self.sequence: int = meta["sequence"]
        self.seed: int = meta["seed"]
        self.run: str = meta["run"]
        self.publisher: int = sample.header.publisher_id.value
        self._lease = _Lease(f"batch (epoch {self.epoch}, step {self.step}) of run {run!r}")
        self._arrays: dict[str, SectionArray] = {}
        for name, array in arrays.items():
            view = array.view(SectionArray)
            view._lease = self._lease
            self._arrays[name] = view
        ids = arrays.get("sample_ids", np.zeros((0, 5), np.uint64))
        self.sample_ids: list[int] = [int(i) for i in ids[:, 1]]
        self.keyframes: list[int] = [int(k) for k in ids[:, 2]]

    @property
    def released(self) -> bool:
        """Whether the batch was released (its arrays may no longer be read)."""
        return self._lease.released

    def names(self) -> list[str]:
        """Every section name, in payload order."""
        return list(self._arrays)

    def __contains__(self, name: str) -> bool:
        return name in self._arrays

    def __getitem__(self, name: str) -> SectionArray:
        self._lease.check()
        try:
            return self._arrays[name]
        except KeyError:
            raise KeyError(f"no section `{name}` in this batch (sections: {', '.join(self._arrays)})")

    def torch(self) -> dict[str, Any]:
        """Every section as a ``torch.Tensor`` sharing the shared memory (``torch.from_numpy``,
        no copy). The memory is the pipeline's: read it, do not write it, and copy what you
        keep past the batch's release (``.clone()``, or ``.to(device)``)."""
        self._lease.check()
        import torch  # optional dependency: pip install superflow[torch]

        with warnings.catch_warnings():
            # The views are read-only; torch warns that its tensors would not be.
            warnings.simplefilter("ignore", UserWarning)
            return {name: torch.from_numpy(np.asarray(a)) for name, a in self._arrays.items()}

    def release(self) -> None:
        """Hands the batch's memory back to the pipeline; its arrays then raise on use."""
        if self._lease.released:
            return
        self._lease.released = True
        self._arrays = {}
        sample, self._sample = self._sample, None
        if sample is not None:
            sample.delete()

    def __enter__(self) -> Batch:
        return self

    def __exit__(self, *exc: Any) -> None:
        self.release()

    def __repr__(self) -> str:
        state = "released" if self.released else f"{len(self._arrays)} sections"
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
    """

    def __init__(self, run: str, rank: int | None = None, world_size: int | None = None,
                 prefix: str | None = None, timeout_s: float | None = None, buffer: int = 2,
                 auto_resume: bool = True):
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
        self._current: Batch | None = None
        self._stash: Any = None
        self._last: tuple[int, int, int] | None = None  # publisher, epoch, step

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

    def pipeline_attached(self) -> bool:
        """Whether a pipeline publishes on this stream (dead ones are cleaned up first)."""
        try:
            self._node.try_cleanup_dead_nodes()
        except Exception:  # noqa: BLE001 - best effort, as the Rust subscriber does
            pass
        return self._batches.dynamic_config.number_of_publishers > 0

    def next(self) -> Batch:
        """The next batch (releasing the one before)."""
        self.release_current()
        deadline = None if self.timeout_s is None else time.monotonic() + self.timeout_s
        sample = self._wait(deadline)
        publisher = sample.header.publisher_id.value
        if (self.auto_resume and self._last is not None and publisher != self._last[0]):
            # Another pipeline (a restart): continue after the last batch received.
            _, epoch, step = self._last
            sample.delete()
            self.resume(epoch, step + 1)
            sample = self._wait(deadline)
            publisher = sample.header.publisher_id.value
        batch = Batch(sample, self.run, self.service)
        self._last = (publisher, batch.epoch, batch.step)
        self._current = batch
        return batch

    def __iter__(self) -> Iterator[Batch]:
        return self

    def __next__(self) -> Batch:
        return self.next()

    def release_current(self) -> None:
        """Releases the batch handed out last, if it is still held."""
        if self._current is not None:
            self._current.release()
            self._current = None

    # -- resuming --------------------------------------------------------------------

    def resume(self, epoch: int, step: int, timeout_s: float = 30.0) -> None:
        """Asks the pipeline to continue this stream at ``(epoch, step)``: the next batch
        received is that one. Batches of the old position still queued are dropped (told
        apart by the reply's sequence number). Raises :class:`ResumeRefused` when the
        pipeline refuses, :class:`PipelineTimeout` when none answers in ``timeout_s``."""
        self.release_current()
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
        request = _ResumeRequest(rank=self.rank or 0, broadcast=int(self.rank is None),
                                 epoch=epoch, step=step)
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
                    return self._accept(reply, epoch, step)
                # No answer yet: keep the queue moving (a pipeline blocked on this full
                # queue could not answer); keep only a batch at the asked position.
                sample = self._receive_sample()
                if sample is None:
                    time.sleep(0.002)
                elif self._stash is None and _position(sample) == (epoch, step):
                    self._stash = sample
                else:
                    sample.delete()
        raise PipelineTimeout(f"run {self.run!r}: no pipeline answered the request to resume "
                              f"{self.service!r} at ({epoch}, {step}) within {timeout_s} s",
                              self.run, self.service)

    def _accept(self, reply: _ResumeReply, epoch: int, step: int) -> None:
        if not reply.accepted:
            raise ResumeRefused(
                f"run {self.run!r}: the pipeline refused to resume {self.service!r} at "
                f"({epoch}, {step}): {_REFUSALS.get(reply.reason, f'reason {reply.reason}')}",
                self.run, self.service)
        publisher = (reply.publisher_hi << 64) | reply.publisher_lo

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

    # -- lifetime --------------------------------------------------------------------

    def close(self) -> None:
        """Releases the current batch and leaves the service."""
        self.release_current()
        if self._stash is not None:
            self._stash.delete()
            self._stash = None
        for port in ("_subscriber", "_listener"):
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
