"""What crosses iceoryx2 besides the batches: the service settings every superflow
process shares, and the request/response types of the control and schedule services,
mirrored from ``schemas/src/service/messages.rs`` (field for field: iceoryx2 refuses a peer whose
type differs in name or size)."""

from __future__ import annotations

import ctypes
from typing import NamedTuple

from .format import HEADER_SIZE

# The service settings every superflow process uses (schemas/src/service/open.rs, `qos`):
# iceoryx2 refuses to open a service with other ones. MAX_BORROWED bounds the batches a
# subscriber holds at once, so `max_held` too.
MAX_SUBSCRIBERS, MAX_BUFFER, MAX_BORROWED, MAX_PUBLISHERS, MAX_NODES = 8, 4, 2, 2, 16

# A field of a resume request that is not known (schemas/src/service/messages.rs `UNKNOWN`).
UNKNOWN = (1 << 64) - 1


class BatchHeaderWords(ctypes.Structure):
    """The 11 400-byte user header, as opaque 8-byte words (the format module parses it)."""

    _fields_ = [("words", ctypes.c_uint64 * (HEADER_SIZE // 8))]

    @staticmethod
    def type_name() -> str:
        return "superflow::BatchHeader"


class ResumeRequest(ctypes.Structure):
    """`superflow::ResumeRequest`."""

    _fields_ = [("rank", ctypes.c_uint32), ("broadcast", ctypes.c_uint32),
                ("epoch", ctypes.c_uint64), ("step", ctypes.c_uint64),
                ("sample", ctypes.c_uint64), ("global_batch", ctypes.c_uint64)]

    @staticmethod
    def type_name() -> str:
        return "superflow::ResumeRequest"


class ResumeReply(ctypes.Structure):
    """`superflow::ResumeReply`; with reason 4 (the run is complete) ``epoch`` is the
    run's epoch count."""

    _fields_ = [("accepted", ctypes.c_uint32), ("reason", ctypes.c_uint32),
                ("next_sequence", ctypes.c_uint64), ("publisher_lo", ctypes.c_uint64),
                ("publisher_hi", ctypes.c_uint64), ("epoch", ctypes.c_uint64),
                ("step", ctypes.c_uint64)]

    @staticmethod
    def type_name() -> str:
        return "superflow::ResumeReply"


class ScheduleRequest(ctypes.Structure):
    """`superflow::ScheduleRequest`."""

    _fields_ = [("rank", ctypes.c_uint32), ("broadcast", ctypes.c_uint32)]

    @staticmethod
    def type_name() -> str:
        return "superflow::ScheduleRequest"


class ScheduleReply(ctypes.Structure):
    """`superflow::ScheduleReply`."""

    _fields_ = [("known", ctypes.c_uint32), ("reserved", ctypes.c_uint32),
                ("steps", ctypes.c_uint64), ("min_steps", ctypes.c_uint64),
                ("epochs", ctypes.c_uint64), ("publisher_lo", ctypes.c_uint64),
                ("publisher_hi", ctypes.c_uint64), ("samples", ctypes.c_uint64),
                ("global_batch", ctypes.c_uint64), ("start_epoch", ctypes.c_uint64),
                ("start_sample", ctypes.c_uint64), ("start_steps", ctypes.c_uint64),
                ("start_min_steps", ctypes.c_uint64), ("seed", ctypes.c_uint64),
                ("host_rank", ctypes.c_uint32), ("host_count", ctypes.c_uint32),
                ("keyframes", ctypes.c_uint64), ("plan_digest", ctypes.c_uint64)]

    @staticmethod
    def type_name() -> str:
        return "superflow::ScheduleReply"


# Why the pipeline refused a resume (`ResumeReply.reason`); 4 is RunComplete's.
REFUSALS = {1: "no such stream (rank out of range, or the pipeline runs in the other mode)",
            2: "the position is past the end of its epoch",
            3: "the step was saved by a job of another size: resume by sample "
               "(stream.resume(epoch, sample=...), or load_state_dict of a state_dict)"}
RUN_COMPLETE = 4


class Schedule(NamedTuple):
    """How the pipeline schedules this stream: ``steps`` batches per epoch (this rank's),
    ``min_steps`` the fewest of any rank, ``epochs`` served (0: endless), the
    ``publisher`` (pipeline process) that said so; ``samples`` per epoch and
    ``global_batch`` samples per step of the whole job (every rank and host); epoch
    ``start_epoch`` starts at sample ``start_sample`` (a job resumed on another size),
    with ``start_steps`` / ``start_min_steps`` batches. The plan served: ``seed``,
    ``host_rank`` of ``host_count`` pipelines, the dataset's ``keyframes`` (all hosts,
    before repeats) and ``plan_digest``, equal on every host of one job."""

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
    seed: int = 0
    host_rank: int = 0
    host_count: int = 1
    keyframes: int = 0
    plan_digest: int = 0

    @classmethod
    def of(cls, reply: ScheduleReply) -> Schedule:
        return cls(reply.steps, reply.min_steps, reply.epochs,
                   (reply.publisher_hi << 64) | reply.publisher_lo, reply.samples,
                   reply.global_batch, reply.start_epoch, reply.start_sample,
                   reply.start_steps, reply.start_min_steps, reply.seed, reply.host_rank,
                   reply.host_count, reply.keyframes, reply.plan_digest)

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

    def step_at(self, epoch: int, sample: int) -> int:
        """The step at which a resume after ``sample`` samples of ``epoch`` continues: a
        step boundary, or 0 when the pipeline will start the epoch there."""
        first = self.start_sample if self._part_way(epoch) else 0
        taken = sample - first
        if self.global_batch <= 0 or taken < 0:
            return 0
        if taken % self.global_batch == 0:
            return taken // self.global_batch
        if sample == self.samples:
            return -(-taken // self.global_batch)
        return 0

    def plan(self) -> dict[str, int]:
        """What must be equal on every rank of a job (``Stream.check_plan``)."""
        return {"plan_digest": self.plan_digest, "seed": self.seed, "keyframes": self.keyframes,
                "host_count": self.host_count, "samples": self.samples,
                "global_batch": self.global_batch, "epochs": self.epochs}
