"""The resume request of a :class:`~superflow.Stream`: asking the pipeline, on
``superflow/<run>/control``, to continue the stream at a step of an epoch or after a
number of the epoch's samples, and telling the batches of the new position from those
of the old one still queued.

While the answer is awaited the batch queue keeps being drained (a pipeline blocked on
this subscriber's full queue could not answer), keeping only a batch at the asked
position: it may be the first of the new position (the *stash*, handed out by the
stream's next receive). The reply names the publisher and the sequence number of the
first batch published after it; that publisher's batches numbered below it belong to the
old position (the *floor*) and are dropped.
"""

from __future__ import annotations

import time
from collections.abc import Callable
from typing import Any

import iceoryx2 as iox2

from .batch import header_record, position_of
from .errors import PipelineTimeout, ResumeRefused, RunComplete, SuperflowError
from .schedule import ScheduleClient
from .wire import (
    MAX_NODES,
    MAX_PUBLISHERS,
    MAX_SUBSCRIBERS,
    REFUSALS,
    RUN_COMPLETE,
    UNKNOWN,
    ResumeReply,
    ResumeRequest,
)


class ResumeClient:
    """One stream's resume requests, and what the last one left for the stream's next
    receive: the ``stash`` (a batch received before the answer) and the ``floor``
    (publisher, first sequence number of the new position)."""

    def __init__(self, node: Any, run: str, service: str, rank: int | None):
        self._node = node
        self.run = run
        self.service = service
        self.rank = rank
        self.stash: Any = None
        self.floor: tuple[int, int] | None = None

    def take(self) -> Any:
        """The stashed sample (None when there is none); the stash is empty after."""
        sample, self.stash = self.stash, None
        return sample

    def drop(self) -> None:
        """Hands the stashed sample, if any, back to the pipeline."""
        if self.stash is not None:
            self.stash.delete()
            self.stash = None

    def before_floor(self, sample: Any) -> bool:
        """Whether ``sample`` is a batch of the position a resume left."""
        return (self.floor is not None
                and sample.header.publisher_id.value == self.floor[0]
                and int(header_record(sample)["sequence"]) < self.floor[1])

    def request(self, epoch: int, step: int | None, sample: int | None,
                global_batch: int | None, timeout_s: float, receive: Callable[[], Any],
                schedules: ScheduleClient) -> ResumeReply:
        """Asks the pipeline to continue at ``step`` of ``epoch``, or (``step`` None)
        after ``sample`` samples of it consumed by the whole job; ``receive`` takes the
        next sample off the stream's queue (None when it is empty), ``schedules`` names
        the step a resume by sample lands on. Returns the accepted reply, with the floor
        set and the new position's first batch stashed when it is already queued. Raises
        :class:`RunComplete` or :class:`ResumeRefused` when the pipeline refuses,
        :class:`PipelineTimeout` when none answers in ``timeout_s``."""
        try:
            control = (
                self._node.service_builder(iox2.ServiceName.new(f"superflow/{self.run}/control"))
                .request_response(ResumeRequest, ResumeReply)
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
            request = ResumeRequest(rank=self.rank or 0, broadcast=int(self.rank is None),
                                     epoch=epoch, step=step, sample=UNKNOWN,
                                     global_batch=UNKNOWN)
        else:
            # The step the answer will name: a step boundary of the pipeline's schedule, or
            # step 0 of an epoch made to start at `sample`.
            schedule = schedules.ask(time.monotonic() + 2.0)
            expected = 0 if schedule is None else schedule.step_at(epoch, sample)
            request = ResumeRequest(rank=self.rank or 0, broadcast=int(self.rank is None),
                                     epoch=epoch, step=UNKNOWN, sample=sample,
                                     global_batch=UNKNOWN if global_batch is None
                                     else global_batch)
        self.drop()
        started = time.monotonic()
        # The pipeline's server may not have connected to this fresh client yet (or the
        # pipeline is restarting): resend until one answers.
        while time.monotonic() - started < timeout_s:
            pending = client.send_copy(request)
            attempt = time.monotonic()
            while time.monotonic() - attempt < 0.5 and time.monotonic() - started < timeout_s:
                response = pending.receive()
                if response is not None:
                    reply = ResumeReply.from_buffer_copy(response.payload().contents)
                    response.delete()
                    self._accept(reply, _where(epoch, step, sample), receive)
                    return reply
                # No answer yet: keep the queue moving (a pipeline blocked on this full
                # queue could not answer); keep only a batch at the asked position.
                received = receive()
                if received is None:
                    time.sleep(0.002)
                elif self.stash is None and position_of(received) == (epoch, expected):
                    self.stash = received
                else:
                    received.delete()
        raise PipelineTimeout(f"run {self.run!r}: no pipeline answered the request to resume "
                              f"{self.service!r} at {_where(epoch, step, sample)} within "
                              f"{timeout_s} s", self.run, self.service)

    def _accept(self, reply: ResumeReply, where: str, receive: Callable[[], Any]) -> None:
        """Raises the refusal of a refused ``reply``; for an accepted one sets the floor
        and keeps only a stashed batch of the new position, receiving one if it is
        queued."""
        if not reply.accepted:
            if reply.reason == RUN_COMPLETE:
                raise RunComplete(
                    f"run {self.run!r}: the run is complete ({reply.epoch} epochs): nothing is "
                    f"left to serve on {self.service!r} at {where}", self.run, self.service,
                    int(reply.epoch))
            raise ResumeRefused(
                f"run {self.run!r}: the pipeline refused to resume {self.service!r} at "
                f"{where}: {REFUSALS.get(reply.reason, f'reason {reply.reason}')}",
                self.run, self.service)
        publisher = (reply.publisher_hi << 64) | reply.publisher_lo
        self.floor = (publisher, int(reply.next_sequence))

        def new(received: Any) -> bool:
            return bool(received.header.publisher_id.value == publisher
                        and int(header_record(received)["sequence"]) >= reply.next_sequence)

        if self.stash is not None and not new(self.stash):
            self.drop()
        while self.stash is None:
            received = receive()
            if received is None:
                break
            if new(received):
                self.stash = received
            else:
                received.delete()


def _where(epoch: int, step: int | None, sample: int | None) -> str:
    """The asked position, as messages name it."""
    return f"({epoch}, {step})" if sample is None else f"epoch {epoch} sample {sample}"
