"""PyTorch glue: a ``torch.utils.data.IterableDataset`` over a :class:`superflow.Stream`.

The pipeline already batches, shuffles, shards and augments, so the dataset yields whole
batches: use it with ``DataLoader(dataset, batch_size=None)`` and no workers (the batch
is in shared memory already; a worker process would copy it through a pipe).
"""

from __future__ import annotations

from typing import Any, Callable, Iterator

from .stream import Batch, Stream

try:
    from torch.utils.data import IterableDataset as _Base
except ImportError:  # torch is optional: TorchIterable then fails when constructed
    _Base = object  # type: ignore[assignment,misc]


class TorchIterable(_Base):  # type: ignore[valid-type,misc]
    """Yields ``transform(batch)`` for every batch of ``stream``; by default
    ``batch.torch()``, a dict of tensors sharing the batch's shared memory. The batch is
    released when the next one is requested, so move or copy what you keep
    (``tensor.to(device)`` copies)."""

    def __init__(self, stream: Stream, transform: Callable[[Batch], Any] | None = None):
        if _Base is object:
            raise ImportError("superflow.TorchIterable needs torch (pip install superflow[torch])")
        super().__init__()
        self.stream = stream
        self.transform = transform if transform is not None else Batch.torch

    def __iter__(self) -> Iterator[Any]:
        for batch in self.stream:
            yield self.transform(batch)
