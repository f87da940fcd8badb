"""The errors of the ``superflow`` package. Each names the run and the iceoryx2 service
where it happened (``run``, ``service``)."""

from __future__ import annotations


class SuperflowError(Exception):
    """An error of a stream; ``run`` and ``service`` name where it happened."""

    def __init__(self, message: str, run: str = "", service: str = ""):
        super().__init__(message)
        self.run = run
        self.service = service


class PipelineTimeout(SuperflowError, TimeoutError):
    """No batch arrived within the stream's ``timeout_s``."""


class ScheduleUnavailable(SuperflowError, TimeoutError):
    """The pipeline publishing the stream did not answer the schedule request (how many
    batches an epoch has, how many epochs): ``len(stream.epoch())`` and ``stream.epoch()``
    cannot know where epochs end."""


class MalformedBatch(SuperflowError, ValueError):
    """A received batch breaks the batch format (the message names the rule and section)."""


class FormatVersionMismatch(MalformedBatch):
    """A received batch was written in another version of the batch format."""

    def __init__(self, message: str, run: str = "", service: str = "", version: int = 0):
        super().__init__(message, run, service)
        self.version = version


class BatchReleased(SuperflowError, RuntimeError):
    """A released batch was asked for a section (``batch[name]``, ``batch.torch()``).
    Views taken before the release stay valid."""


class TooManyBatchesHeld(SuperflowError, RuntimeError):
    """Receiving another batch would hold more than the stream's ``max_held``: released
    batches whose views are still alive keep their shared memory. ``held`` lists their
    ``(epoch, step)``."""

    def __init__(self, message: str, run: str = "", service: str = "",
                 held: list[tuple[int, int]] | None = None):
        super().__init__(message, run, service)
        self.held = [] if held is None else held


class ResumeRefused(SuperflowError):
    """The pipeline refused to move the stream (no such stream, a position past the end,
    or a step saved by a job of another size)."""


class RunComplete(ResumeRefused):
    """A resume at or past the end of the pipeline's last epoch (a final checkpoint):
    the run is complete, nothing is left to serve. ``epochs`` is the run's epoch count."""

    def __init__(self, message: str, run: str = "", service: str = "", epochs: int = 0):
        super().__init__(message, run, service)
        self.epochs = epochs


class PlanMismatch(SuperflowError, RuntimeError):
    """The ranks of a job are served different plans (the pipelines of its hosts were
    given other drives, seeds or configurations, or two hosts run the same
    ``--host-rank``)."""


class WorkersUnsupported(SuperflowError, RuntimeError):
    """A ``superflow.TorchIterable`` iterated in a ``DataLoader`` worker process
    (``num_workers > 0``): the pipeline is the worker pool; use ``num_workers=0``."""


class StreamNotPicklable(SuperflowError, TypeError):
    """A ``Stream`` (or a ``TorchIterable`` holding one) was pickled, as ``spawn`` and
    ``forkserver`` processes do: its shared-memory ports belong to this process."""
