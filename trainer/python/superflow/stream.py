"""Receiving batches from a running ``superflow-pipeline`` over iceoryx2 shared memory.

A :class:`Stream` subscribes to one run's batches (broadcast, or one rank's shard) and
yields :class:`Batch` objects whose sections are numpy arrays over the batch's memory:
nothing is copied. The lifetime rule: a batch's shared memory goes back to the pipeline
only when the batch is released (``batch.release()``, the end of a ``with batch:``
block, or the next iteration) *and* no view of it is alive (its numpy sections, the
tensors of ``batch.torch()``, anything made from them without a copy). A view kept past
the release stays valid; the hand-back waits until the last one is garbage-collected.
A stream holds at most ``max_held`` batches that way; the receive that would hold more
raises :class:`TooManyBatchesHeld` naming them.

What the stream asks the pipeline is in modules of its own: the schedule request
(:mod:`superflow.schedule`) and the resume request (:mod:`superflow.resume`).
"""

from __future__ import annotations

import ctypes
import functools
import gc
import os
import socket
import time
from collections.abc import Iterator
from typing import Any

import iceoryx2 as iox2

from . import ranks
from .batch import Batch, SectionArray
from .errors import (
    PipelineTimeout,
    PlanMismatch,
    StreamNotPicklable,
    SuperflowError,
    TooManyBatchesHeld,
)
from .format import RUN_CHARS
from .memory import Memory
from .resume import ResumeClient
from .schedule import ScheduleClient
from .wire import (
    MAX_BORROWED,
    MAX_BUFFER,
    MAX_NODES,
    MAX_PUBLISHERS,
    MAX_SUBSCRIBERS,
    BatchHeaderWords,
    Schedule,
)

__all__ = ["Batch", "Epoch", "SectionArray", "Stream"]

# How long one wait on the ready event lasts before the queue is looked at again (a
# wake-up sent before the listener existed is not lost).
_WAIT_SLICE_MS = 100


class Stream:
    """The batches of run ``run`` from a ``superflow-pipeline``.

    ``rank`` / ``world_size`` select the shard stream ``superflow/<run>/rank/<rank>`` of
    the pipeline of this host, started with ``--world-size W``; by default they come from
    the launcher: torchrun's ``LOCAL_RANK`` / ``LOCAL_WORLD_SIZE`` (the rank on this
    node: every node runs its own pipeline), else ``RANK`` / ``WORLD_SIZE``, else Slurm's
    (``superflow.ranks`` says which wins). A single process reads the broadcast stream
    ``superflow/<run>/batches``. ``prefix`` is the iceoryx2 prefix of the deployment
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
        shard = ranks.resolve(rank, world_size)
        self.run = run
        self.rank = shard.rank
        self.world_size = shard.world_size
        self.shard = shard
        rank = shard.rank
        self.timeout_s = timeout_s
        self.auto_resume = auto_resume
        self.service = f"superflow/{run}/batches" if rank is None else f"superflow/{run}/rank/{rank}"
        prefix = os.environ.get("SUPERFLOW_IOX_PREFIX") if prefix is None else prefix
        self.prefix = prefix or ""
        config = iox2.config.default()
        if prefix:
            config.global_cfg.prefix = iox2.FileName.new(prefix + "_")
        try:
            self._node = iox2.NodeBuilder.new().config(config).create(iox2.ServiceType.Ipc)
            self._batches = (
                self._node.service_builder(iox2.ServiceName.new(self.service))
                .publish_subscribe(iox2.Slice[ctypes.c_uint8])
                .user_header(BatchHeaderWords)
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
        self._held: set[Memory] = set()
        self._current: Batch | None = None
        self._pending: Batch | None = None  # received, handed out by the next next()
        # Bound to the ports, not to the stream: a stream dropped leaves its services at once.
        self._schedules = ScheduleClient(self._node, run, self.service, rank,
                                         functools.partial(_attached, self._node, self._batches))
        self._resumes = ResumeClient(self._node, run, self.service, rank)
        self._position: tuple[int, int] | None = None  # of the next batch, once known
        self._ended = False
        self._last: tuple[int, int, int] | None = None  # publisher, epoch, step

    # -- receiving -------------------------------------------------------------------

    def _receive_sample(self) -> Any:
        if self.closed:
            raise SuperflowError(f"run {self.run!r}: the stream of {self.service!r} was closed",
                                 self.run, self.service)
        try:
            return self._subscriber.receive()
        except Exception as e:
            raise SuperflowError(f"run {self.run!r}: receiving on {self.service!r}: {e}",
                                 self.run, self.service) from e

    def _wait(self, deadline: float | None) -> Any:
        """The next sample, blocking on the ready event until ``deadline``."""
        sample = self._resumes.take()
        if sample is not None:
            return sample
        while True:
            sample = self._receive_sample()
            if sample is not None and self._resumes.before_floor(sample):
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

    def pipeline_attached(self) -> bool:
        """Whether a pipeline publishes on this stream (dead ones are cleaned up first)."""
        return _attached(self._node, self._batches)

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
            schedule = self._schedules.known
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
        schedule = self._schedules.of(batch.publisher)
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
        """The pipeline's schedule of this stream, asked on ``superflow/<run>/schedule``.
        While no pipeline publishes on the stream it waits for one like a receive does
        (``timeout_s``, default the stream's; :class:`PipelineTimeout` after it); a
        pipeline that publishes but does not answer within 5 s raises
        :class:`ScheduleUnavailable` (it has no schedule service: the stream cannot know
        where epochs end)."""
        return self._schedules.require(self.timeout_s if timeout_s is None else timeout_s)

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
        reply = self._resumes.request(epoch, step, sample, global_batch, timeout_s,
                                      self._receive_sample, self._schedules)
        self._last = None
        self._ended = False
        self._position = (int(reply.epoch), int(reply.step))
        # The pipeline may deal the epoch differently now (a resume by sample): ask again.
        self._schedules.forget()

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

    # -- the plan of a job ------------------------------------------------------------

    def check_plan(self, group: Any = None) -> dict[str, int]:
        """Checks that every rank of a ``torch.distributed`` job (``group``, default the
        world) is served the same plan: the same drives, keyframes, seed and configuration
        on every host's pipeline (``plan_digest``), one pipeline per ``--host-rank`` and
        as many as ``--host-count`` says. Raises :class:`PlanMismatch` naming the ranks
        and what differs; returns this rank's plan. A collective: every rank calls it
        (``TorchIterable`` does at its first ``iter()``). Without an initialized process
        group there is nothing to compare: returns the plan."""
        schedule = self.schedule()
        # A pipeline is told apart by its machine and iceoryx2 prefix (each stream has a
        # publisher of its own).
        mine = {"rank": self.shard.job_rank, "host_rank": schedule.host_rank,
                "pipeline": f"{socket.gethostname()}/{self.prefix}", "plan": schedule.plan()}
        import torch.distributed as dist

        if not (dist.is_available() and dist.is_initialized()):
            return schedule.plan()
        everyone: list[Any] = [None] * dist.get_world_size(group)
        dist.all_gather_object(everyone, mine, group=group)
        check_plans(self.run, self.service, everyone)
        return schedule.plan()

    # -- lifetime --------------------------------------------------------------------

    def close(self) -> None:
        """Releases the current batch and leaves the service at once: the pipeline stops
        counting this subscriber. Views of held batches stay valid (their pages not yet
        copied are copied into this process first)."""
        if self._pending is not None:
            self._pending.release()
            self._pending = None
        self.release_current()
        self._resumes.drop()
        for memory in list(self._held):
            memory.detach()
        self._schedules.close()
        for port in ("_subscriber", "_listener"):
            obj = getattr(self, port, None)
            if obj is not None:
                obj.delete()
                setattr(self, port, None)

    @property
    def closed(self) -> bool:
        """Whether ``close()`` left the service."""
        return getattr(self, "_subscriber", None) is None

    def __reduce__(self) -> Any:
        raise StreamNotPicklable(
            f"a superflow.Stream (run {self.run!r}) cannot be pickled: its shared-memory ports "
            "belong to this process (spawn/forkserver DataLoader workers and multiprocessing "
            "pickle what they get). Open a Stream in the process that reads it, and keep "
            "DataLoader(num_workers=0): the pipeline is the worker pool",
            self.run, self.service)

    def __enter__(self) -> Stream:
        return self

    def __exit__(self, *exc: Any) -> None:
        self.close()

    def __repr__(self) -> str:
        return f"Stream(run={self.run!r}, service={self.service!r})"


def _attached(node: Any, batches: Any) -> bool:
    """Whether a publisher is on ``batches``, after ``node`` cleaned up dead ones."""
    try:
        node.try_cleanup_dead_nodes()
    except Exception:  # best effort, as the Rust subscriber does
        pass
    return bool(batches.dynamic_config.number_of_publishers > 0)


def check_plans(run: str, service: str, everyone: list[dict[str, Any]]) -> None:
    """Raises :class:`PlanMismatch` unless every rank's ``{"rank", "host_rank",
    "pipeline", "plan"}`` agrees: one plan, one pipeline per host rank, ``host_count``
    pipelines."""
    first = everyone[0]
    for other in everyone[1:]:
        if other["plan"] != first["plan"]:
            fields = [f"{k} {other['plan'][k]} vs {first['plan'][k]}" for k in first["plan"]
                      if other["plan"].get(k) != first["plan"][k]]
            raise PlanMismatch(
                f"run {run!r}: rank {other['rank']}'s pipeline serves another plan than rank "
                f"{first['rank']}'s ({', '.join(fields)} on rank {first['rank']}): every host's "
                "pipeline needs the same drives, seed and configuration", run, service)
    hosts: dict[int, dict[str, Any]] = {}
    for entry in everyone:
        seen = hosts.setdefault(entry["host_rank"], entry)
        if seen["pipeline"] != entry["pipeline"]:
            raise PlanMismatch(
                f"run {run!r}: ranks {seen['rank']} and {entry['rank']} read two pipelines that "
                f"both run --host-rank {entry['host_rank']}: give each host its own "
                f"--host-rank (0 to {first['plan']['host_count'] - 1})", run, service)
    count = first["plan"]["host_count"]
    if len(hosts) != count:
        raise PlanMismatch(
            f"run {run!r}: the pipelines run with --host-count {count}, but the job's ranks read "
            f"{len(hosts)} (host ranks {sorted(hosts)}): the other hosts' share of every epoch "
            "would never be trained", run, service)


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
            schedule = stream._schedules.known
            if not (self.drop_uneven and schedule is not None
                    and schedule.publisher == batch.publisher
                    and batch.step >= schedule.min_steps_in(batch.epoch)):
                yield batch
            if batch.last_in_epoch:
                return

    def __repr__(self) -> str:
        return f"Epoch({self.stream!r}, drop_uneven={self.drop_uneven})"
