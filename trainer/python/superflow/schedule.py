"""The schedule request of a :class:`~superflow.Stream`: how the pipeline deals the
stream's epochs (batches per epoch, epochs served), asked on ``superflow/<run>/schedule``.

The pipeline answers from a thread of its own, even while its publisher waits on a full
subscriber queue, so asking leaves the batch queue alone. An answer belongs to the
pipeline process (publisher) named in it: a batch of another publisher (a restarted
pipeline) is asked about again.
"""

from __future__ import annotations

import time
import warnings
from collections.abc import Callable
from typing import Any

import iceoryx2 as iox2

from .errors import PipelineTimeout, ScheduleUnavailable, SuperflowError
from .wire import (
    MAX_NODES,
    MAX_PUBLISHERS,
    MAX_SUBSCRIBERS,
    REFUSALS,
    Schedule,
    ScheduleReply,
    ScheduleRequest,
)

# How long a stream waits for the schedule of a pipeline that publishes (it answers from
# a thread of its own, within milliseconds); one that does not answer by then has no
# schedule service (an older pipeline, or one whose service failed to start).
SCHEDULE_WAIT_S = 5.0


class ScheduleClient:
    """One stream's schedule requests and the answer kept (``known``). ``attached`` says
    whether a pipeline publishes on the stream; the client port is opened at the first
    request and kept."""

    def __init__(self, node: Any, run: str, service: str, rank: int | None,
                 attached: Callable[[], bool]):
        self._node = node
        self.run = run
        self.service = service
        self.rank = rank
        self._attached = attached
        self._client: Any = None  # (request-response service, client port)
        self.known: Schedule | None = None
        self._missing: set[int] = set()  # publishers that did not answer

    def require(self, timeout_s: float | None) -> Schedule:
        """The schedule: the one kept, else asked. While no pipeline publishes it waits
        for one up to ``timeout_s`` (None: as long as it takes), then raises
        :class:`PipelineTimeout`; a pipeline that publishes but does not answer within
        :data:`SCHEDULE_WAIT_S` raises :class:`ScheduleUnavailable`."""
        if self.known is not None:
            return self.known
        deadline = None if timeout_s is None else time.monotonic() + timeout_s
        schedule = self.ask(deadline, SCHEDULE_WAIT_S)
        if schedule is not None:
            return schedule
        if self._attached():
            raise ScheduleUnavailable(
                f"run {self.run!r}: the pipeline publishing {self.service!r} did not answer "
                f"the schedule request on 'superflow/{self.run}/schedule' within "
                f"{SCHEDULE_WAIT_S:.0f} s (an older pipeline, or its schedule service failed "
                "to start: see its log), so the stream cannot know where epochs end; iterate "
                "the stream itself (`for batch in stream`) and count steps instead",
                self.run, self.service)
        raise PipelineTimeout(f"run {self.run!r}: no pipeline answered the schedule request "
                              f"of {self.service!r} within {timeout_s} s (no pipeline publishes "
                              "on it)", self.run, self.service)

    def of(self, publisher: int) -> Schedule | None:
        """The schedule of ``publisher``'s batches, asked when the one kept is another
        publisher's; None when that publisher does not answer (warned about once, and not
        asked again)."""
        schedule = self.known
        if schedule is not None and schedule.publisher == publisher:
            return schedule
        if publisher in self._missing:
            return None
        schedule = self.ask(time.monotonic() + SCHEDULE_WAIT_S)
        if schedule is None:
            self._missing.add(publisher)
            # stacklevel: the code that called Stream.next (through Stream._mark).
            warnings.warn(f"run {self.run!r}: the pipeline publishing {self.service!r} "
                          "did not say how its epochs are scheduled: the stream will "
                          "not end by itself", RuntimeWarning, stacklevel=4)
        return schedule

    def ask(self, deadline: float | None, patience_s: float | None = None) -> Schedule | None:
        """Asks the pipeline for the stream's schedule; None when none answers by
        ``deadline``, or (``patience_s``) when a pipeline has been publishing for that
        long without answering. The answer is kept (it belongs to the publisher named in
        it)."""
        try:
            if self._client is None:
                service = (
                    self._node.service_builder(
                        iox2.ServiceName.new(f"superflow/{self.run}/schedule"))
                    .request_response(ScheduleRequest, ScheduleReply)
                    .max_clients(MAX_SUBSCRIBERS * 4)
                    .max_servers(MAX_PUBLISHERS)
                    .max_nodes(MAX_NODES * 2)
                    .open_or_create()
                )
                self._client = (service, service.client_builder().create())
        except Exception as e:
            raise SuperflowError(f"run {self.run!r}: opening its schedule service "
                                 f"'superflow/{self.run}/schedule' (a pipeline of another "
                                 f"superflow version?): {e}", self.run, self.service) from e
        client = self._client[1]
        request = ScheduleRequest(rank=self.rank or 0, broadcast=int(self.rank is None))
        attached_since = None
        while True:
            # A fresh client may not be connected to the server yet: resend until one
            # answers.
            pending = client.send_copy(request)
            attempt = time.monotonic()
            while time.monotonic() - attempt < 0.5:
                response = pending.receive()
                if response is not None:
                    reply = ScheduleReply.from_buffer_copy(response.payload().contents)
                    response.delete()
                    if not reply.known:
                        raise SuperflowError(
                            f"run {self.run!r}: the pipeline has no stream {self.service!r} "
                            f"({REFUSALS[1]})", self.run, self.service)
                    self.known = Schedule.of(reply)
                    return self.known
                if deadline is not None and time.monotonic() >= deadline:
                    return None
                time.sleep(0.005)
            if patience_s is not None:
                now = time.monotonic()
                if attached_since is None and self._attached():
                    attached_since = attempt
                if attached_since is not None and now - attached_since >= patience_s:
                    return None

    def forget(self) -> None:
        """Drops the schedule kept: the next request asks again (after a resume, which
        may make the pipeline deal the epoch differently)."""
        self.known = None

    def close(self) -> None:
        """Leaves the schedule service (the schedule kept stays)."""
        if self._client is not None:
            self._client[1].delete()
            self._client = None
