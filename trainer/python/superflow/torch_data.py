"""PyTorch glue: a ``torch.utils.data.IterableDataset`` over a :class:`superflow.Stream`.

The pipeline already batches, shuffles, shards and augments, so the dataset yields whole
batches: use it with ``DataLoader(dataset, batch_size=None)`` and no workers. The
pipeline is the worker pool: a worker process would only add a copy of every batch
(torch moves what a worker returns into new shared memory, and the batch is in shared
memory already), so iterating in a worker raises :class:`WorkersUnsupported` and
pickling the dataset (spawn, forkserver) raises :class:`StreamNotPicklable`. Each
``iter()`` is one epoch, as with a map-style dataset.
"""

from __future__ import annotations

from collections.abc import Callable, Iterator
from typing import Any

from .batch import Batch
from .errors import StreamNotPicklable, WorkersUnsupported
from .stream import Stream

try:
    from torch.utils.data import IterableDataset as _Base
    from torch.utils.data import get_worker_info
except ImportError:  # torch is optional: TorchIterable then fails when constructed
    _Base = object  # type: ignore[assignment,misc]

_WORKERS = ("superflow.TorchIterable in a DataLoader worker (num_workers={n}): the pipeline "
            "already is the worker pool (it decodes, builds and batches on its own cores), and "
            "a worker would only copy each batch out of the shared memory into torch's. Use "
            "DataLoader(dataset, batch_size=None, num_workers=0); more speed comes from the "
            "pipeline's --threads")


class TorchIterable(_Base):  # type: ignore[type-arg]
    """One epoch of ``stream`` per ``iter()``: yields ``transform(batch)`` for this rank's
    batches of the current epoch (``stream.epoch()``), by default ``batch.torch()``, a
    dict of tensors sharing the batch's memory (``{}`` for a lost batch: every sample
    failed in the pipeline; it is still yielded so every rank counts it). ``len()`` is
    the epoch's batch count; past the pipeline's last epoch an ``iter()`` yields nothing.
    ``set_epoch(e)`` follows ``DistributedSampler``: start at epoch ``e`` (a resume;
    nothing when the stream is at ``e`` already, so ``iter()`` continues the current
    epoch). The batch is released when the next one is requested; a tensor kept longer
    keeps its batch's memory (the stream's ``max_held``), so copy what you keep
    (``tensor.to(device)``). With ``torch.distributed`` initialized, the first ``iter()``
    checks that every rank is served the same plan (``Stream.check_plan``; a collective:
    ``check_plan=False`` to skip)."""

    def __init__(self, stream: Stream, transform: Callable[[Batch], Any] | None = None,
                 drop_uneven: bool = False, check_plan: bool = True):
        if _Base is object:
            raise ImportError("superflow.TorchIterable needs torch (pip install superflow[torch])")
        super().__init__()
        self.stream = stream
        self.transform = transform if transform is not None else Batch.torch
        self.drop_uneven = drop_uneven
        self._check_plan = check_plan

    def __iter__(self) -> Iterator[Any]:
        worker = get_worker_info()
        if worker is not None:
            raise WorkersUnsupported(_WORKERS.format(n=worker.num_workers),
                                     self.stream.run, self.stream.service)
        if self._check_plan:
            self._check_plan = False
            self.stream.check_plan()
        for batch in self.stream.epoch(self.drop_uneven):
            yield self.transform(batch)

    def __len__(self) -> int:
        return len(self.stream.epoch(self.drop_uneven))

    def __reduce__(self) -> Any:
        raise StreamNotPicklable(
            "superflow.TorchIterable cannot be pickled (a DataLoader with num_workers > 0 under "
            "spawn or forkserver, the default from Python 3.14, pickles its dataset): "
            + _WORKERS.format(n="> 0"), self.stream.run, self.stream.service)

    def state_dict(self) -> dict[str, int]:
        """The stream's ``state_dict()``: where the whole job stands (save it with the
        model; ``load_state_dict`` resumes there on any number of ranks)."""
        return self.stream.state_dict()

    def load_state_dict(self, state: dict[str, int]) -> None:
        """Continues where a ``state_dict()`` (of a job of any size) stopped."""
        self.stream.load_state_dict(state)

    def set_epoch(self, epoch: int) -> None:
        """Starts the next ``iter()`` at epoch ``epoch`` (a fresh stream is taken to be at
        epoch 0, where a pipeline starts)."""
        at = self.stream.position()
        if (0 if at is None else at[0]) != epoch:
            self.stream.resume(epoch, 0)
